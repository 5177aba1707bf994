"""``sigmaslam run``'s command line and what it writes, without running the pipeline: the ATE over the ground truth's
span, CONFIG after the options, the progress line (where a dataset keeps its ground truth: tests/test_player.py)."""

from __future__ import annotations

import numpy as np
import pytest

from test_player import T0


def test_run_ate_is_computed_over_the_ground_truths_span_only():
    """Ground truth that starts 1 s after the first pose and ends before the last: the poses outside its span
    are not matched (nor aligned), and ate.json says how many were and over which span."""
    import tempfile
    from pathlib import Path

    from services.app.run_outputs import evaluate
    from shared.euroc import PoseSeries, write_tum

    t = T0 + np.arange(60, dtype=np.int64) * 50_000_000  # 3 s of poses at 20 Hz
    p = np.c_[np.linspace(0, 1, 60), np.zeros(60), np.zeros(60)]
    q = np.tile([1.0, 0, 0, 0], (60, 1))
    p_far = p.copy()
    p_far[:20] += 5.0  # before the ground truth starts: would ruin the ATE if it were used
    tg = T0 + 1_000_000_000 + np.arange(301, dtype=np.int64) * 5_000_000  # 1.0 .. 2.5 s at 200 Hz
    gt = PoseSeries(tg, np.c_[(tg - T0) * 1e-9 / 2.95, np.zeros(301), np.zeros(301)], np.tile([1.0, 0, 0, 0], (301, 1)))
    with tempfile.TemporaryDirectory() as d:
        write_tum(Path(d) / "gt.txt", gt)
        ate = evaluate(PoseSeries(t, p_far, q), Path(d) / "gt.txt")
    assert ate["poses"] == 60 and ate["matched"] == 31, ate  # 1.0 .. 2.5 s
    assert ate["matched_span_ns"] == [T0 + 1_000_000_000, T0 + 2_500_000_000]
    assert ate["groundtruth_span_ns"] == [int(tg[0]), int(tg[-1])]
    assert ate["ate_rmse_m"] < 1e-6


def test_run_takes_the_config_after_the_options():
    """``sigmaslam run DATASET --out DIR CONFIG`` (the documented form; Python 3.11's argparse refuses it
    unless positionals and options are parsed intermixed)."""
    import argparse

    from services.app import run_cmd

    top = argparse.ArgumentParser(prog="sigmaslam")
    run = top.add_subparsers(dest="command").add_parser("run")
    run_cmd.add_arguments(run)
    a = top.parse_args(["run", "data/V1_02", "--out", "out/v102", "configs/demo.yaml", "--gt", "gt.txt",
                        "--player-arg=--max-frames=20", "--set", "o2p.enabled=false"])
    assert (a.dataset, a.config, a.out, a.gt) == ("data/V1_02", "configs/demo.yaml", "out/v102", "gt.txt")
    assert a.player_arg == ["--max-frames=20"] and a.set == ["o2p.enabled=false"]
    a = top.parse_args(["run", "data/V1_02", "configs/demo.yaml", "--out", "o"])
    assert (a.dataset, a.config, a.gt) == ("data/V1_02", "configs/demo.yaml", None)
    assert top.parse_args(["run", "d", "--out", "o"]).config is None
    with pytest.raises(SystemExit):
        top.parse_args(["run", "d", "--out", "o", "c", "extra"])
    # a --gt that is not there: refused before anything starts
    a = top.parse_args(["run", "d", "--out", "o", "--gt", "/nonexistent/gt.txt"])
    assert run_cmd.main(a) == 2


def test_run_progress_line_counts_states_and_sequence_time():
    """`sigmaslam run` prints a progress line every PROGRESS_EVERY_S: what it has received so far."""
    from types import SimpleNamespace

    from services.app.run_collector import Collection, progress_line

    col = Collection()
    assert "no state yet" in progress_line(col, 12.0)
    for k, status in enumerate(["initialising"] * 3 + ["tracking"] * 7):
        col.states.append(SimpleNamespace(header=SimpleNamespace(stamp_ns=1_000_000_000 + k * 50_000_000), status=status))
    line = progress_line(col, 20.4)
    assert line == "20 s: 10 states (initialising 3, tracking 7), 0.5 s into the sequence", line
