"""The occupancy-to-point factor at the true poses (tools/o2p_bias.py): on a room mapped from noisy ray-cast
depth, exact points of new views must lie on the map's L = 0 surface on average, and the factor alone must
not pull a frame away from its true pose along the viewing direction. With eq. 3's tau as printed
(tau / 2 < 3 sigma: the occupied side saturates early) the surface sits millimetres behind the true one."""

from __future__ import annotations

import numpy as np
import pytest

from shared.occupancy.blocks import BlockStore
from services.mapping.config import SensorModelConfig
from services.mapping.integrate import integrate
from shared.occupancy.query import near_surface_field
from services.mapping.sensor_model import prepare_depth
from shared.geometry import inv_T
from tests.o2p_room import H, K, W, view
from tools.o2p_bias import factor_offset, residuals
from raycast_depth import DepthRenderer, room_scene

NOISE = 0.04  # per-pixel depth noise [m], independent across views; the sigma given to the map and factor


def _bias(cfg: SensorModelConfig) -> tuple[float, np.ndarray]:
    """Mean signed distance e of exact points [m] and the mean factor-only camera offset [m] (camera axes)
    over 8 views not used for mapping."""
    renderer = DepthRenderer(room_scene())
    rng = np.random.default_rng(0)
    store = BlockStore(cfg.voxel_size_m)
    for a in np.tile(np.linspace(0, 2 * np.pi, 24, endpoint=False), 2):
        T = view(a)
        d = renderer.render(K, W, H, T) + rng.normal(0, NOISE, (H, W)).astype(np.float32)
        d, s, _ = prepare_depth(d, np.full((H, W), NOISE, np.float32), cfg)
        integrate(store, d, s, K, T, cfg)
    field = near_surface_field(store)
    es, ts = [], []
    for a in np.linspace(0.1, 2 * np.pi, 8, endpoint=False):
        T = view(a)
        z = renderer.render(K, W, H, T)
        v, u = np.mgrid[3:H:6, 3:W:6]
        ok = np.isfinite(z[v, u])
        z, u, v = z[v, u][ok], u[ok], v[ok]
        p = np.column_stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
        sig = np.full(len(p), NOISE)
        res = residuals(field, cfg.l_min, p, sig, T, np.eye(4))
        assert res["valid"].sum() > 100
        es.append(res["e"][res["valid"]])
        ts.append((inv_T(T) @ factor_offset(field, cfg.l_min, p, sig, T, np.eye(4))["T_WA_hat"])[:3, 3])
    return float(np.mean(np.concatenate(es))), np.mean(ts, axis=0)


@pytest.mark.parametrize("tau_sigma_k", [6.0, 0.0])
def test_factor_is_unbiased_at_the_true_pose(tau_sigma_k):
    e_mean, t_cam = _bias(SensorModelConfig(tau_sigma_k=tau_sigma_k))
    if tau_sigma_k > 0:  # tau >= 6 sigma: surface on the true one, no pull along the viewing direction
        assert abs(e_mean) < 0.001, e_mean
        assert np.linalg.norm(t_cam) < 0.0015 and abs(t_cam[2]) < 0.001, t_cam
    else:  # eq. 3 as printed (the default): the zero crossing lies behind the surface, the factor pulls the camera forward
        assert e_mean < -0.002, e_mean
        assert t_cam[2] > 0.003, t_cam
