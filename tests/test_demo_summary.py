"""The demo's closing summary: what a live run lost and how late its poses were, from the run's own files."""

import json

from services.app.demo_cmd import summary_lines


def test_summary_reports_lost_frames_latency_and_by_design_drops_apart(tmp_path):
    (tmp_path / "ate.json").write_text(json.dumps({"ate_rmse_m": 0.0139, "matched": 496,
                                                   "non_causal": {"ate_rmse_m": 0.012, "matched": 496}}))
    (tmp_path / "stats.json").write_text(json.dumps({
        "frames_sent": 501, "frames_without_state": 4,
        "state_latency_ms": {"n": 497, "median": 68.2, "p99": 361.0},
        "drops": {"frontend:sensors/frame": 4, "depth:sensors/frame": 436, "backend:frontend/frame": 188},
        "frontend_backend_median_ms": 31.4}))
    text = "\n".join(summary_lines(tmp_path, None, "http://127.0.0.1:8080"))
    assert "frames without a state              4 of 501" in text
    assert "p50 68 ms, p99 361 ms over 497 states" in text
    lost = next(line for line in text.splitlines() if line.startswith("frames lost by the estimator"))
    assert "frontend:sensors/frame 4" in lost and "depth" not in lost
    other = next(line for line in text.splitlines() if line.startswith("other queue drops"))
    assert "depth:sensors/frame 436" in other and "backend:frontend/frame 188" in other
    (tmp_path / "stats.json").write_text(json.dumps({"frames_sent": 501, "frames_without_state": 0,
                                                     "drops": {"depth:sensors/frame": 400}}))
    assert "frames lost by the estimator        none" in "\n".join(summary_lines(tmp_path, None, "x"))


def test_summary_reports_the_share_of_depth_pixels_only_freeing_space(tmp_path):
    (tmp_path / "stats.json").write_text(json.dumps({"depth_uncertain_fraction": 0.115, "drops": {}}))
    text = "\n".join(summary_lines(tmp_path, None, "x"))
    assert "depth pixels only freeing space     11.5 %" in text
    (tmp_path / "stats.json").write_text(json.dumps({"depth_uncertain_fraction": None}))
    assert "only freeing space" not in "\n".join(summary_lines(tmp_path, None, "x"))
