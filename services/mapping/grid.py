"""The 2D occupancy grid of the combined map over a height band of the gravity-aligned world frame W, for
navigation stacks: published on ``map/grid``, written as ``occupancy_grid.pgm`` + ``.yaml`` (services/mapping/
grid_files.py), and what the planner example plans on.

The band is ``[floor + band_min_m, floor + band_max_m]`` in W. The floor is the fullest horizontal layer of occupied
voxels in the lower half of the map (``floor: map``; every occupied voxel centre's height in W, binned at the voxel
size), or a given height (``floor: fixed``). Cells lie on a lattice of ``resolution_m`` anchored at W's origin, row 0
at the lowest y (as nav_msgs/OccupancyGrid). Each submap is rasterised on its own, every observed voxel whose centre
(placed by the submap's current pose) lies in the band counted in the cell under it, and the submaps combine with
the rule of the point queries (services/mapping/combined.py): a cell is

- occupied (100) when any submap has an occupied voxel (L > occupied_above) in its band,
- else unknown (255) when the submaps' uncertain voxels there (free_below <= L <= occupied_above), summed over the
  submaps, are more than ``max_uncertain_fraction`` of the voxel centres a cell's band holds on average, or when
  less than ``min_free_fraction`` of the band's levels (one voxel high, at most 64 of them) hold a voxel observed
  free in the cell by some submap, or a submap's free voxel centres in the cell are fewer than 0.9 of those a cell
  holds on average (counts alone vary with a submap's rotation against the cells, levels alone miss a cell that is
  partly unobserved),
- else free (0).

A submap's raster is kept while the submap and the band stay the same and its pose moves no corner of its blocks' box
by more than a quarter cell, so the live grid costs the re-rasterising of the growing submap and of those a keyframe
update moved that far. A coarse block (free space carved as a whole: one value) is rasterised at every other voxel
centre along each axis, each standing for 8.
"""

from __future__ import annotations

import dataclasses

import numba as nb
import numpy as np

from services.mapping.config import GridConfig, QueryConfig
from shared.codec import Header
from shared.messages import OccupancyGrid2D
from shared.occupancy.blocks import unpack_keys

FREE_CELL, OCCUPIED_CELL, UNKNOWN_CELL = 0, 100, 255


@dataclasses.dataclass(frozen=True)
class Grid2D:
    """A 2D grid: ``cells`` (H, W) uint8 (0 free, 100 occupied, 255 unknown), row r / column c covering
    ``origin_xy_m + ([c, c + 1), [r, r + 1)) * resolution_m`` in W, over the band ``z_band_m`` of W."""

    cells: np.ndarray
    resolution_m: float
    origin_xy_m: np.ndarray
    z_band_m: np.ndarray
    floor_z_m: float

    def message(self, stamp_ns: int, seq: int = 0) -> OccupancyGrid2D:
        return OccupancyGrid2D(header=Header(stamp_ns=int(stamp_ns), seq=seq, frame_id="W"),
                               resolution_m=float(self.resolution_m), origin_xy_m=np.asarray(self.origin_xy_m, float),
                               z_band_m=np.asarray(self.z_band_m, float), cells=self.cells)

    def cell_of(self, xy_W: np.ndarray) -> np.ndarray:
        """(row, col) int64 of points (N, 2) in W (may lie outside the grid)."""
        c = np.floor((np.asarray(xy_W, float).reshape(-1, 2) - self.origin_xy_m) / self.resolution_m).astype(np.int64)
        return c[:, ::-1]

    def centres_W(self) -> tuple[np.ndarray, np.ndarray]:
        """x (W,) and y (H,) of the cell centres [m]."""
        h, w = self.cells.shape
        return (self.origin_xy_m[0] + (np.arange(w) + 0.5) * self.resolution_m,
                self.origin_xy_m[1] + (np.arange(h) + 0.5) * self.resolution_m)


class GridBuilder:
    """Builds the grid of a :class:`~services.mapping.submaps.SubmapMapper`, keeping each submap's raster while it
    does not change."""

    def __init__(self, cfg: GridConfig | None = None, query: QueryConfig | None = None) -> None:
        self.cfg, self.query = cfg or GridConfig(), query or QueryConfig()
        self._z: dict[int, tuple] = {}
        self._rasters: dict[int, tuple] = {}

    def floor_z(self, mapper) -> float | None:
        """The floor's height in W (None: no occupied voxel yet, with floor: map)."""
        if self.cfg.floor == "fixed":
            return float(self.cfg.floor_z_m)
        zs = []
        for sm in list(mapper.submaps):
            key = (sm.store.n_blocks, sm.store.n_refined, sm.n_frames)
            got = self._z.get(sm.id)
            if got is None or got[0] != key or _moved(got[2], sm, mapper.sensor.voxel_size_m / 2):
                got = (key, _occupied_heights(sm, self.query.occupied_above), np.array(sm.T_WM))
                self._z[sm.id] = got
            zs.append(got[1])
        z = np.concatenate(zs) if zs else np.zeros(0)
        if len(z) == 0:
            return None
        vs = mapper.sensor.voxel_size_m
        low = z[z <= np.median(z)]
        bins = np.floor(low / vs).astype(np.int64)
        values, counts = np.unique(bins, return_counts=True)
        return float((values[np.argmax(counts)] + 1) * vs)  # occupied voxels lie just below the surface

    def build(self, mapper) -> Grid2D | None:
        """The grid now (None: nothing mapped yet)."""
        vs = mapper.sensor.voxel_size_m
        res = self.cfg.resolution_m
        if res < vs:
            raise ValueError(f"grid.resolution_m {res} is finer than the voxels ({vs} m)")
        floor = self.floor_z(mapper)
        if floor is None:
            return None
        band = (floor + self.cfg.band_min_m, floor + self.cfg.band_max_m)
        rasters = []
        for sm in list(mapper.submaps):
            key = (sm.store.n_blocks, sm.store.n_refined, sm.n_frames, band, res)
            got = self._rasters.get(sm.id)
            if got is None or got[0] != key or _moved(got[2], sm, res / 4):
                got = (key, _raster(sm, band, res, self.query), np.array(sm.T_WM))
                self._rasters[sm.id] = got
            if got[1] is not None:
                rasters.append(got[1])
        if not rasters:
            return None
        return _combine_rasters(rasters, band, res, vs, floor, self.cfg.min_free_fraction,
                                self.cfg.max_uncertain_fraction)


def _moved(T_old: np.ndarray, sm, tol_m: float) -> bool:
    """Whether the submap's pose moved any corner of its blocks' box by more than ``tol_m`` since ``T_old``."""
    ijk = sm.store.keys[: sm.store.n_blocks]
    if len(ijk) == 0:
        return False
    from shared.occupancy.blocks import unpack_keys

    c = unpack_keys(ijk)
    bm = sm.store.block_size * sm.store.voxel_size
    lo, hi = c.min(0) * bm, (c.max(0) + 1) * bm
    box = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return bool(np.abs(box @ (np.asarray(sm.T_WM) - T_old).T).max() > tol_m)


def _combine_rasters(rasters, band, res, vs, floor, min_free, max_uncertain) -> Grid2D:
    x0 = min(r[0] for r in rasters)
    y0 = min(r[1] for r in rasters)
    x1 = max(r[0] + r[4].shape[1] for r in rasters)
    y1 = max(r[1] + r[4].shape[0] for r in rasters)
    occ = np.zeros((y1 - y0, x1 - x0), bool)
    unsure = np.zeros(occ.shape)
    seen = np.zeros(occ.shape, np.uint64)
    count = np.zeros(occ.shape)
    for cx, cy, o, u, levels, n_free in rasters:
        sl = np.s_[cy - y0: cy - y0 + o.shape[0], cx - x0: cx - x0 + o.shape[1]]
        occ[sl] |= o
        unsure[sl] += u
        seen[sl] |= levels
        count[sl] = np.maximum(count[sl], n_free)
    cover = np.unpackbits(seen[..., None].view(np.uint8), axis=-1).sum(axis=-1) / _levels(band, vs)[1]
    # and free voxel centres against those a cell holds on average: a cell whose band is partly unobserved (an
    # object's unseen side) has too few, however its levels are covered
    full = (res / vs) ** 2 * (band[1] - band[0]) / vs
    dense = count >= 0.9 * full
    # a few uncertain voxels in a column (seen once, far, at a grazing angle) do not make it unknown; a surface's
    # ramp (eq. 3) in front of an object in the cell comes with its occupied voxels, which make the cell occupied
    sure = unsure <= max_uncertain * full
    cells = np.full(occ.shape, UNKNOWN_CELL, np.uint8)
    cells[(cover >= min_free) & dense & sure] = FREE_CELL
    cells[occ] = OCCUPIED_CELL
    return Grid2D(cells, res, np.array([x0 * res, y0 * res]), np.array(band, float), floor)


def _levels(band, vs: float) -> tuple[float, int]:
    """Height of one level of the band and how many there are (at most 64: one bit each)."""
    h = max(vs, (band[1] - band[0]) / 64)
    return h, max(int(np.ceil((band[1] - band[0]) / h - 1e-9)), 1)


def _block_arrays(sm):
    st = sm.store
    n = st.n_blocks
    return unpack_keys(st.keys[:n]), st.coarse_L[:n], st.coarse_w[:n], st.vox_slot[:n], st.Lv, st.wv


def _occupied_heights(sm, occupied_above: float) -> np.ndarray:
    """Heights in W of the centres of a submap's occupied voxels."""
    ijk, cL, cw, vslot, Lv, wv = _block_arrays(sm)
    refined = np.flatnonzero(vslot >= 0)
    if len(refined) == 0:
        return np.zeros(0)
    rows = vslot[refined]
    b = sm.store.block_size
    occ = (Lv[rows] > occupied_above) & (wv[rows] > 0)
    blk, i, j, k = np.nonzero(occ)
    c = ((ijk[refined][blk] * b + np.column_stack([i, j, k])) + 0.5) * sm.store.voxel_size
    return c @ sm.T_WM[2, :3] + sm.T_WM[2, 3]


def _raster(sm, band, res, q: QueryConfig):
    """(cell x0, cell y0, occupied, uncertain-voxel count, free levels, free-voxel count) of one submap over its
    footprint, or None."""
    ijk, cL, cw, vslot, Lv, wv = _block_arrays(sm)
    if len(ijk) == 0:
        return None
    st = sm.store
    bm = st.block_size * st.voxel_size
    corners = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], float) * bm
    lo_M, hi_M = ijk.min(0) * bm, (ijk.max(0) + 1) * bm
    box = lo_M + corners / bm * (hi_M - lo_M)
    box_W = box @ sm.T_WM[:3, :3].T + sm.T_WM[:3, 3]
    cx0, cy0 = np.floor(box_W[:, :2].min(0) / res).astype(np.int64)
    cx1, cy1 = np.floor(box_W[:, :2].max(0) / res).astype(np.int64) + 1
    occ = np.zeros((cy1 - cy0, cx1 - cx0), bool)
    unsure, levels, n_free = np.zeros(occ.shape, np.int32), np.zeros(occ.shape, np.uint64), np.zeros(occ.shape, np.int32)
    _rasterise(np.ascontiguousarray(ijk), cL, cw, vslot, Lv, wv, np.ascontiguousarray(sm.T_WM[:3, :3]),
               np.ascontiguousarray(sm.T_WM[:3, 3]), st.voxel_size, st.block_size, band[0], band[1],
               cx0 * res, cy0 * res, res, q.occupied_above, q.free_below, _levels(band, st.voxel_size)[0], occ,
               unsure, levels, n_free)
    return int(cx0), int(cy0), occ, unsure, levels, n_free


def warm_up() -> None:
    """Load the compiled rasteriser (numba's on-disk cache) on one empty block, so that the first live grid does not
    pay for it."""
    b = 8
    occ = np.zeros((1, 1), bool)
    _rasterise(np.zeros((1, 3), np.int64), np.zeros(1, np.float32), np.zeros(1, np.uint16), np.full(1, -1, np.int32),
               np.zeros((1, b, b, b), np.float32), np.zeros((1, b, b, b), np.uint16), np.eye(3), np.zeros(3), 0.025, b,
               0.0, 1.0, 0.0, 0.0, 0.05, 0.0, -2.5, 0.025, occ, np.zeros((1, 1), np.int32), np.zeros((1, 1), np.uint64),
               np.zeros((1, 1), np.int32))


@nb.njit(cache=True)
def _rasterise(ijk, cL, cw, vslot, Lv, wv, R, t, vs, b, z0, z1, ox, oy, res, occ_above, free_below, level_m, occ,
               unsure, levels, n_free):
    half = 0.5 * np.sqrt(3.0) * b * vs
    ny, nx = occ.shape
    for s in range(ijk.shape[0]):
        cz = (ijk[s, 0] * b + 0.5 * b) * vs * R[2, 0] + (ijk[s, 1] * b + 0.5 * b) * vs * R[2, 1] \
            + (ijk[s, 2] * b + 0.5 * b) * vs * R[2, 2] + t[2]
        if cz + half < z0 or cz - half >= z1:
            continue
        v = vslot[s]
        if v < 0 and cw[s] == 0:
            continue
        for i in range(b):
            for j in range(b):
                for k in range(b):
                    if v >= 0:
                        L, w = Lv[v, i, j, k], wv[v, i, j, k]
                    else:
                        L, w = cL[s], cw[s]
                    if w == 0:
                        continue
                    px = (ijk[s, 0] * b + i + 0.5) * vs
                    py = (ijk[s, 1] * b + j + 0.5) * vs
                    pz = (ijk[s, 2] * b + k + 0.5) * vs
                    z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
                    if z < z0 or z >= z1:
                        continue
                    x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
                    y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
                    c, r = int(np.floor((x - ox) / res)), int(np.floor((y - oy) / res))
                    if c < 0 or c >= nx or r < 0 or r >= ny:
                        continue
                    if L > occ_above:
                        occ[r, c] = True
                    elif L >= free_below:
                        unsure[r, c] += 1
                    else:
                        levels[r, c] |= np.uint64(1) << np.uint64(min(int((z - z0) / level_m), 63))
                        n_free[r, c] += 1
