"""Depth only where the rectified images have content: the black rectification border (and a margin around it)
gets NaN depth from stereo, MVS and the fusion (the networks made up depth there, MVS mostly far behind the walls,
which put surfaces behind the room's walls in the fused map)."""
import cv2
import numpy as np
import pytest

from services.depth.config import DepthConfig
from services.depth.coverage import covered, valid_region
from tests.depth_nets import random_network_pipeline


def test_covered_follows_the_raw_image_bounds():
    mx, my = np.meshgrid(np.linspace(-2, 11, 14, dtype=np.float32), np.linspace(-1, 6, 8, dtype=np.float32))
    m = covered((mx, my), (6, 10))  # raw image 10 wide, 6 high: x in [0, 9], y in [0, 5]
    np.testing.assert_array_equal(m, (mx >= 0) & (mx <= 9) & (my >= 0) & (my <= 5))
    mx[3, 5] = np.nan
    assert not covered((mx, my), (6, 10))[3, 5]


def test_valid_region_margin_is_measured_from_uncovered_pixels_only():
    m = np.ones((20, 30), bool)
    m[:, :2] = False  # an uncovered strip on the left
    v = valid_region([m, np.ones_like(m)], 3)
    assert not v[:, :5].any() and v[:, 5:].all()  # 3 px more on the left, none at the other image edges
    np.testing.assert_array_equal(valid_region([m], 0), m)
    with pytest.raises(ValueError):
        valid_region([m], -1)
    with pytest.raises(ValueError):
        DepthConfig(border_margin_px=-1)


def test_pipeline_drops_depth_outside_the_rectified_coverage(tmp_path):
    pipe = random_network_pipeline(tmp_path, mvs_sources=2, border_margin_px=4)
    white = np.full((480, 752), 255, np.uint8)
    left, right = pipe.rect.rectify(white, white)
    black = (left < 128) | (right < 128)  # rectified pixels that no raw pixel fills
    assert 0.01 < black.mean() < 0.2  # the EuRoC rig has a border at the top and bottom
    assert not (pipe.valid & black).any()
    assert pipe.valid.mean() > 0.8
    grown = cv2.dilate(black.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0  # the 4 px margin
    assert not (pipe.valid & grown).any()

    rng = np.random.default_rng(1)
    raw = [rng.integers(0, 255, (480, 752), dtype=np.uint8) for _ in range(4)]
    T_WS = [np.eye(4) for _ in range(4)]
    for i, T in enumerate(T_WS):
        T[0, 3] = 0.05 * i
    for i in (1, 2, 3):
        pipe.remember_frame(i, raw[i])
    pipe.update_keyframes(np.array([1, 2]), np.stack([T_WS[1], T_WS[2]]))
    res = pipe.process(3, raw[3], raw[0], T_WS[3])
    assert res.mvs is not None
    for d, s in (res.stereo, res.mvs, res.fused):
        assert np.isnan(d[grown]).all() and np.isnan(s[grown]).all()
        assert np.isfinite(d[pipe.valid]).mean() > 0.9


def test_mono_pipeline_masks_the_undistortion_border(tmp_path):
    pipe = random_network_pipeline(tmp_path, mvs_sources=1, border_margin_px=0, mono=True)
    white = np.full((480, 752), 255, np.uint8)
    black = cv2.remap(white, *pipe._left_maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT) < 128
    assert black.any() and not (pipe.valid & black).any()
    rng = np.random.default_rng(2)
    raw = [rng.integers(0, 255, (480, 752), dtype=np.uint8) for _ in range(2)]
    T1 = np.eye(4)
    T1[0, 3] = 0.1
    pipe.remember_frame(0, raw[0])
    pipe.update_keyframes(np.array([0]), np.eye(4)[None])
    res = pipe.process(1, raw[1], None, T1)
    assert res.fused is not None and np.isnan(res.fused[0][black]).all()
    assert np.isfinite(res.fused[0][pipe.valid]).mean() > 0.9
