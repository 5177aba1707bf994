"""The mapped room the occupancy-to-point tests share: ray-cast depth of a box room with a box inside,
integrated from 12 views on a circle (map frame = world)."""
from __future__ import annotations

import numpy as np

from shared.occupancy.blocks import BlockStore
from services.mapping.config import SensorModelConfig
from services.mapping.integrate import integrate
from services.mapping.sensor_model import prepare_depth
from raycast_depth import DepthRenderer, intrinsics, look_at, room_scene

W, H = 160, 120
K = intrinsics(W, H)


def view(a: float) -> np.ndarray:
    """Camera pose T_WC on a circle in the room, looking slightly down and ahead."""
    eye = np.array([3.0 + 0.8 * np.cos(a), 2.5 + 0.8 * np.sin(a), 1.5])
    return look_at(eye, eye + np.array([np.cos(a + 0.5), np.sin(a + 0.5), -0.3]))


def mapped_room(sigma_m: float) -> tuple[BlockStore, DepthRenderer, SensorModelConfig]:
    """Occupancy store of the room integrated with a constant depth sigma, its renderer and sensor config."""
    renderer = DepthRenderer(room_scene())
    cfg = SensorModelConfig()
    store = BlockStore(cfg.voxel_size_m)
    for a in np.linspace(0, 2 * np.pi, 12, endpoint=False):
        T = view(a)
        d, s, _ = prepare_depth(renderer.render(K, W, H, T), np.full((H, W), sigma_m, np.float32), cfg)
        integrate(store, d, s, K, T, cfg)
    return store, renderer, cfg
