"""Rectification + SGBM on a pair rendered through the real (distorted) EuRoC cameras gives depth close to
the ground truth rendered in the rectified left camera; the pipeline falls back to SGBM without weights
and rejects images of the wrong size."""
import numpy as np
import pytest

from services.depth.config import DepthConfig
from services.depth.pipeline import DepthPipeline
from services.depth.uncertainty import depth_metrics
from shared.camera import camera_from_sensor_yaml, read_sensor_yaml_file
from shared.paths import euroc_dir
from tools.depth.scenes import random_camera, random_scene, render_pinhole, render_rays


@pytest.fixture(scope="module")
def rendered():
    calib = euroc_dir() / "calib"
    cams = [camera_from_sensor_yaml(read_sensor_yaml_file(calib / f"cam{i}_sensor.yaml"), f"cam{i}") for i in (0, 1)]
    rng = np.random.default_rng(5)
    scene = random_scene(rng)
    T_WN0 = random_camera(scene, rng)
    cfg = DepthConfig(method="sgbm")
    pipe = DepthPipeline(cfg, *cams)
    T_WS = T_WN0 @ np.linalg.inv(pipe.T_SC)  # body pose that puts the rectified left camera at T_WN0
    raw = []
    for cam in cams:
        rays = cam.camera.unproject(cam.camera.pixel_grid())  # distorted pixels -> rays with z = 1
        img, _ = render_rays(scene, T_WS @ cam.T_SC, rays)
        raw.append(np.clip(img * 255, 0, 255).astype(np.uint8).reshape(cam.camera.height, cam.camera.width))
    _, gt = render_pinhole(scene, T_WN0, pipe.K, (cfg.width, cfg.height), supersample=1)
    return pipe, raw, gt, T_WS


def test_rectified_sgbm_depth_is_close_to_ground_truth(rendered):
    pipe, raw, gt, T_WS = rendered
    assert pipe.method == "sgbm"
    res = pipe.process(0, raw[0], raw[1], T_WS)
    d, s = res.stereo
    inner = np.zeros_like(gt, bool)
    inner[40:-40, 100:-40] = True  # away from the unmatched left band and the rectification border
    valid = np.isfinite(d) & inner
    assert valid.sum() > 0.5 * inner.sum()
    m = depth_metrics(np.where(inner, d, np.nan), s, gt)
    assert m["absrel"] < 0.05, m  # SGBM outliers at depth edges included
    rel = (d[valid] - gt[valid]) / gt[valid]
    assert np.median(np.abs(rel)) < 0.05  # ~0.3 px of sub-pixel noise at ~10 px disparity
    assert abs(np.median(rel)) < 0.015  # no bias: a wrong rectification (K, baseline, rotation) would show here
    np.testing.assert_allclose(res.T_WC, T_WS @ pipe.T_SC)
    assert res.mvs is None and res.fused is res.stereo  # SGBM has no MVS partner


def test_heuristic_sigma_follows_eq11(rendered):
    pipe, raw, _, _ = rendered
    d, s = pipe.stereo(*pipe.rect.rectify(raw[0], raw[1]))
    ok = np.isfinite(d)
    coeff = pipe.cfg.heuristic_sigma_coeff / (pipe.f_px * pipe.baseline_m)
    np.testing.assert_allclose(s[ok], coeff * d[ok] ** 2, rtol=1e-5)


def test_network_method_without_weights_falls_back_to_sgbm(rendered, tmp_path):
    pipe, raw, _, _ = rendered
    calib = euroc_dir() / "calib"
    cams = [camera_from_sensor_yaml(read_sensor_yaml_file(calib / f"cam{i}_sensor.yaml"), f"cam{i}") for i in (0, 1)]
    p2 = DepthPipeline(DepthConfig(method="network", stereo_weights=str(tmp_path / "none.pt")), *cams)
    assert p2.method == "sgbm"
    with pytest.raises(ValueError, match="calibration says"):
        p2.process(0, raw[0][:100], raw[1], None)


def test_sgbm_guided_network_in_the_pipeline_starts_from_sgbm(rendered, tmp_path):
    """The SGBM-guided network (arch stereo_refine) loads through the weights interface and runs inside the
    pipeline; untrained (its correction head starts at zero) its depth is SGBM's where SGBM matched, with the
    holes filled from the background side, and its sigma is positive and scaled by the gain in the JSON."""
    import torch

    from services.depth import weights
    from services.depth.refine_net import RefineStereoNet
    from services.depth.sgbm import fill_background, sgbm_disparity

    pipe, raw, _, _ = rendered
    torch.manual_seed(0)
    weights.save(RefineStereoNet(96), tmp_path / "ref", "stereo_refine", {"max_disparity": 96}, {"gain": 2.0})
    calib = euroc_dir() / "calib"
    cams = [camera_from_sensor_yaml(read_sensor_yaml_file(calib / f"cam{i}_sensor.yaml"), f"cam{i}") for i in (0, 1)]
    p2 = DepthPipeline(DepthConfig(method="network", use_mvs=False, stereo_weights=str(tmp_path / "ref.pt"),
                                   threads=1, device="cpu"), *cams)
    assert p2.method == "network" and p2.stereo_gain == 2.0
    left, right = p2.rect.rectify(raw[0], raw[1])
    d, s = p2.stereo(left, right)
    sg = sgbm_disparity(left, right, p2.sgbm_params)
    u = fill_background(sg)
    expect = p2.f_px * p2.baseline_m / u
    ok = np.isfinite(sg) & (u > 1.0)
    np.testing.assert_allclose(d[ok], expect[ok], rtol=1e-4)
    assert np.all(np.isfinite(s[np.isfinite(d)])) and np.all(s[np.isfinite(d)] > 0)
    res = p2.process(0, raw[0], raw[1], None)
    assert res.stereo[0].shape == (p2.cfg.height, p2.cfg.width) and res.mvs is None
