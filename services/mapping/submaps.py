"""Occupancy submaps (sec. IV-E): integration into the current submap, a new submap when the depth
frustum's overlap with it falls below eps_vol, and submap poses that follow keyframe updates.

Submap j is anchored in M_j, the body frame S at its creation: ``T_WM = T_WS(creation)``. When the
estimator reports keyframes, each submap binds to the keyframe nearest its creation time (within a
tolerance) by the fixed offset ``T_KM = T_WK^-1 T_WM``; later keyframe updates then move it as
``T_WM = T_WK T_KM``, which keeps the map consistent after loop closures. At the end of a run the non-causal
trajectory (final bundle adjustment) moves every bound submap the same way (:meth:`SubmapMapper.follow_trajectory`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from shared.occupancy.blocks import BlockStore
from services.mapping.config import SensorModelConfig, SubmapConfig
from services.mapping.integrate import IntegrationResult, integrate
from services.mapping.mesh import ChunkMesher
from shared.occupancy.query import UNKNOWN, BlockField, interpolate, state
from services.mapping.sensor_model import prepare_depth
from shared.occupancy.uncertain_pixels import carve_only_pixels
from shared.geometry import inv_T


FROZEN = -2  # keyframe_id of submaps made before an estimator reset: their keyframes no longer exist


@dataclasses.dataclass
class Submap:
    id: int
    T_WM: np.ndarray
    anchor_stamp_ns: int
    store: BlockStore
    mesher: ChunkMesher
    n_frames: int = 0
    keyframe_id: int = -1  # keyframe this submap follows (-1: not bound yet; FROZEN: never moves again)
    T_KM: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    keyframe_stamp_ns: int = -1  # the bound keyframe's time
    pose_version: int = 0  # incremented when T_WM changes
    anchor_view: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # first frame: (depth 1/4 size, K, T_MC)

    def field(self) -> BlockField:
        return BlockField.of(self.store)


@dataclasses.dataclass(frozen=True)
class FrameReport:
    submap_id: int
    new_submap: bool
    overlap: float  # observed fraction of the frustum samples in the previous current submap (NaN if none)
    result: IntegrationResult


class SubmapMapper:
    """All submaps of one run; the algorithm behind the mapping service (no transport)."""

    def __init__(self, sensor: SensorModelConfig | None = None, submaps: SubmapConfig | None = None, seed: int = 0) -> None:
        self.sensor = sensor or SensorModelConfig()
        self.sensor.check()
        self.cfg = submaps or SubmapConfig()
        self.submaps: list[Submap] = []
        self._rng = np.random.default_rng(seed)

    @property
    def current(self) -> Submap | None:
        return self.submaps[-1] if self.submaps else None

    def estimator_reset(self) -> None:
        """The estimator restarted in a new world frame with new keyframe ids: freeze every existing submap
        where it is (no keyframe follows it any more) and start a new submap with the next frame, so that no
        submap mixes depth from two world frames."""
        for sm in self.submaps:
            sm.keyframe_id = FROZEN
        self._force_new = True

    def new_submap(self, T_WM: np.ndarray, stamp_ns: int) -> Submap:
        sm = Submap(len(self.submaps), np.array(T_WM, float), int(stamp_ns), BlockStore(self.sensor.voxel_size_m),
                    ChunkMesher(self.cfg.mesh_chunk_blocks))
        self.submaps.append(sm)
        return sm

    def overlap(self, submap: Submap, depth: np.ndarray, K: np.ndarray, T_WC: np.ndarray) -> float:
        """Fraction of points sampled uniformly in the observed frustum (random valid pixel, random range
        between near and its depth) that lie in space the submap has observed: its observed voxels
        (reference 'submap') or the free/surface space of its first frame (reference 'anchor')."""
        v, u = np.nonzero(np.isfinite(depth))
        if len(u) == 0:
            return float("nan")
        pick = self._rng.integers(0, len(u), self.cfg.overlap_samples)
        u, v = u[pick], v[pick]
        z = self.sensor.near_m + self._rng.random(len(u)) * (depth[v, u] - self.sensor.near_m)
        p_C = np.column_stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
        T_MC = inv_T(submap.T_WM) @ T_WC
        p_M = p_C @ T_MC[:3, :3].T + T_MC[:3, 3]
        if self.cfg.overlap_reference == "submap" or submap.anchor_view is None:
            return float(np.mean(state(submap.field(), p_M) != UNKNOWN))
        d_a, K_a, T_MA = submap.anchor_view
        T_AM = inv_T(T_MA)
        p_A = p_M @ T_AM[:3, :3].T + T_AM[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            ua = np.floor(K_a[0, 0] * p_A[:, 0] / p_A[:, 2] + K_a[0, 2] + 0.5)
            va = np.floor(K_a[1, 1] * p_A[:, 1] / p_A[:, 2] + K_a[1, 2] + 0.5)
        h, w = d_a.shape
        inside = (p_A[:, 2] > self.sensor.near_m) & (ua >= 0) & (ua < w) & (va >= 0) & (va < h)
        seen = np.zeros(len(p_A), bool)
        ui, vi = ua[inside].astype(np.int64), va[inside].astype(np.int64)
        seen[inside] = p_A[inside, 2] <= d_a[vi, ui] + 3.0 * self.sensor.sigma_min_m  # NaN depth: not seen
        return float(np.mean(seen))

    def integrate(self, depth: np.ndarray, sigma: np.ndarray | None, K: np.ndarray, T_WC: np.ndarray,
                  T_SC: np.ndarray, stamp_ns: int, surface_max_relative_sigma: float = 0.0) -> FrameReport:
        """Integrate one depth frame (raw depth/sigma: NaN invalid) seen from ``T_WC``; the body pose
        ``T_WS = T_WC T_SC^-1`` anchors a new submap when one starts. Pixels whose sigma exceeds
        ``surface_max_relative_sigma`` x depth (the DepthFrame's; 0: none) only free the space in front of them."""
        carve = None if sigma is None else carve_only_pixels(depth, sigma, surface_max_relative_sigma)
        d, s, _ = prepare_depth(depth, sigma, self.sensor)
        K = np.asarray(K, float)
        _check_inputs(K, T_WC, T_SC)
        cur = self.current
        ov = float("nan")
        new = cur is None or getattr(self, "_force_new", False)
        self._force_new = False
        if not new and cur.n_frames >= self.cfg.min_frames:
            ov = self.overlap(cur, d, K, T_WC)
            new = bool(ov < self.cfg.eps_vol)
        if new:
            if cur is not None:  # the closed submap no longer grows: keep voxels only near surfaces
                cur.store.coarsen_free(0.7 * self.sensor.l_min)
            cur = self.new_submap(T_WC @ inv_T(T_SC), stamp_ns)
        T_MC = inv_T(cur.T_WM) @ T_WC
        if cur.anchor_view is None:
            K4 = K.copy()
            K4[:2] /= 4.0
            K4[:2, 2] = (K[:2, 2] - 1.0) / 4.0  # pixel 4 i + 1 of the full image is pixel i of the subsampled one
            cur.anchor_view = (d[1::4, 1::4].copy(), K4, T_MC)
        res = integrate(cur.store, d, s, K, T_MC, self.sensor, carve)
        cur.mesher.mark(cur.store, res.updated_slots)
        cur.n_frames += 1
        return FrameReport(cur.id, new, ov, res)

    def update_keyframes(self, ids: np.ndarray, stamps_ns: np.ndarray, T_WS: np.ndarray) -> list[int]:
        """Apply an estimator keyframe update; returns the ids of submaps whose pose changed."""
        ids = np.asarray(ids, np.int64)
        stamps_ns = np.asarray(stamps_ns, np.int64)
        if len(ids) == 0:
            return []
        index = {int(k): i for i, k in enumerate(ids)}
        tol_ns = self.cfg.keyframe_bind_tolerance_s * 1e9
        moved = []
        for sm in self.submaps:  # a loop over submaps (tens), not voxels
            if sm.keyframe_id == FROZEN:
                continue
            if sm.keyframe_id < 0:
                i = int(np.argmin(np.abs(stamps_ns - sm.anchor_stamp_ns)))
                if abs(int(stamps_ns[i]) - sm.anchor_stamp_ns) <= tol_ns:
                    sm.keyframe_id = int(ids[i])
                    sm.keyframe_stamp_ns = int(stamps_ns[i])
                    sm.T_KM = inv_T(T_WS[i]) @ sm.T_WM
                continue
            i = index.get(sm.keyframe_id)
            if i is not None and self._follow(sm, T_WS[i]):
                moved.append(sm.id)
        return moved

    @staticmethod
    def _follow(sm: Submap, T_WK: np.ndarray) -> bool:
        """``T_WM = T_WK T_KM`` for the submap's keyframe pose T_WK; True when the pose changed."""
        T_new = np.asarray(T_WK, float) @ sm.T_KM
        if np.allclose(T_new, sm.T_WM, atol=1e-9):
            return False
        sm.T_WM = T_new
        sm.pose_version += 1
        return True

    def follow_trajectory(self, stamps_ns: np.ndarray, T_WS: np.ndarray) -> list[int]:
        """Move every bound submap onto a trajectory that has a pose at its keyframe's time (the final bundle
        adjustment's, one pose per published frame): ``T_WM = T_WS(keyframe) T_KM``. Returns the ids moved;
        submaps not bound, frozen, or whose keyframe the trajectory lacks stay where they are."""
        index = {int(s): i for i, s in enumerate(np.asarray(stamps_ns, np.int64))}
        moved = []
        for sm in self.submaps:
            i = index.get(sm.keyframe_stamp_ns) if sm.keyframe_id >= 0 else None
            if i is not None and self._follow(sm, T_WS[i]):
                moved.append(sm.id)
        return moved

    def remesh(self, budget_s: float | None = None) -> list[int]:
        """Re-mesh changed chunks (all, or within a time budget); returns ids of submaps whose mesh changed."""
        import time

        t0 = time.perf_counter()
        changed = []
        for sm in sorted(self.submaps, key=lambda s: -s.id):  # newest first: that is where changes are
            if len(sm.mesher.pending) == 0:
                continue
            left = None if budget_s is None else budget_s - (time.perf_counter() - t0)
            if left is not None and left <= 0:
                break
            if sm.mesher.update(sm.store, left):
                changed.append(sm.id)
        return changed

    def mesh(self, submap: Submap) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A submap's mesh as published and written (in M): vertices (V, 3) float32, faces (F, 3) int32 and each
        vertex's map uncertainty ``sigma_map = |l_min| / (3 ||grad L||)`` (eq. 7) [m], inf where the field gives
        none. Faces with a vertex whose sigma_map exceeds ``mesh_max_sigma_m`` are left out, and the vertices only
        they used (the occupancy map keeps what they came from; docs/mapping.md, 'Confident mesh')."""
        v, f = submap.mesher.mesh()
        if len(v) == 0:
            return v, f, np.empty(0, np.float32)
        _, g, valid = interpolate(submap.field(), v)
        with np.errstate(divide="ignore", invalid="ignore"):
            sig = abs(self.sensor.l_min) / (3.0 * np.linalg.norm(g, axis=1))
        sig = np.where(valid & np.isfinite(sig), sig, np.inf).astype(np.float32)
        limit = self.cfg.mesh_max_sigma_m
        if limit <= 0:
            return v, f, sig
        f = f[np.all(sig[f] <= limit, axis=1)]
        used = np.unique(f)
        index = np.full(len(v), -1, np.int64)
        index[used] = np.arange(len(used))
        return v[used], index[f].astype(np.int32), sig[used]

    def colored_mesh(self, submap: Submap, sigma_lo_m: float = 0.02, sigma_hi_m: float | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`mesh` with vertex colours from sigma_map: blue at ``sigma_lo_m`` to red at ``sigma_hi_m`` (None:
        ``mesh_max_sigma_m``, the least sure a face of the mesh can be, or 0.2 m when every face is kept)."""
        hi = sigma_hi_m if sigma_hi_m is not None else (self.cfg.mesh_max_sigma_m if self.cfg.mesh_max_sigma_m > 0
                                                         else 0.2)
        v, f, sig = self.mesh(submap)
        x = np.clip((np.minimum(sig, hi) - sigma_lo_m) / max(hi - sigma_lo_m, 1e-9), 0.0, 1.0)
        rgb = np.stack([np.clip(2 * x - 1, 0, 1), 1 - np.abs(2 * x - 1), np.clip(1 - 2 * x, 0, 1)], axis=1)
        return v, f, np.round(rgb * 255).astype(np.uint8).reshape(-1, 3)

    def world_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """All submap meshes (:meth:`mesh`) in W (vertices float32 [m], faces int32), combined with the submap
        poses."""
        return meshes_in_world([(sm.T_WM, *self.mesh(sm)[:2]) for sm in self.submaps])

    def nbytes(self) -> int:
        return sum(sm.store.nbytes() for sm in self.submaps)


def meshes_in_world(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """One mesh in W (vertices float32 [m], faces int32) from submap meshes ``(T_WM, vertices_M, faces)``."""
    verts, faces, off = [], [], 0
    for T_WM, v, f in parts:
        verts.append((v @ T_WM[:3, :3].T + T_WM[:3, 3]).astype(np.float32))
        faces.append(f + off)
        off += len(v)
    if not verts:
        return np.empty((0, 3), np.float32), np.empty((0, 3), np.int32)
    return np.concatenate(verts), np.concatenate(faces).astype(np.int32)


def _check_inputs(K: np.ndarray, T_WC: np.ndarray, T_SC: np.ndarray) -> None:
    """ValueError for intrinsics or poses that would corrupt the map."""
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"bad intrinsics K {K.tolist()}")
    for name, T in (("T_WC", T_WC), ("T_SC", T_SC)):
        T = np.asarray(T, float)
        if T.shape != (4, 4) or not np.isfinite(T).all() or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-4):
            raise ValueError(f"{name} is not a rigid transform")
