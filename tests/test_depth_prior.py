"""The MVS network's sparse depth prior from landmarks (services/depth/prior.py) against a known geometry, and
through the depth pipeline: landmarks within the age limit reach the network and change its output."""
import numpy as np
import torch

from services.depth.mvs_net import MVSNet
from services.depth.prior import landmark_prior
from shared.geometry import make_T, so3_exp, transform_points
from tests.depth_nets import random_network_pipeline

K = np.array([[300.0, 0, 255.5], [0, 310.0, 191.5], [0, 0, 1]])
H, W = 384, 512


def _points_at(T_WC, uv, z):
    """World points that the camera T_WC sees at pixels uv (N,2) with depths z (N,)."""
    uv, z = np.asarray(uv, float), np.asarray(z, float)
    p_C = np.c_[(uv[:, 0] - K[0, 2]) / K[0, 0] * z, (uv[:, 1] - K[1, 2]) / K[1, 1] * z, z]
    return transform_points(T_WC, p_C)


def test_projection_against_known_pixels_and_depths():
    T_WC = make_T(so3_exp(np.array([0.3, -0.2, 0.1])), np.array([1.0, -2.0, 0.5]))
    uv = np.array([[10, 20], [500, 380], [255, 191], [100.4, 200.4], [0, 0]])
    z = np.array([2.0, 7.5, 0.5, 14.0, 3.0])
    inside = _points_at(T_WC, uv, z)
    outside = np.r_[_points_at(T_WC, [[-3, 10], [600, 10], [10, 390]], [2.0, 2.0, 2.0]),  # off the image
                    _points_at(T_WC, [[50, 50]], [20.0]),  # beyond the depth range
                    _points_at(T_WC, [[60, 60]], [0.1]),  # too near
                    transform_points(T_WC, np.array([[0.1, 0.1, -2.0]]))]  # behind
    farther_same_pixel = _points_at(T_WC, [[10.3, 19.8]], [4.0])  # same pixel as the first, farther: hidden
    p_W = np.r_[inside, outside, farther_same_pixel, [[np.nan, 0, 0]]]
    pr = landmark_prior(p_W, T_WC, K, (H, W), 0.3, 15.0, 300)
    assert pr.depth.shape == (H, W) and pr.depth.dtype == np.float32
    assert pr.used == 5 and pr.rejected == len(p_W) - 5
    expect = np.zeros((H, W))
    for (u, v), d in zip(np.floor(uv + 0.5).astype(int), z):
        expect[v, u] = d
    np.testing.assert_allclose(pr.depth, expect, rtol=1e-6)
    # the nearer of two landmarks in one pixel wins whatever their order
    pr2 = landmark_prior(np.r_[farther_same_pixel, inside], T_WC, K, (H, W), 0.3, 15.0, 300)
    assert pr2.depth[20, 10] == np.float32(2.0)


def test_cap_keeps_the_highest_priority():
    T_WC = np.eye(4)
    rng = np.random.default_rng(0)
    uv = np.c_[rng.integers(0, W, 50), rng.integers(0, H, 50)].astype(float)
    uv = np.unique(uv, axis=0)
    p_W = _points_at(T_WC, uv, rng.uniform(1, 5, len(uv)))
    pri = np.arange(len(uv))
    pr = landmark_prior(p_W, T_WC, K, (H, W), 0.3, 15.0, 10, priority=pri)
    assert pr.used == 10 and np.count_nonzero(pr.depth) == 10
    kept = np.flatnonzero(pr.depth[uv[:, 1].astype(int), uv[:, 0].astype(int)] > 0)
    assert sorted(kept.tolist()) == list(range(len(uv) - 10, len(uv)))
    assert landmark_prior(p_W, T_WC, K, (H, W), 0.3, 15.0, 0).used == 0
    assert landmark_prior(np.zeros((0, 3)), T_WC, K, (H, W), 0.3, 15.0, 10).used == 0


def test_prior_mask_matches_the_networks_coarse_cells():
    """The network's mask channel is set exactly in the 1/4-resolution cells that hold a landmark pixel."""
    T_WC = np.eye(4)
    uv = np.array([[3, 3], [4, 3], [100, 50], [511, 383]], float)
    pr = landmark_prior(_points_at(T_WC, uv, [1.0, 2.0, 3.0, 4.0]), T_WC, K, (H, W), 0.3, 15.0, 300)
    net = MVSNet(8)
    vol = net.prior_volume(torch.from_numpy(pr.depth)[None], H // 4, W // 4)[0, -1].numpy()
    cells = {(int(v) // 4, int(u) // 4) for u, v in uv}
    assert {tuple(c) for c in np.argwhere(vol > 0)} == cells


def test_pipeline_feeds_recent_landmarks_to_the_network(tmp_path):
    pipe = random_network_pipeline(tmp_path, mvs_sources=1, prior_max_age_s=0.5)
    rng = np.random.default_rng(0)
    raw = [rng.integers(0, 255, (480, 752), dtype=np.uint8) for _ in range(3)]
    T_WS = [make_T(np.eye(3), np.array([0.05 * i, 0, 0])) for i in range(3)]
    pipe.remember_frame(1, raw[1])
    pipe.update_keyframes(np.array([1]), T_WS[1][None])
    stamp = 2_000_000_000
    res0 = pipe.process(stamp, raw[2], raw[0], T_WS[2])
    assert res0.mvs is not None and res0.n_prior == 0  # no landmarks yet: empty prior
    T_WC = T_WS[2] @ pipe.T_SC
    uv = np.c_[rng.uniform(0, 511, 40), rng.uniform(0, 383, 40)]
    z = rng.uniform(1.0, 6.0, 40)  # points at these pixels and depths of the pipeline's rectified camera
    p_C = np.c_[(uv[:, 0] - pipe.K[0, 2]) / pipe.K[0, 0] * z, (uv[:, 1] - pipe.K[1, 2]) / pipe.K[1, 1] * z, z]
    p_W = transform_points(T_WC, p_C)
    last = np.full(40, stamp, np.int64)
    last[:10] = stamp - 2_000_000_000  # seen 2 s before the frame: left out (older than prior_max_age_s)
    pipe.update_landmarks(p_W, last, np.full(40, 3))
    n_pix = len(np.unique(np.floor(uv[10:] + 0.5).astype(int), axis=0))
    prior = pipe.mvs_prior(stamp, T_WC)
    assert np.count_nonzero(prior) == n_pix
    np.testing.assert_allclose(np.sort(prior[prior > 0]), np.sort(z[10:]), rtol=1e-6)
    res1 = pipe.process(stamp, raw[2], raw[0], T_WS[2])
    assert res1.n_prior == n_pix
    assert not np.allclose(res1.mvs[0], res0.mvs[0])  # the prior reaches the network
