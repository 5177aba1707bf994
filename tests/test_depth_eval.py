"""`python -m tools eval depth` end to end on a tiny rendered split: every method gets finite metrics, the table has
the Laplacian and Gaussian expectations, the calibration plot is written."""

from __future__ import annotations

import json

import numpy as np
import pytest

import tools.__main__ as dev_cli
from tools.depth import make_dataset
from tools.depth.evaluate import METHODS

pytestmark = pytest.mark.e2e  # renders a split and runs the whole evaluation command (~20 s)


@pytest.fixture(scope="module")
def tiny_set(tmp_path_factory):
    root = tmp_path_factory.mktemp("depth_set")
    assert make_dataset.main(["--out", str(root), "--train", "0", "--val", "1", "--test", "1", "--frames", "5",
                              "--workers", "1"]) == 0
    return root


def test_eval_depth_writes_every_method(tiny_set, tmp_path):
    out = tmp_path / "eval"
    rc = dev_cli.main(["eval", "depth", "--data", str(tiny_set), "--split", "test", "--frames", "2", "--out", str(out)])
    assert rc == 0
    m = json.loads((out / "metrics.json").read_text())
    assert set(METHODS) <= set(m["metrics"])
    for name in METHODS:
        r = m["metrics"][name]
        assert np.isfinite([r["absrel"], r["rmse"], r["mahalanobis"], r["nll_laplace"], r["nll_gauss"]]).all(), name
        assert 0.0 <= r["within_1s"] <= r["within_2s"] <= r["within_3s"] <= 1.0, name
        assert 0.0 < r["coverage"] <= 1.0
    # the networks predict every pixel; SGBM leaves unmatched ones out
    assert m["metrics"]["stereo_net"]["coverage"] == pytest.approx(1.0)
    assert m["metrics"]["sgbm_linear"]["coverage"] < 1.0
    # a depth estimate that is not useless on an unseen scene
    assert m["metrics"]["stereo_net"]["absrel"] < 0.5
    table = (out / "table.md").read_text()
    assert "Laplace expectation" in table and "Gaussian expectation" in table
    assert (out / "calibration.png").stat().st_size > 1000


def test_make_dataset_keeps_rendered_scenes(tiny_set):
    f = tiny_set / "test" / "scene_03000.npz"
    before = f.stat().st_mtime_ns
    assert make_dataset.main(["--out", str(tiny_set), "--train", "0", "--val", "0", "--test", "1", "--frames", "5",
                              "--workers", "1"]) == 0
    assert f.stat().st_mtime_ns == before
    assert not list(tiny_set.rglob("*.tmp.npz"))


def test_fit_fusion_reports_a_correlation(tiny_set, tmp_path):
    from tools.depth import fit_fusion

    out = tmp_path / "fit.json"
    assert fit_fusion.main(["--data", str(tiny_set), "--frames", "2", "--out", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["pixels"] > 10_000 and 0.0 <= r["rho"] <= 0.9
    sig = [row["mean_err_over_sigma"] for row in r["rows"]]
    assert sig[5] < sig[0]  # a correlation widens the fused sigma (rho 0.25 against 0)
    assert abs(r["rows"][0]["rho"]) < 1e-9 and len(r["rows"]) == 19
