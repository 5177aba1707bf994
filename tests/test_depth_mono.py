"""depth.mono (cam0 alone, MVS only) on a rendered scene: the left image is undistorted to the rectified K
without any right camera; nothing comes out before a pose and posed keyframes, then MVS depth with finite
sigma close to the rendered ground truth, as fused depth; stereo configs are untouched."""
from __future__ import annotations

import numpy as np
import pytest

from services.depth.config import DepthConfig
from services.depth.pipeline import DepthPipeline
from shared.camera import camera_from_sensor_yaml, read_sensor_yaml_file, rectified_intrinsics, stereo_rectification
from shared.paths import euroc_dir
from tools.depth.scenes import look_at, random_scene, render_pinhole, render_rays


def _cam(i: int):
    return camera_from_sensor_yaml(read_sensor_yaml_file(euroc_dir() / "calib" / f"cam{i}_sensor.yaml"), f"cam{i}")


def test_mono_config_needs_the_mvs_network():
    with pytest.raises(ValueError, match="depth.mono"):
        DepthConfig(mono=True, method="sgbm")
    with pytest.raises(ValueError, match="depth.mono"):
        DepthConfig(mono=True, use_mvs=False)


def test_mono_and_stereo_share_the_rectified_intrinsics():
    cam0, cam1 = _cam(0), _cam(1)
    cfg = DepthConfig(method="sgbm")
    stereo = DepthPipeline(cfg, cam0, cam1)
    np.testing.assert_array_equal(stereo.K, stereo_rectification(cam0, cam1, (512, 384)).K)
    np.testing.assert_array_equal(stereo.K, rectified_intrinsics(cam0, (512, 384)))
    with pytest.raises(ValueError, match="right camera"):
        DepthPipeline(cfg, cam0)


@pytest.mark.e2e  # several seconds of CPU: out of the unit tier (tests/README.md)
def test_mono_pipeline_mvs_depth_after_posed_keyframes():
    cam0 = _cam(0)
    # every pixel kept (max_relative_sigma 0): this is about the mono geometry, not which pixels are sure enough
    cfg = DepthConfig(mono=True, mvs_sources=3, threads=1, device="cpu", max_relative_sigma=0.0)
    pipe = DepthPipeline(cfg, cam0)  # no right camera
    assert pipe.mvs_net is not None and pipe.stereo_net is None
    np.testing.assert_array_equal(pipe.K, rectified_intrinsics(cam0, (512, 384)))
    np.testing.assert_array_equal(pipe.T_SC, cam0.T_SC)  # the camera's own axes: no rectifying rotation
    scene = random_scene(np.random.default_rng(5))
    centre = 0.5 * (scene.box_lo[0] + scene.box_hi[0])
    target = centre + np.array([3.0, 0.0, -0.3])
    # the camera slides sideways by 6 cm per frame, looking at the same point
    T_WC = [look_at(centre + np.array([-0.5, -0.15 + 0.06 * i, 0.0]), target) for i in range(4)]
    T_WS = [T @ np.linalg.inv(cam0.T_SC) for T in T_WC]
    rays = cam0.camera.unproject(cam0.camera.pixel_grid())
    raw = []
    for T in T_WC:  # the raw, distorted cam0 image
        img, _ = render_rays(scene, T, rays)
        raw.append(np.clip(img * 255, 0, 255).astype(np.uint8).reshape(cam0.camera.height, cam0.camera.width))
    # no pose, or a pose but no keyframes yet: nothing
    for T in (None, T_WS[0]):
        res = pipe.process(0, raw[0], None, T)
        assert res.fused is None and res.mvs is None and res.stereo is None
    for i in range(3):  # three posed keyframes: the three MVS sources
        pipe.remember_frame(i, raw[i])
    pipe.update_keyframes(np.arange(3), np.stack(T_WS[:3]))
    assert pipe.n_keyframe_views == 3
    res = pipe.process(3, raw[3], None, T_WS[3])
    assert res.stereo is None and res.n_sources == 3 and res.fused is res.mvs
    depth, sigma = res.fused
    assert depth.shape == sigma.shape == (384, 512)
    ok = np.isfinite(depth)
    # depth everywhere but on the flying pixels at the scene's silhouettes (dropped, counted)
    assert 0 < pipe.flying_px < 0.1 * ok.size and ok.mean() + pipe.flying_px / ok.size > 0.9
    assert np.isfinite(sigma[ok]).all() and (sigma[ok] > 0).all()
    np.testing.assert_allclose(res.T_WC, T_WS[3] @ cam0.T_SC)
    _, gt = render_pinhole(scene, T_WC[3], pipe.K, (512, 384), supersample=1)
    both = ok & np.isfinite(gt) & (gt > 0)
    rel = np.abs(depth[both] - gt[both]) / gt[both]
    assert np.median(rel) < 0.15  # a wrong K, pose or undistortion gives tens of percent
    # the wrong size of image is refused with a clear error
    with pytest.raises(ValueError, match="shape"):
        pipe.process(4, raw[3][:100], None, T_WS[3])
