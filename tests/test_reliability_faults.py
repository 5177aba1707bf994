"""Process faults and overload on a live replica run (tools/fault_inject, real processes over real Zenoh).

Reduced form: SIGKILL depth, mapping, backend in turn (player at 0.5 x sensor time). ``SIGMASLAM_E2E=full``:
also the frontend, and longer windows. The overload case runs the pipeline twice, depth at its normal cost
and depth 6x over its 100 ms budget (``depth.inject_delay_ms``), and compares the estimator.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from helpers_zenoh import REPO

FULL = os.environ.get("SIGMASLAM_E2E", "") == "full"
WINDOW = "4" if FULL else "3"


def _replica() -> str:
    from services.app.synth.api import ensure_default_replica

    return str(ensure_default_replica())


def _inject(out, *args: str, timeout: float = 600.0):
    cmd = [sys.executable, "-m", "tools.fault_inject", _replica(), "--out", str(out), "--window-s", WINDOW, *args]
    with open(out.parent / f"{out.name}.log", "w") as log:
        proc = subprocess.run(cmd, cwd=REPO, stdout=log, stderr=subprocess.STDOUT, timeout=timeout)
    text = (out.parent / f"{out.name}.log").read_text()
    report = json.loads((out / "faults.json").read_text())
    assert report.get("started"), text[-3000:]
    return proc.returncode, report, text


@pytest.mark.e2e
def test_sigkill_each_service_is_restarted_and_the_estimator_keeps_its_rate(tmp_path):
    kill = ["depth", "mapping", "frontend", "backend"] if FULL else ["depth", "mapping", "backend"]
    rate = 0.3 if FULL else 0.5  # x sensor time: 20 Hz frames -> 6 or 10 Hz; the 25 s replica outlasts the kills
    rc, rep, text = _inject(tmp_path / "faults", "--kill", ",".join(kill), "--rate", str(rate))
    assert rc == 0, text[-3000:]
    base = rep["baseline"]["rate_hz"]
    assert base > 0.5 * 20 * rate, rep["baseline"]
    by = {f["service"]: f for f in rep["faults"]}
    for name in kill:
        f = by[name]
        assert f["restarted"] and f["new_pid"] != f["old_pid"], f
        assert rep["restarts"][name] == 1
    for name in ("depth", "mapping", "backend"):  # states keep coming, tracking (without the back end: the fast path
        # against its last window)
        down = by[name]["while_down"]
        assert down["rate_hz"] >= 0.6 * base, (name, down, base)
        # a back end restarted within the window already said 'reset' and re-initialised in it
        allowed = {"tracking", "reset", "initialising"} if name == "backend" else {"tracking"}
        assert "tracking" in down["statuses"] and set(down["statuses"]) <= allowed, down
    # the mapper resumed from its checkpoint rather than starting an empty map
    assert "mapping: resumed" in text
    be = by["backend"]
    assert be["reset_seen"], be  # the restarted back end's history starts anew, and consumers are told
    assert be["tracking_again_s"] is not None, be
    assert by["backend"]["after"]["rate_hz"] >= 0.5 * base, be


@pytest.mark.e2e
def test_depth_overload_does_not_slow_the_estimator(tmp_path):
    _, normal, t1 = _inject(tmp_path / "normal", "--rate", "0.5")
    _, slow, t2 = _inject(tmp_path / "slow", "--rate", "0.5", "--set", "depth.inject_delay_ms=600")
    for rep, text in ((normal, t1), (slow, t2)):
        assert rep["measure"]["states"] > 0, text[-3000:]
    a, b = normal["measure"], slow["measure"]
    assert b["rate_hz"] >= 0.8 * a["rate_hz"], (a, b)
    assert b["latency_p50_ms"] <= max(2.0 * a["latency_p50_ms"], a["latency_p50_ms"] + 30.0), (a, b)
    # the depth service is 6x over budget: it counts its overruns and the frames it had to drop
    d = slow["stages"]["depth"]["depth"]
    assert d["overruns"] >= 1 and d["p50_ms"] >= 600.0, d
    assert slow["queues"]["depth"]["sensors/frame"]["dropped"] > normal["queues"]["depth"]["sensors/frame"]["dropped"]


@pytest.mark.e2e
@pytest.mark.skipif(not FULL, reason="long form only (SIGMASLAM_E2E=full): the recorder writes ~15 MB/s of images")
def test_sigkill_viewer_and_recorder(tmp_path):
    """The viewer serves its page again after a restart; the recorder's cut file is kept beside the new one and
    rebuilds with --recover."""
    from services.app.cli import main as cli_main
    from services.recorder.mcap_reader import read_recording

    out = tmp_path / "vr"
    rc, rep, text = _inject(out, "--with", "viewer,recorder", "--kill", "viewer,recorder", "--rate", "0.5",
                            "--set", "recorder.foxglove=false")
    assert rc == 0, text[-3000:]
    by = {f["service"]: f for f in rep["faults"]}
    assert by["viewer"]["restarted"] and by["viewer"]["http_ok"], by["viewer"]
    assert by["recorder"]["restarted"] and by["recorder"]["recordings"] == ["recording.1.mcap", "recording.mcap"]
    fixed = tmp_path / "fixed.mcap"
    assert cli_main(["record", "--recover", str(out / "recording.mcap"), "--out", str(fixed)]) == 0
    assert sum(1 for _ in read_recording(fixed)) > 100
    for p in (out / "recording.mcap", out / "recording.1.mcap", fixed):
        p.unlink()


@pytest.mark.e2e
def test_a_restarted_back_end_relocalises_in_its_runs_saved_map(tmp_path):
    """With loop closure on, the back end checkpoints its sparse map (DIR/map/sparse.npz); killed mid-run, the
    restarted one loads it, relocalises and publishes in the run's frame again: every pose published in 'W' over the
    whole run fits the ground truth under one alignment."""
    # 0.3 x sensor time and a checkpoint every 2 s (sensor time): the kill comes ~4 s into the replica, just after the
    # first checkpoint, while the drone takes off, and a restart (5-7 s of wall time on 2 busy cores) ends ~1.5-2 s
    # later where the saved map can place it. At 0.5 x the restart ended ~3.5 s later in the replica's fast crossing
    # of the room (1.3 m/s, 9-12 s), away from everything mapped, and relocalisation waited for the drone's return
    # at ~23 s: after the end of the measurement (stop 53).
    rc, rep, text = _inject(tmp_path / "resume", "--kill", "backend", "--rate", "0.3", "--kill-after-s", "10",
                            "--set", "loop.enabled=true", "--set", "loop.map_checkpoint_period_s=2")
    assert rc == 0, text[-3000:]
    be = rep["faults"][0]
    assert be["reset_seen"] and "relocalising in this run's last saved map" in text, text[-3000:]
    assert be["relocalised_s"] is not None, (be, text[-3000:])
    ate = rep["ate_one_alignment"]
    # aligned ~3 s (sensor time) after the restart; the measurement window that follows (3 s of wall time at 6 Hz)
    # holds ~25 states in 'W' after the restart
    assert ate["after_backend_restart"]["matched"] >= 12, ate
    # one frame: a new world frame would be off by the metres flown since the start. The restarted back end starts
    # in flight and its window is turned to the gravity it measures (gravity_align.py): 1.9 cm after the restart,
    # 0.9 cm over the whole run (stop 53; before that turn: 8-12 cm and 4-6 cm; docs/maps.md)
    assert ate["rmse_m"] < 0.05 and ate["after_backend_restart"]["rmse_m"] < 0.08, ate
