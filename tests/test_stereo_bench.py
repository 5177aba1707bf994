"""`python -m tools eval stereo`: Middlebury-style folders are read in both layouts, the metrics and the background
fill do what they say on hand-made arrays, and on the real Middlebury scenes SGBM and the network are scored
with figures that a broken reader or a sign error would change."""
import json

import cv2
import numpy as np
import pytest

from tools.depth.stereo_scene import StereoSceneError, find_scenes, read_pfm, read_stereo_scene
from tests.helpers_data import require_real_data
from services.depth.sgbm import fill_background
from tools.depth.stereo_bench import disparity_metrics, scene_scale


def _textured(rng, h, w):
    return cv2.GaussianBlur(rng.integers(0, 255, (h, w)).astype(np.uint8), (3, 3), 0)


def _write_2003(d, disp, scale=4):
    rng = np.random.default_rng(0)
    left = _textured(rng, *disp.shape)
    right = np.zeros_like(left)
    h, w = disp.shape
    for y in range(h):  # a fronto-parallel shift: right(x - d) = left(x)
        for x in range(w):
            xr = x - int(disp[y, x])
            if xr >= 0:
                right[y, xr] = left[y, x]
    d.mkdir()
    cv2.imwrite(str(d / "imL.png"), cv2.cvtColor(left, cv2.COLOR_GRAY2BGR))
    cv2.imwrite(str(d / "imR.png"), right)
    cv2.imwrite(str(d / "groundtruth.png"), (disp * scale).astype(np.uint8))
    mask = np.full(disp.shape, 255, np.uint8)
    mask[:, :8] = 0
    cv2.imwrite(str(d / "nonocc.png"), mask)
    (d / "info.txt").write_text(f"{scale}\n{int(disp.max())}\n")
    return left, right


def _write_pfm(path, a):
    h, w = a.shape
    with open(path, "wb") as f:
        f.write(b"Pf\n" + f"{w} {h}\n-1.0\n".encode())
        np.flipud(a).astype("<f4").tofile(f)


@pytest.mark.unit
def test_reads_both_middlebury_layouts(tmp_path):
    disp = np.full((32, 48), 6.0, np.float32)
    disp[:, 30:] = 0.0  # unknown
    _write_2003(tmp_path / "old", disp)
    s = read_stereo_scene(tmp_path / "old")
    assert s.left.dtype == np.uint8 and s.left.ndim == 2 and s.max_disparity == 6.0
    assert np.all(s.disparity[:, :30] == 6.0) and np.all(np.isnan(s.disparity[:, 30:]))
    assert not s.masks["nonocc"][:, :8].any() and s.masks["nonocc"][:, 8:].all()

    new = tmp_path / "new"
    new.mkdir()
    cv2.imwrite(str(new / "im0.png"), s.left)
    cv2.imwrite(str(new / "im1.png"), s.right)
    gt = np.where(np.isnan(s.disparity), np.inf, s.disparity).astype(np.float32)
    gt[0, 0] = 7.25
    _write_pfm(new / "disp0GT.pfm", gt)
    occ = np.full(gt.shape, 255, np.uint8)
    occ[5:10] = 128
    cv2.imwrite(str(new / "mask0nocc.png"), occ)
    assert read_pfm(new / "disp0GT.pfm")[0, 0] == 7.25  # top row first
    t = read_stereo_scene(new)
    assert t.disparity[0, 0] == 7.25 and np.isnan(t.disparity[0, 40])
    assert not t.masks["nonocc"][5:10].any() and t.masks["nonocc"][12, :30].all()
    assert [p.name for p in find_scenes([tmp_path])] == ["new", "old"]


@pytest.mark.unit
def test_bad_folders_give_errors_that_name_the_file(tmp_path):
    with pytest.raises(StereoSceneError, match="neither"):
        read_stereo_scene(tmp_path)
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "im0.png").write_bytes(b"not a png")
    with pytest.raises(StereoSceneError, match="disp0GT"):
        read_stereo_scene(tmp_path / "x")
    with pytest.raises(StereoSceneError, match="not found"):
        find_scenes([tmp_path / "missing"])


@pytest.mark.unit
def test_background_fill_takes_the_farther_neighbour():
    d = np.array([[5.0, np.nan, np.nan, 2.0, np.nan], [np.nan, np.nan, np.nan, np.nan, np.nan]], np.float32)
    f = fill_background(d)
    assert f[0].tolist() == [5.0, 2.0, 2.0, 2.0, 2.0]  # the smaller disparity (background) wins, edges copy
    assert f[1].tolist() == [3.5] * 5  # an empty row takes the image's median


@pytest.mark.unit
def test_disparity_metrics_by_hand():
    gt = np.array([[1.0, 2.0, 3.0, 4.0]], np.float32)
    est = np.array([[1.5, 5.0, np.nan, 4.0]], np.float32)
    sigma = np.array([[1.0, 1.0, 1.0, 0.5]], np.float32)
    mask = np.array([[True, True, True, True]])
    m = disparity_metrics(est, sigma, gt, mask)
    assert m["n"] == 4 and m["coverage"] == pytest.approx(75.0)
    assert m["epe"] == pytest.approx((0.5 + 3.0 + 0.0) / 3)
    assert m["bad1"] == pytest.approx(100 / 3) and m["bad3"] == pytest.approx(0.0)
    assert m["err_over_sigma"] == pytest.approx((0.5 + 3.0 + 0.0) / 3)
    assert m["within1s"] == pytest.approx(200 / 3)


@pytest.mark.unit
def test_scale_shrinks_only_pairs_beyond_the_range(tmp_path):
    disp = np.full((16, 16), 50.0, np.float32)
    _write_2003(tmp_path / "s", disp, scale=1)
    s = read_stereo_scene(tmp_path / "s")
    assert scene_scale(s, 96, 0.9) == 1.0
    s.max_disparity = 192.0
    assert scene_scale(s, 96, 0.9) == pytest.approx(0.45)


def test_real_middlebury_scores(tmp_path):
    root = require_real_data("middlebury_2001_2003")
    from tools.__main__ import main

    rc = main(["eval", "stereo", str(root / "venus"), str(root / "tsukuba"), "--euroc", "none", "--out",
               str(tmp_path)])
    assert rc == 0
    rep = json.loads((tmp_path / "metrics.json").read_text())
    assert set(rep["scenes"]) == {"venus", "tsukuba"}
    for name in ("venus", "tsukuba"):
        rows = rep["scenes"][name]
        # SGBM on real photographs is good where it matches; made dense it covers every evaluated pixel
        assert rows["sgbm"]["bad2"] < 5.0 and rows["sgbm"]["coverage"] > 80
        assert rows["sgbm_dense"]["coverage"] == pytest.approx(100.0)
        assert rows["sgbm_dense"]["bad2"] >= rows["sgbm"]["bad2"] - 1e-9
        # the shipped network is dense and finite, with an EPE of a fraction of the scene's range
        assert rows["net"]["coverage"] == pytest.approx(100.0) and 0 < rows["net"]["epe"] < 3.0
        assert 0 < rows["net"]["err_over_sigma"] < 20
    assert (tmp_path / "venus.png").is_file() and "## Mean over scenes" in (tmp_path / "table.md").read_text()
