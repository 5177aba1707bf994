"""Occupancy of the combined map: every submap placed by its current pose in W, asked about points, segments and
axis-aligned boxes given in W. The algorithm behind ``<namespace>/map/query``, ``sigmaslam map query`` (a saved
map), the 2D grid, the 3D export and the safety figures; no transport.

How overlapping submaps are combined. A point p_W is taken into each submap's frame, ``p_M = T_WM^-1 p_W`` with the
submap's pose as it is now (after keyframe updates and loop closures, services/mapping/submaps.py), and looked up
in the voxel that holds it. Submaps that have not observed that voxel (w = 0, or outside their blocks) say nothing.
Of those that have, the combined log-odds is the *largest* L: a point is occupied when any submap that saw it says
occupied, free only when every submap that saw it says free, unknown when none saw it. Why not fuse them (add or
average the log-odds): submaps are placed by estimated poses that disagree by millimetres to centimetres, so the same
surface sits at slightly different places in two submaps; averaging lets one submap's free space in front of its
copy of the wall cancel the other's occupied voxel, which is a free answer inside a wall, the error a planner pays
for with a collision. The maximum fails safe: overlaps cost a little free space near surfaces, never a wall.
Occupied is ``L > occupied_above``, free ``L < free_below`` and anything between is reported unknown
(:class:`~services.mapping.config.QueryConfig`).

Segments (start, end, radius) and boxes (lo, hi) are tested at the points of a lattice ``sample_step_voxels`` voxels
apart covering the capsule or box (with the default half voxel, every voxel lying wholly inside the shape holds a
lattice point, whatever the submap's rotation). A snapshot (:meth:`CombinedMap.of`) holds references to the
submaps' arrays as they are; read while the mapping integrates in another thread it may see a voxel before or after
a frame, never outside its arrays (shared/occupancy/query.py reads bounds-checked).
"""

from __future__ import annotations

import dataclasses

import numba as nb
import numpy as np

from services.mapping.config import QueryConfig
from shared.occupancy.blocks import unpack_keys
from shared.occupancy.query import FREE, OCCUPIED, UNKNOWN, BlockField, _voxel

__all__ = ["CombinedMap", "SubmapView", "PointAnswer", "SegmentAnswer", "BoxAnswer", "UNKNOWN", "FREE", "OCCUPIED"]


@dataclasses.dataclass(frozen=True)
class SubmapView:
    """One submap as a query sees it: id, pose T_WM, its field, and the voxel index range its blocks span."""

    id: int
    T_WM: np.ndarray
    field: BlockField
    lo_ijk: np.ndarray  # (3,) int64, inclusive
    hi_ijk: np.ndarray  # (3,) int64, inclusive

    @classmethod
    def of(cls, submap_id: int, T_WM: np.ndarray, field: BlockField) -> SubmapView:
        T_WM = np.array(T_WM, np.float64)
        if len(field.keys_sorted):
            ijk = unpack_keys(field.keys_sorted)
            lo, hi = ijk.min(0) * field.block_size, (ijk.max(0) + 1) * field.block_size - 1
        else:
            lo, hi = np.zeros(3, np.int64), np.full(3, -1, np.int64)  # empty: nothing inside
        return cls(int(submap_id), T_WM, field, lo.astype(np.int64), hi.astype(np.int64))


@dataclasses.dataclass(frozen=True)
class PointAnswer:
    state: np.ndarray  # (N,) int8: UNKNOWN 0, FREE 1, OCCUPIED 2
    log_odds: np.ndarray  # (N,) float32: the combined (largest observed) L; NaN where no submap observed the point
    submaps: np.ndarray  # (N,) int16: how many submaps observed the point


@dataclasses.dataclass(frozen=True)
class SegmentAnswer:
    hit: np.ndarray  # (K,) bool: an occupied lattice point lies within radius of the segment
    hit_distance_m: np.ndarray  # (K,) float64: distance from start along the segment of the first one (NaN: none)
    hit_point_W: np.ndarray  # (K, 3) float64: that occupied point (NaN: none)
    free: np.ndarray  # (K,) bool: every lattice point of the capsule is free (none occupied, none unknown)
    unknown_fraction: np.ndarray  # (K,) float64: fraction of the capsule's lattice points that are unknown


@dataclasses.dataclass(frozen=True)
class BoxAnswer:
    any_occupied: np.ndarray  # (K,) bool
    occupied_fraction: np.ndarray  # (K,) float64: fraction of the box's lattice points occupied
    unknown_fraction: np.ndarray  # (K,) float64: fraction of the box's lattice points unknown


class CombinedMap:
    """The submaps of a map at one moment, queried in W (see the module docstring for how they combine)."""

    def __init__(self, views: list[SubmapView], voxel_size_m: float, cfg: QueryConfig | None = None) -> None:
        self.views, self.voxel_size_m, self.cfg = list(views), float(voxel_size_m), cfg or QueryConfig()
        if any(abs(v.field.voxel_size - self.voxel_size_m) > 1e-12 for v in self.views):
            raise ValueError("all submaps of a combined map must have one voxel size")
        n = len(self.views)
        T_MW = np.array([np.linalg.inv(v.T_WM) for v in self.views]).reshape(n, 4, 4)
        self._R, self._t = np.ascontiguousarray(T_MW[:, :3, :3]), np.ascontiguousarray(T_MW[:, :3, 3])
        self._lo = np.array([v.lo_ijk for v in self.views], np.int64).reshape(n, 3)
        self._hi = np.array([v.hi_ijk for v in self.views], np.int64).reshape(n, 3)
        self._lists = None if n == 0 else tuple(
            [np.ascontiguousarray(getattr(v.field, name)) for v in self.views]
            for name in ("keys_sorted", "slot_of_sorted", "coarse_L", "coarse_w", "vox_slot", "Lv", "wv"))
        self.block_size = self.views[0].field.block_size if self.views else 8

    @classmethod
    def of(cls, mapper, cfg: QueryConfig | None = None, submap_ids: list[int] | None = None) -> CombinedMap:
        """A snapshot of a :class:`~services.mapping.submaps.SubmapMapper`'s submaps (all, or ``submap_ids``)."""
        views = [SubmapView.of(sm.id, sm.T_WM, sm.field()) for sm in list(mapper.submaps)
                 if submap_ids is None or sm.id in submap_ids]
        return cls(views, mapper.sensor.voxel_size_m, cfg)

    # ------------------------------------------------------------------ points

    def log_odds(self, p_W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Combined L (float32, NaN unobserved) and the number of submaps observing, at points (N, 3) in W."""
        p = _points(p_W, "points", self.cfg.max_points)
        L, n = np.full(len(p), np.nan, np.float32), np.zeros(len(p), np.int16)
        if self._lists is not None and len(p):
            _combine(p, self._R, self._t, self._lo, self._hi, self.voxel_size_m, self.block_size, self._lists, L, n)
        return L, n

    def log_odds_many(self, p_W: np.ndarray, chunk: int = 500_000) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`log_odds` of any number of points, ``chunk`` at a time (for the map's own users: exports,
        evaluation; a request over the wire stays within ``max_points``)."""
        p = np.asarray(p_W, np.float64).reshape(-1, 3)
        parts = [self.log_odds(p[i:i + chunk]) for i in range(0, len(p), chunk)] or [self.log_odds(p)]
        return np.concatenate([a for a, _ in parts]), np.concatenate([b for _, b in parts])

    def classify(self, L: np.ndarray) -> np.ndarray:
        """UNKNOWN / FREE / OCCUPIED (int8) of combined log-odds (NaN: unknown)."""
        L = np.asarray(L)
        out = np.full(L.shape, UNKNOWN, np.int8)
        with np.errstate(invalid="ignore"):
            out[L > self.cfg.occupied_above] = OCCUPIED
            out[L < self.cfg.free_below] = FREE
        return out

    def points(self, p_W: np.ndarray) -> PointAnswer:
        L, n = self.log_odds(p_W)
        return PointAnswer(self.classify(L), L, n)

    # ------------------------------------------------------------------ segments and boxes

    @property
    def step_m(self) -> float:
        return self.cfg.sample_step_voxels * self.voxel_size_m

    def segments(self, start_W: np.ndarray, end_W: np.ndarray, radius_m: np.ndarray | float = 0.0) -> SegmentAnswer:
        """First occupied point and freeness of capsules (segment start -> end (K, 3) in W, radius (K,) [m])."""
        a = _points(start_W, "segment starts", self.cfg.max_points)
        b = _points(end_W, "segment ends", self.cfg.max_points)
        r = np.broadcast_to(np.asarray(radius_m, np.float64), (len(a),)) if len(a) else np.zeros(0)
        if a.shape != b.shape:
            raise ValueError(f"segment starts {a.shape} and ends {b.shape} differ in shape")
        if not np.isfinite(r).all() or (r < 0).any():
            raise ValueError("segment radii must be finite and >= 0")
        lattices = [_capsule_lattice(a[k], b[k], r[k], self.step_m) for k in range(len(a))]
        self._check_samples(sum(len(t) * len(d) for t, d, _ in lattices), "segments")
        samples = [a[k] + t[:, None, None] * u + d[None, :, :] for k, (t, d, u) in enumerate(lattices)]
        states = self._states_of(samples)
        K = len(a)
        hit, dist, point = np.zeros(K, bool), np.full(K, np.nan), np.full((K, 3), np.nan)
        free, unknown = np.zeros(K, bool), np.zeros(K)
        for k, ((t, d, _), st, pts) in enumerate(zip(lattices, states, samples)):
            st = st.reshape(len(t), len(d))
            occ = st == OCCUPIED
            rows = np.flatnonzero(occ.any(axis=1))
            if len(rows):
                i = rows[0]
                j = np.flatnonzero(occ[i])[np.argmin(np.linalg.norm(d[occ[i]], axis=1))]
                hit[k], dist[k], point[k] = True, t[i], pts[i, j]
            free[k] = bool((st == FREE).all())
            unknown[k] = float(np.mean(st == UNKNOWN))
        return SegmentAnswer(hit, dist, point, free, unknown)

    def boxes(self, lo_W: np.ndarray, hi_W: np.ndarray) -> BoxAnswer:
        """Any occupied point and the occupied and unknown fractions of axis-aligned boxes [lo, hi] (K, 3) in W."""
        lo = _points(lo_W, "box corners lo", self.cfg.max_points)
        hi = _points(hi_W, "box corners hi", self.cfg.max_points)
        if lo.shape != hi.shape or (hi < lo).any():
            raise ValueError("boxes need lo and hi of one shape (K, 3) with lo <= hi")
        counts = np.maximum(1, np.ceil((hi - lo) / self.step_m - 1e-9)).astype(np.int64)
        self._check_samples(int(np.prod(counts, axis=1).sum()), "boxes")
        samples = []
        for k in range(len(lo)):
            axes = [lo[k, i] + (np.arange(counts[k, i]) + 0.5) * (hi[k, i] - lo[k, i]) / counts[k, i] for i in range(3)]
            samples.append(np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3))
        states = self._states_of(samples)
        occ = np.array([float(np.mean(s == OCCUPIED)) for s in states])
        unk = np.array([float(np.mean(s == UNKNOWN)) for s in states])
        return BoxAnswer(occ > 0, occ, unk)

    def _check_samples(self, n: int, what: str) -> None:
        if n > self.cfg.max_samples:
            raise ValueError(f"the {what} need {n} lattice points, more than max_samples = {self.cfg.max_samples}: "
                             "ask for fewer or smaller shapes")

    def _states_of(self, samples: list[np.ndarray]) -> list[np.ndarray]:
        """States of several point sets, queried in one call."""
        if not samples:
            return []
        flat = np.concatenate([s.reshape(-1, 3) for s in samples])
        L, n = np.full(len(flat), np.nan, np.float32), np.zeros(len(flat), np.int16)
        if self._lists is not None:
            _combine(np.ascontiguousarray(flat), self._R, self._t, self._lo, self._hi, self.voxel_size_m,
                     self.block_size, self._lists, L, n)
        st = self.classify(L)
        return np.split(st, np.cumsum([s.size // 3 for s in samples])[:-1])


def warm_up(voxel_size_m: float = 0.025) -> None:
    """Load the compiled query kernel (numba's on-disk cache) with an empty submap, so that a process's first
    query does not pay for it."""
    from shared.occupancy.blocks import BlockStore

    store = BlockStore(voxel_size_m)
    CombinedMap([SubmapView.of(0, np.eye(4), BlockField.of(store))], voxel_size_m).points(np.zeros((1, 3)))


def _points(p: np.ndarray, what: str, max_points: int) -> np.ndarray:
    """``p`` as a C-contiguous (N, 3) float64 array; ValueError for a wrong shape, non-finite values or too many."""
    try:
        p = np.asarray(p, np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: not numbers ({exc})") from None
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{what} must be an (N, 3) array, got shape {p.shape}")
    if len(p) > max_points:
        raise ValueError(f"{what}: {len(p)} of them, more than max_points = {max_points}")
    if not np.isfinite(p).all():
        raise ValueError(f"{what}: {int((~np.isfinite(p).all(axis=1)).sum())} rows hold NaN or infinity")
    return np.ascontiguousarray(p)


def _capsule_lattice(a: np.ndarray, b: np.ndarray, r: float, step: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lattice of a capsule: distances t along the axis (T,), offsets across it (D, 3) (the axis itself first) and
    the unit axis u; the points are ``a + t u + offset``."""
    axis = b - a
    length = float(np.linalg.norm(axis))
    u = axis / length if length > 0 else np.array([1.0, 0.0, 0.0])
    t = np.linspace(0.0, length, int(np.ceil(length / step)) + 1)
    e1 = np.cross(u, [0.0, 0.0, 1.0] if abs(u[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    m = int(np.floor(r / step))
    g = np.arange(-m, m + 1) * step
    gx, gy = np.meshgrid(g, g, indexing="ij")
    keep = gx**2 + gy**2 <= r * r + 1e-12
    ab = np.column_stack([gx[keep], gy[keep]])
    ab = ab[np.argsort(np.hypot(ab[:, 0], ab[:, 1]), kind="stable")]  # (0, 0) first
    return t, ab[:, :1] * e1 + ab[:, 1:] * e2, u


def _combine(p, R, t, lo, hi, vs, b, lists, L, n_obs) -> None:
    """Per point: the largest L over the submaps that observed its voxel, and how many did (module docstring);
    one compiled pass per submap (plain arrays: the compiled code is cached on disk)."""
    best = np.full(p.shape[0], -np.inf, np.float32)
    for s in range(R.shape[0]):
        _combine_one(p, R[s], t[s], lo[s], hi[s], vs, b, *(a[s] for a in lists), best, n_obs)
    seen = n_obs > 0
    L[seen] = best[seen]


@nb.njit(cache=True)
def _combine_one(p, R, t, lo, hi, vs, b, keys, slots, cL, cw, vslot, Lv, wv, best, n_obs):
    memo = np.full(2, -1, np.int64)
    for r in range(p.shape[0]):
        x = R[0, 0] * p[r, 0] + R[0, 1] * p[r, 1] + R[0, 2] * p[r, 2] + t[0]
        y = R[1, 0] * p[r, 0] + R[1, 1] * p[r, 1] + R[1, 2] * p[r, 2] + t[1]
        z = R[2, 0] * p[r, 0] + R[2, 1] * p[r, 1] + R[2, 2] * p[r, 2] + t[2]
        i, j, k = np.int64(np.floor(x / vs)), np.int64(np.floor(y / vs)), np.int64(np.floor(z / vs))
        if i < lo[0] or i > hi[0] or j < lo[1] or j > hi[1] or k < lo[2] or k > hi[2]:
            continue
        Lq, wq = _voxel(i, j, k, b, keys, slots, cL, cw, vslot, Lv, wv, memo)
        if wq > 0:
            n_obs[r] += 1
            if Lq > best[r]:
                best[r] = Lq
