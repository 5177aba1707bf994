"""``sigmaslam eval ablation`` (services/app/eval/ablation.py): a short real run through the CLI entry (4 s of the 25 s
V1_02 replica, baseline + learned rows, depth at 2.5 Hz, mesh on), --resume, a rerun that gives the same
trajectories, and the table; each row is the pipeline's nodes on the in-process runner, and what makes a row is
config."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest

from services.app.cli import main
from services.app.eval.ablation_table import table_markdown


@pytest.mark.e2e
def test_short_ablation_writes_results_and_resume_skips_finished_rows(tmp_path, default_replica, capsys):
    out = tmp_path / "abl"
    argv = ["eval", "ablation", str(default_replica), "--rows", "baseline,learned", "--seconds", "4",
            "--set", "depth.rate_hz=2.5", "--out", str(out)]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    label = default_replica.name
    for row in ("baseline", "learned"):
        assert f"[eval ablation] {label} {row}: running" in printed and f"{label} {row}: done in" in printed
    res = json.loads((out / "ablation.json").read_text())["replicas"][label]
    assert set(res) == {"baseline", "learned"}
    for row, r in res.items():
        assert "error" not in r, r
        for key in ("ate_causal_m", "ate_noncausal_m", "accuracy_m", "accuracy_final_m", "backend_median_ms", "backend_p99_ms"):
            assert math.isfinite(r[key]) and r[key] >= 0, (row, key, r[key])
        assert r["ate_causal_m"] < 0.05 and r["ate_noncausal_m"] < 0.05, r  # a 4 s stretch tracks to cm
        assert 0 < r["completeness_5cm"] <= r["completeness"] <= 1
        # the depth node paces itself by stamps: 4 s at 2.5 Hz, every posed depth frame integrated by the mapping node
        assert 8 <= r["depth_frames"] <= 11 and r["depth_rate_hz"] == 2.5, r["depth_frames"]
        # (the first depth frame may come before the fast path has a pose: not mapped)
        assert r["depth_frames"] - 1 <= r["mapping_counts"]["integrated"] <= r["depth_frames"], r["mapping_counts"]
        assert r["mapping_counts"]["final_trajectories"] == 1  # the submaps followed the final trajectory
        assert (out / label / row / "trajectory_causal.txt").is_file()
        assert (out / label / row / "trajectory_final.txt").is_file()
        assert (out / label / f"{row}.log").is_file()
    assert "o2p_counts" not in res["baseline"]
    assert res["learned"]["o2p_counts"].get("frame_to_map", 0) > 0, res["learned"]["o2p_counts"]
    table = (out / "table.md").read_text()
    assert "| + learned sigma |" in table and "baseline (no dense terms)" in table
    assert f"- {label}: " in table and "causal ATE" in table

    # --resume: the finished row is read back, not run again (its result file is untouched)
    before = (out / label / "baseline.json").stat().st_mtime_ns
    assert main([*argv, "--resume"]) == 0  # the same settings: both rows read back
    printed = capsys.readouterr().out
    assert f"{label} baseline: done before" in printed and f"{label} learned: done before" in printed
    assert "running" not in printed
    assert (out / label / "baseline.json").stat().st_mtime_ns == before
    again = json.loads((out / "ablation.json").read_text())["replicas"][label]["baseline"]
    assert again["ate_causal_m"] == res["baseline"]["ate_causal_m"]

    # a second run of the same row (not resumed) gives the same trajectories to the bit: loop.synchronous (set by
    # eval ablation) takes the loop thread's timing out of the result
    rerun = tmp_path / "rerun"
    assert main(["eval", "ablation", str(default_replica), "--rows", "learned", "--seconds", "4", "--set",
                 "depth.rate_hz=2.5", "--no-mesh", "--out", str(rerun)]) == 0
    assert json.loads((rerun / label / "learned.json").read_text())["overrides"][0] == "loop.synchronous=true"
    for name in ("trajectory_causal.txt", "trajectory_final.txt"):
        assert (rerun / label / "learned" / name).read_bytes() == (out / label / "learned" / name).read_bytes(), name


@pytest.mark.e2e
def test_mono_row_runs_on_mvs_depth_or_fails_clearly_without_depth_mono(tmp_path, default_replica, capsys):
    from services.depth.config import DepthConfig

    out = tmp_path / "abl"
    # 6 s: MVS alone has no depth until keyframes with enough baseline are posed (the first ~3 s here)
    argv = ["eval", "ablation", str(default_replica), "--rows", "mono", "--seconds", "6", "--set", "depth.rate_hz=2.5",
            "--no-mesh", "--out", str(out)]
    if "mono" not in {f.name for f in dataclasses.fields(DepthConfig)}:
        assert main(argv) == 1
        r = json.loads((out / default_replica.name / "mono.json").read_text())
        assert "depth.mono" in r["error"]
        assert "failed: ValueError: this build has no monocular depth" in (out / "table.md").read_text()
        assert "row mono failed" in (out / default_replica.name / "mono.log").read_text()  # the traceback: row log only
        return
    assert main(argv) == 0, (out / default_replica.name / "mono.log").read_text()[-3000:]
    r = json.loads((out / default_replica.name / "mono.json").read_text())
    assert r["overrides"][-4:] == ["rig.cameras=[cam0]", "depth.mono=true", "depth.use_mvs=true", "o2p.enabled=true"]
    assert r["depth"]["stereo_weights"] == "-" and r["depth"]["mvs_weights"] != "-"  # MVS alone
    assert r["depth_frames"] > 0  # MVS depth reached the map once the first keyframes were posed
    assert math.isfinite(r["ate_causal_m"]) and r["ate_causal_m"] < 0.1, r


def test_table_marks_failed_rows_and_says_which_dense_rows_beat_the_baseline():
    rows = {"baseline": {"ate_causal_m": 0.010, "ate_noncausal_m": 0.008, "accuracy_m": 0.12, "accuracy_final_m": 0.11,
                         "completeness": 0.15,
                         "completeness_5cm": 0.05, "backend_median_ms": 10.0, "backend_p99_ms": 80.0, "wall_s": 60},
            "learned": {"ate_causal_m": 0.006, "o2p_counts": {"frame_to_map": 30, "map_to_map": 2}, "wall_s": 70},
            "fused": {"ate_causal_m": 0.012, "o2p_counts": {"frame_to_map": 28}, "wall_s": 90},
            "mono": {"error": "ValueError: no | mono", "wall_s": 0}}
    md = table_markdown({"V1_02": rows, "MH_04": {"learned": {"error": "boom"}}})
    lines = md.splitlines()
    assert lines[0].count("|") == lines[1].count("|") == lines[2].count("|")
    assert "| V1_02 | + learned sigma | 0.0060 | - |" in md and "| 30 / 2 |" in md and "| 28 / 0 |" in md
    assert "| V1_02 | baseline (no dense terms) | 0.0100 | 0.0080 | 0.120 / 0.110 | 15.0% | 5.0% | 10.0 / 80 | - | 60 |" in md
    assert "failed: ValueError: no / mono" in md  # a '|' in the reason does not break the table
    assert "- V1_02: dense rows beating the baseline's causal ATE (0.0100 m): learned 0.0060; not beating: fused 0.0120." in md
    assert "- MH_04: no baseline causal ATE to compare with." in md


def test_unknown_row_is_refused(tmp_path, capsys):
    assert main(["eval", "ablation", "V1_02", "--rows", "baseline,nope", "--out", str(tmp_path)]) == 2
    assert "unknown rows ['nope']" in capsys.readouterr().err


def test_rows_differ_by_config_alone():
    """Every row's keys load into the system config; the heuristic row asks the depth service for the heuristic
    stereo sigma of --heuristic-px pixels, the fused row maps the fused depth."""
    from services.app.system_config import load_system_config
    from services.app.eval.ablation import EVAL_DEFAULTS, row_overrides
    from services.app.eval.ablation_table import ROWS

    for row in ROWS:
        cfg = load_system_config(None, [*EVAL_DEFAULTS, *row_overrides(row, 2.5)])
        assert cfg.loop.synchronous
        assert cfg.o2p.enabled == (row in ("heuristic", "learned", "fused", "mono")), row
        assert cfg.depth.use_mvs == (row in ("fused", "mono", "mono_baseline")), row
        assert cfg.depth.stereo_sigma == ("heuristic" if row == "heuristic" else "network"), row
        assert cfg.mapping.depth_topic == ("depth/fused" if row == "fused" else "depth/stereo"), row
    heur = load_system_config(None, row_overrides("heuristic", 2.5)).depth
    assert heur.heuristic_sigma_model == "quadratic" and heur.heuristic_sigma_coeff == 2.5


def test_mono_row_is_judged_against_the_mono_baseline():
    from services.app.eval.ablation import row_overrides
    from services.app.eval.ablation_table import verdict

    assert row_overrides("mono_baseline")[-1] == "o2p.enabled=false" and row_overrides("mono")[-1] == "o2p.enabled=true"
    rows = {"baseline": {"ate_causal_m": 0.010}, "learned": {"ate_causal_m": 0.012},
            "mono_baseline": {"ate_causal_m": 0.30}, "mono": {"ate_causal_m": 0.25}}
    v = verdict("MH_04", rows)
    # mono (0.25 m) is worse than the stereo baseline but better than its own baseline: it counts as beating
    assert v == ("- MH_04: dense rows beating the baseline's causal ATE (0.0100 m): mono 0.2500 (vs mono_baseline 0.3000); "
                 "not beating: learned 0.0120."), v
    v = verdict("MH_04", {"mono_baseline": {"ate_causal_m": 0.30}, "mono": {"ate_causal_m": 0.35}})
    assert v == "- MH_04: dense rows beating their baseline's causal ATE: none; not beating: mono 0.3500 (vs mono_baseline 0.3000).", v
