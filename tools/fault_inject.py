"""Fault injection on a live pipeline: SIGKILL services in turn, or overload one, and measure the estimator.

    python -m tools.fault_inject DATASET --out DIR [--kill depth,mapping,backend] [--rate 0.5] [--set k=v ...]

Runs player (``--rate`` x sensor time), frontend, backend, depth (SGBM unless ``--set depth.method=network``)
and mapping (``--out DIR``, checkpoints every 2 s) under :class:`services.app.supervisor.Supervisor` with restart
'on-failure', on a private router and namespace. This process listens to estimator/state, sensors/frame,
heartbeats and stats. Once the estimator tracks, it measures a baseline window, then for each service in
``--kill``: SIGKILL its process, measure the estimator/state rate and latency while it is down, wait for a
heartbeat from the new process (a new pid), and one more window. Writes ``DIR/faults.json`` and prints one
line per fault. With no ``--kill`` it just measures (the overload case: ``--set depth.inject_delay_ms=500``).

Latency = arrival of an estimator/state here - arrival of the sensors/frame with the same stamp here.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import threading
import time
import uuid
from pathlib import Path

import numpy as np

from services.app.cli import command_names
from services.app.run_outputs import find_ground_truth
from services.app.supervisor import ServiceSpec, Supervisor, validate
from services.app.system_config import load_system_config
from shared import topics
from shared.config import override, to_yaml
from transport.node import Node
from transport.session import free_local_port

PIPELINE = ("frontend", "backend", "depth", "mapping")
OPTIONAL = ("viewer", "recorder")  # started with --with; the viewer on a free port, the recorder to DIR/recording.mcap


class Probe:
    """What this process sees on the bus, with arrival times (filled from Zenoh threads)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.states: list[tuple[float, int, str]] = []  # (arrival, stamp, status)
        self.poses: dict[int, tuple[np.ndarray, str]] = {}  # stamp -> (position, header.frame_id) of posed states
        self.frame_arrival: dict[int, float] = {}
        self.heartbeats: dict[str, tuple[float, int]] = {}  # service -> (arrival, pid) of the newest
        self.stats: dict[str, object] = {}

    def on_state(self, m) -> None:
        with self.lock:
            self.states.append((time.monotonic(), int(m.header.stamp_ns), m.status))
            if m.status not in ("initialising", "reset"):
                self.poses[int(m.header.stamp_ns)] = (np.array(m.T_WS)[:3, 3], m.header.frame_id)

    def one_frame_ate(self, gt_path: Path, bounds_ns: dict[str, tuple[int, int]] = {}) -> dict | None:
        """ATE (SE(3), one alignment) of every posed state published in the main frame ('W': not the temporary
        frame of a back end that has not relocalised yet), and with that alignment the RMSE of each named span of
        stamps in ``bounds_ns`` (e.g. before the first kill, after it)."""
        from shared.euroc import read_trajectory
        from shared.map_folder import UNALIGNED_FRAME
        from shared.metrics.ate import compute_ate

        with self.lock:
            items = sorted((st, p) for st, (p, f) in self.poses.items() if f != UNALIGNED_FRAME)
        if len(items) < 10:
            return None
        gt = read_trajectory(gt_path)
        res = compute_ate(gt.stamps_ns, gt.p_WS, np.array([i[0] for i in items]), np.array([i[1] for i in items]))
        out = {"rmse_m": res.rmse_m, "max_m": res.max_m, "matched": res.matched}
        for name, (lo, hi) in bounds_ns.items():
            e = res.errors_m[(res.stamps_ns >= lo) & (res.stamps_ns < hi)]
            out[name] = {"rmse_m": float(np.sqrt(np.mean(e ** 2))) if len(e) else None,
                         "max_m": float(e.max()) if len(e) else None, "matched": int(len(e))}
        return out

    def on_frame(self, m) -> None:
        with self.lock:
            self.frame_arrival[int(m.header.stamp_ns)] = time.monotonic()

    def on_heartbeat(self, m) -> None:
        if m.state == "running":
            with self.lock:
                self.heartbeats[m.service] = (time.monotonic(), int(m.pid))

    def on_stats(self, m) -> None:
        with self.lock:
            self.stats[m.service] = m

    def window(self, t0: float, t1: float) -> dict:
        """State rate and latency over arrivals in [t0, t1)."""
        with self.lock:
            sel = [s for s in self.states if t0 <= s[0] < t1]
            lat = [1e3 * (a - self.frame_arrival[st]) for a, st, _ in sel if st in self.frame_arrival]
        tracking = [s for s in sel if s[2] in ("tracking", "imu_only")]
        return {"t0": t0, "t1": t1, "states": len(sel), "rate_hz": len(sel) / max(t1 - t0, 1e-9),
                "tracking_rate_hz": len(tracking) / max(t1 - t0, 1e-9),
                "latency_p50_ms": float(np.median(lat)) if lat else None,
                "latency_p99_ms": float(np.percentile(lat, 99)) if lat else None,
                "statuses": sorted({s[2] for s in sel})}

    def queue_drops(self) -> dict:
        with self.lock:
            return {name: {q: {"received": int(s.queue_received[k]), "dropped": int(s.queue_dropped[k])}
                           for k, q in enumerate(s.queue_names)} for name, s in self.stats.items()}

    def stages(self) -> dict:
        with self.lock:
            return {name: {st: {"count": int(s.stage_count[k]), "p50_ms": float(s.stage_p50_ms[k]),
                                "overruns": int(s.stage_overruns[k])} for k, st in enumerate(s.stage_names)}
                    for name, s in self.stats.items()}


def build(dataset: str, out: Path, rate: float, sets: list[str], nice: int = 10, extra: tuple[str, ...] = ()):
    port = free_local_port()
    overrides = [f"transport.namespace=sigmaslam/faults-{uuid.uuid4().hex[:8]}", f"transport.connect=[tcp/127.0.0.1:{port}]",
                 f"transport.router_listen=[tcp/127.0.0.1:{port}]", "depth.method=sgbm", "depth.rate_hz=5",
                 "mapping.depth_topic=depth/stereo", "mapping.checkpoint_period_s=2", "loop.enabled=false",
                 "transport.stats_period_s=0.5", f"viewer.port={free_local_port()}", f"loop.map_output={out.resolve()}",
                 "loop.map_checkpoint_period_s=2", *sets]
    spec = dict(restart="on-failure", max_restarts=5, window_s=120.0, backoff_s=0.2)
    services = [ServiceSpec(name="frontend", argv=["frontend"], **spec),
                ServiceSpec(name="backend", argv=["backend"], **spec),
                ServiceSpec(name="depth", argv=["depth"], nice=nice, **spec),
                ServiceSpec(name="mapping", argv=["mapping", "--out", str(out)], nice=nice, **spec),
                ServiceSpec(name="player", argv=["player", dataset, "--rate", f"{rate:g}",
                                                 "--wait-for", ",".join(PIPELINE + tuple(extra))], restart="never")]
    if "viewer" in extra:
        services.insert(0, ServiceSpec(name="viewer", argv=["viewer"], nice=nice, **spec))
    if "recorder" in extra:
        services.insert(0, ServiceSpec(name="recorder", argv=["record", "--out", str(out / "recording.mcap")], **spec))
    cfg = override(load_system_config(None, overrides), {"rig.calibration": dataset, "supervisor.services": services,
                                                         "supervisor.start_router": True})
    validate(cfg.supervisor, command_names())
    path = (out / "config.yaml").resolve()
    path.write_text(to_yaml(cfg))
    return cfg, path


def wait_until(pred, timeout_s: float, step: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step)
    return bool(pred())


def run(dataset: str, out: Path, kill: list[str], rate: float, window_s: float, sets: list[str],
        restart_timeout_s: float = 90.0, start_timeout_s: float = 180.0, during=None, extra: tuple[str, ...] = (),
        kill_after_s: float = 0.0) -> dict:
    """``during(node, probe) -> dict``, if given, is called after the baseline window (e.g. to publish bad
    input); its result goes into the report under 'during', then a 'measure' window follows."""
    out.mkdir(parents=True, exist_ok=True)
    cfg, config_path = build(dataset, out, rate, sets, extra=tuple(extra))
    report_extra = {"viewer_port": cfg.viewer.port} if "viewer" in extra else {}
    sup = Supervisor(cfg.supervisor, config_path, out.resolve())
    probe = Probe()
    report: dict = {"dataset": dataset, "rate": rate, "window_s": window_s, "sets": sets, "faults": [], **report_extra}
    with Node("faults", cfg.transport) as node:
        node.subscriber(topics.STATE, policy="all", depth=100_000, handler=probe.on_state)
        node.subscriber(topics.FRAME, handler=probe.on_frame)
        node.subscriber(topics.HEARTBEAT, key="heartbeat/*", handler=probe.on_heartbeat)
        node.subscriber(topics.STATS, key="stats/*", handler=probe.on_stats)
        th = threading.Thread(target=sup.run, name="supervisor", daemon=True)
        th.start()
        try:
            ok = wait_until(lambda: any(s[2] == "tracking" for s in probe.states), start_timeout_s)
            report["started"] = ok
            if not ok:
                report["error"] = "the estimator never tracked"
                return report
            t = time.monotonic()
            time.sleep(window_s)
            report["baseline"] = probe.window(t, t + window_s)
            print(f"[faults] baseline: {report['baseline']['rate_hz']:.1f} states/s, latency p50 "
                  f"{report['baseline']['latency_p50_ms']} ms", flush=True)
            if kill and kill_after_s > 0:
                time.sleep(kill_after_s)
            for name in kill:
                report["faults"].append(_kill_one(sup, probe, name, out, window_s, restart_timeout_s))
            if during is not None:
                report["during"] = during(node, probe)
            if not kill:  # overload/measure only: a second window
                t = time.monotonic()
                time.sleep(window_s)
                report["measure"] = probe.window(t, t + window_s)
        finally:
            time.sleep(1.0)  # one more stats period
            report["queues"] = probe.queue_drops()
            report["stages"] = probe.stages()
            report["restarts"] = {c.spec.name: c.tracker.total_restarts for c in sup.children}
            gt = find_ground_truth(Path(dataset))
            if gt is not None:  # the whole run in one frame? one alignment over every state in 'W'
                big = 1 << 62
                spans = {"before_first_kill": (-big, min(f["kill_stamp_ns"] for f in report["faults"]))} if report["faults"] else {}
                for f in report["faults"]:
                    if f.get("restart_stamp_ns") is not None:
                        spans[f"{f['service']}_down"] = (f["kill_stamp_ns"], f["restart_stamp_ns"])
                        spans[f"after_{f['service']}_restart"] = (f["restart_stamp_ns"], big)
                report["ate_one_alignment"] = probe.one_frame_ate(gt, spans)
            with probe.lock:  # every posed state, for plots: stamp, position, frame
                st = sorted(probe.poses)
                np.savez(out / "states.npz", stamps_ns=np.array(st, np.int64),
                         p=np.array([probe.poses[k][0] for k in st]).reshape(-1, 3),
                         frame_id=np.array([probe.poses[k][1] for k in st]))
            sup.request_stop()
            th.join(timeout=cfg.supervisor.longest_stop_s() + cfg.supervisor.shutdown_timeout_s + 10)
    (out / "faults.json").write_text(json.dumps(report, indent=1))
    return report


def _kill_one(sup: Supervisor, probe: Probe, name: str, out: Path, window_s: float, restart_timeout_s: float) -> dict:
    child = next(c for c in sup.children if c.spec.name == name)
    if name == "mapping":  # kill it only once it has saved a checkpoint to resume from
        wait_until(lambda: (out / "map" / "dense.npz").exists(), 30.0)
    if name == "backend" and load_system_config(sup.config_path).loop.enabled:  # likewise its sparse map (with
        # loop closure off the back end saves none and cannot relocalise)
        wait_until(lambda: (out / "map" / "sparse.npz").exists(), 60.0)
    old_pid = child.proc.pid
    t_kill = time.monotonic()
    with probe.lock:
        kill_stamp = probe.states[-1][1] if probe.states else -1  # the newest frame time when it was killed
    os.kill(old_pid, signal.SIGKILL)
    time.sleep(window_s)
    down = probe.window(t_kill, t_kill + window_s)
    back = wait_until(lambda: probe.heartbeats.get(name, (0, old_pid))[1] != old_pid, restart_timeout_s)
    t_back = probe.heartbeats.get(name, (None,))[0]
    res = {"service": name, "old_pid": old_pid, "kill_stamp_ns": int(kill_stamp), "new_pid": probe.heartbeats.get(name, (0, None))[1] if back else None,
           "restarted": back, "restart_s": (t_back - t_kill) if back else None, "while_down": down}
    if back and name == "backend":
        # while the back end is down the fast path (in the frontend process) goes on against its last window; the restarted back
        # end's first window says 'reset' (one 'reset' state), then it re-initialises and states are 'tracking'
        def tracking_after_reset(states) -> list:
            resets = [s[0] for s in states if s[0] > t_kill and s[2] == "reset"]
            return [s[0] for s in states if resets and s[0] > resets[0] and s[2] == "tracking"]

        wait_until(lambda: bool(tracking_after_reset(probe.states)), restart_timeout_s)
        with probe.lock:
            after = [s for s in probe.states if s[0] > t_kill]
        res["first_status_after_restart"] = after[0][2] if after else None
        res["reset_seen"] = any(s[2] == "reset" for s in after)
        res["restart_stamp_ns"] = next((s[1] for s in after if s[2] == "reset"), None)  # the new back end's first
        tr = tracking_after_reset(after)
        res["tracking_again_s"] = (tr[0] - t_kill) if tr else None
        # with loop closure, the restarted back end relocalises in its run's last saved map: states in 'W' again
        from shared.map_folder import UNALIGNED_FRAME

        def back_in_frame() -> list:
            with probe.lock:
                after = sorted(st for st, (_, f) in probe.poses.items() if st > res["kill_stamp_ns"])
                odom = [st for st in after if probe.poses[st][1] == UNALIGNED_FRAME]
                return [st for st in after if odom and st > odom[0] and probe.poses[st][1] != UNALIGNED_FRAME]

        if load_system_config(sup.config_path).loop.enabled and wait_until(lambda: bool(back_in_frame()),
                                                                         restart_timeout_s):
            st = back_in_frame()[0]
            with probe.lock:
                arrival = next(a for a, s2, _ in probe.states if s2 == st)
            res["relocalised_s"] = arrival - t_kill  # from the kill to the first state in the old frame again
        else:
            res["relocalised_s"] = None
    if back and name == "viewer":  # the restarted viewer serves its page again on the same port
        res["http_ok"] = wait_until(lambda: _http_ok(port), 30.0, 0.5) if (port := sup_port(sup)) else None
    if name == "recorder":
        res["recordings"] = sorted(p.name for p in out.glob("recording*.mcap"))
    t = time.monotonic()
    time.sleep(window_s)
    res["after"] = probe.window(t, t + window_s)
    print(f"[faults] SIGKILL {name} (pid {old_pid}): restarted={back} in {res['restart_s']} s; while down "
          f"{down['rate_hz']:.1f} states/s (tracking {down['tracking_rate_hz']:.1f}), latency p50 "
          f"{down['latency_p50_ms']} ms; after {res['after']['rate_hz']:.1f} states/s"
          + (f"; reset seen {res.get('reset_seen')}, tracking again after {res.get('tracking_again_s')} s, "
             f"in the old frame again after {res.get('relocalised_s')} s" if name == "backend" else ""), flush=True)
    return res


def sup_port(sup: Supervisor) -> int | None:
    """The viewer's port, from the config file the supervisor hands to its children."""
    from services.app.system_config import load_system_config as load

    return load(sup.config_path).viewer.port


def _http_ok(port: int) -> bool:
    import urllib.request

    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2.0) as r:
            return r.status == 200
    except OSError:
        return False


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dataset")
    p.add_argument("--out", required=True)
    p.add_argument("--kill", default="", help="comma-separated services to SIGKILL in turn (of %s)" % ",".join(PIPELINE + OPTIONAL))
    p.add_argument("--with", dest="extra", default="", help="also run these (of %s)" % ",".join(OPTIONAL))
    p.add_argument("--rate", type=float, default=0.5, help="player speed, x sensor time")
    p.add_argument("--window-s", type=float, default=3.0, help="measurement window [s]")
    p.add_argument("--kill-after-s", type=float, default=0.0, help="run this long after the baseline before the "
                   "first kill (a back end killed later has a larger saved map to relocalise in) [s]")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    a = p.parse_args(argv)
    kill = [k for k in a.kill.split(",") if k]
    extra = [k for k in a.extra.split(",") if k]
    bad = [k for k in kill if k not in PIPELINE + tuple(extra)] + [k for k in extra if k not in OPTIONAL]
    if bad:
        p.error(f"--kill/--with: unknown or not started services {bad}")
    rep = run(a.dataset, Path(a.out), kill, a.rate, a.window_s, a.set, extra=tuple(extra), kill_after_s=a.kill_after_s)
    print(json.dumps({k: rep.get(k) for k in ("baseline", "measure", "restarts")}, indent=1), flush=True)
    return 0 if rep.get("started") and all(f["restarted"] for f in rep["faults"]) else 1


if __name__ == "__main__":
    raise SystemExit(main())
