"""A ray-cast room mapped into two overlapping submaps, the fixture of the occupancy query, grid and export tests.

The room is raycast_depth.room_scene() (6 x 5 x 3 m, a 1 m box at x 3.6-4.6, y 2.75-3.75 on the floor, a 0.5 m
sphere at (1.8, 3.5, 1.2)). Submap 0 is seen from (2, 1.5, 1.4) looking along +x at the far wall and the box;
submap 1 from (4, 1.6, 1.4) looking towards the sphere and the wall behind it. Both see the floor between them, so
they overlap. Each submap's content is integrated in its own frame M (anchored at its first camera's body pose);
``drift`` moves submap 1's *pose* (not its content) as an uncorrected estimator would, which a loop closure
(a keyframe update) then corrects.
"""

from __future__ import annotations

import numpy as np

from raycast_depth import DepthRenderer, intrinsics, look_at, room_scene
from services.mapping.config import SensorModelConfig
from services.mapping.integrate import integrate
from services.mapping.sensor_model import prepare_depth
from services.mapping.submaps import SubmapMapper
from shared.occupancy.blocks import BlockStore

W, H = 160, 120
K = intrinsics(W, H)
SIGMA_M = 0.02
ROOM = (6.0, 5.0, 3.0)
BOX = (np.array([3.6, 2.75, 0.0]), np.array([4.6, 3.75, 1.0]))
BALL = (np.array([1.8, 3.5, 1.2]), 0.5)


def views(k: int) -> list[np.ndarray]:
    """Camera poses T_WC of submap k: a few views around one place, looking at one side of the room."""
    if k == 0:
        eye, target = np.array([2.0, 1.5, 1.4]), np.array([6.0, 2.2, 0.9])
    else:
        eye, target = np.array([4.0, 1.6, 1.4]), np.array([1.6, 3.6, 0.9])
    out = []
    for dx, dy in ((0, 0), (0.15, 0), (0, 0.15)):
        d = np.array([dx, dy, 0.0])
        for tz in (0.0, 0.6, -0.6):
            out.append(look_at(eye + d, target + d + np.array([0.0, 0.0, tz])))
    return out


_STORES: list | None = None


def _stores() -> list:
    """(T_WM true, BlockStore) of each submap, integrated once per test session (read-only afterwards)."""
    global _STORES
    if _STORES is None:
        renderer, cfg, _STORES = room_renderer(), SensorModelConfig(), []
        for k in (0, 1):
            poses = views(k)
            store = BlockStore(cfg.voxel_size_m)
            for T_WC in poses:
                d, s, _ = prepare_depth(renderer.render(K, W, H, T_WC), np.full((H, W), SIGMA_M, np.float32), cfg)
                integrate(store, d, s, K, np.linalg.inv(poses[0]) @ T_WC, cfg)
            _STORES.append((poses[0], store, len(poses)))
    return _STORES


def mapped_room(drift: np.ndarray | None = None) -> tuple[SubmapMapper, DepthRenderer]:
    """Two submaps of the room (ids 0, 1, anchored at their first camera pose, stamps 0 and 10 s), sharing the
    session's voxel stores (do not integrate into them). ``drift`` (4x4): submap 1's pose is ``drift @ T_WM(true)``,
    its content unchanged (an estimator's error)."""
    mapper = SubmapMapper(SensorModelConfig())
    for k, (T_WM, store, n) in enumerate(_stores()):
        sm = mapper.new_submap(T_WM if (k == 0 or drift is None) else drift @ T_WM, k * 10_000_000_000)
        sm.store, sm.n_frames = store, n
    return mapper, room_renderer()


_RENDERER: DepthRenderer | None = None


def room_renderer() -> DepthRenderer:
    global _RENDERER
    if _RENDERER is None:
        _RENDERER = DepthRenderer(room_scene(ROOM))
    return _RENDERER


def observed_points(renderer: DepthRenderer, k: int, rng: np.random.Generator, n: int = 2000
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Points in W seen by submap k's views: (free points at least 0.2 m in front of the surface their ray hits,
    surface points exactly on it)."""
    free, surf = [], []
    for T_WC in views(k):
        depth = renderer.render(K, W, H, T_WC)
        v, u = rng.integers(0, H, n // 10), rng.integers(0, W, n // 10)
        d = depth[v, u].astype(float)
        ok = np.isfinite(d) & (d > 0.6)
        u, v, d = u[ok], v[ok], d[ok]
        ray = np.column_stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(len(u))])
        z = 0.3 + rng.random(len(u)) * (d - 0.2 - 0.3)
        free.append((ray * z[:, None]) @ T_WC[:3, :3].T + T_WC[:3, 3])
        surf.append((ray * d[:, None]) @ T_WC[:3, :3].T + T_WC[:3, 3])
    return np.concatenate(free), np.concatenate(surf)
