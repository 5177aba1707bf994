"""The safety figures of an occupancy map, measured against a replica's exact scene mesh (``sigmaslam eval occupancy``).

Ground truth of a point: *near* a surface when its distance to the scene mesh is below one voxel; *inside* an object
when most of six axis-aligned rays from it (4 or more) first meet a surface from behind (its normal facing away) or
meet nothing (outside the room's closed box); the scene's faces point into free space
(services/app/synth/scene.py). Ground-truth free is neither.

- Voxels: centres of voxels of W's lattice (the 3D export's, services/mapping/voxel_export.py) drawn uniformly in the
  box the map's submaps span, each asked of the combined map (services/mapping/combined.py) and of each submap
  alone. *False free* = the share of voxels reported free whose centre is near a surface or inside an object; *free
  recall* = the share of ground-truth free voxels inside the observed volume (some submap observed them) that are
  reported free.
- Grid cells: each cell's column over the height band, sampled at the voxel size across it (corners, edges, centre)
  and along it. A cell is ground-truth free when no sample is near a surface or inside an object; observed when some
  sample's voxel was observed. *False free* = the share of free cells that are not ground-truth free; *free recall*
  = the share of observed ground-truth free cells that are free. Free recall is also given over the cells whose
  whole band was observed (every sample's voxel): what the camera never saw of a column keeps a cell unknown, so
  the gap between the two recalls is coverage, not the map's rule.

The map is in the run's world frame W; the mesh is brought into it by the SE(3) alignment of the run's trajectory to
the ground truth (:func:`shared.metrics.ate.run_alignment`), so the figures include the estimator's error where
the map was placed.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from services.mapping.combined import FREE, CombinedMap
from services.mapping.grid import FREE_CELL, Grid2D

_DIRS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float32)


class SceneTruth:
    """Near-surface and inside tests of points against a triangle mesh (open3d ray casting)."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, voxel_size_m: float) -> None:
        import open3d as o3d

        self.o3d, self.voxel_size_m = o3d, float(voxel_size_m)
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d.core.Tensor(np.asarray(vertices, np.float32))
        mesh.triangle.indices = o3d.core.Tensor(np.asarray(triangles, np.int32))
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(mesh)

    @classmethod
    def in_band(cls, vertices: np.ndarray, triangles: np.ndarray, T_W_gt: np.ndarray, z_band_m, voxel_size_m: float
                ) -> SceneTruth:
        """The mesh moved into W by ``T_W_gt``, keeping only the triangles that reach into the height band of W:
        what a robot moving on the floor can touch (the floor itself and the ceiling left out)."""
        v = np.asarray(vertices, float) @ T_W_gt[:3, :3].T + T_W_gt[:3, 3]
        z = v[np.asarray(triangles)][:, :, 2]
        keep = (z.max(axis=1) >= z_band_m[0]) & (z.min(axis=1) <= z_band_m[1])
        return cls(v, np.asarray(triangles)[keep], voxel_size_m)

    def distance(self, p: np.ndarray) -> np.ndarray:
        """Distance [m] of points (N, 3) to the mesh."""
        return self.scene.compute_distance(self.o3d.core.Tensor(np.asarray(p, np.float32).reshape(-1, 3))).numpy()

    def classify(self, p: np.ndarray, chunk: int = 400_000) -> tuple[np.ndarray, np.ndarray]:
        """(near, inside) bool masks of points (N, 3) in the mesh's frame."""
        p = np.asarray(p, np.float32).reshape(-1, 3)
        near, inside = np.zeros(len(p), bool), np.zeros(len(p), bool)
        for a in range(0, len(p), chunk):
            q = p[a:a + chunk]
            d = self.scene.compute_distance(self.o3d.core.Tensor(q)).numpy()
            near[a:a + chunk] = d < self.voxel_size_m
            behind = np.zeros(len(q), np.int32)
            for u in _DIRS:
                rays = np.concatenate([q, np.broadcast_to(u, q.shape)], axis=1)
                hit = self.scene.cast_rays(self.o3d.core.Tensor(np.ascontiguousarray(rays)))
                t, n = hit["t_hit"].numpy(), hit["primitive_normals"].numpy()
                behind += (~np.isfinite(t)) | (n @ u > 0)
            inside[a:a + chunk] = behind >= 4
        return near, inside


@dataclasses.dataclass(frozen=True)
class SafetyFigures:
    false_free: float  # share of free answers that are near a surface or inside an object
    free_recall: float  # share of observed ground-truth free answered free
    free: int  # free answers (points or cells)
    false_free_count: int
    gt_free_observed: int  # observed ground-truth free points or cells
    free_recall_whole_band: float | None = None  # grid only: free recall over the cells whose whole band was observed

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def _figures(free: np.ndarray, gt_free: np.ndarray, observed: np.ndarray) -> SafetyFigures:
    wrong = int((free & ~gt_free).sum())
    base = gt_free & observed
    return SafetyFigures(wrong / max(int(free.sum()), 1), float((free & base).sum()) / max(int(base.sum()), 1),
                         int(free.sum()), wrong, int(base.sum()))


def voxel_figures(cm: CombinedMap, truth: SceneTruth, T_gt_W: np.ndarray, n: int = 300_000, seed: int = 0
                  ) -> tuple[SafetyFigures, dict[int, SafetyFigures]]:
    """Combined and per-submap figures of ``n`` voxels drawn in the map's box (W); ``T_gt_W`` takes W into the
    mesh's frame."""
    from services.mapping.voxel_export import lattice_bounds

    bounds = lattice_bounds(cm)
    if bounds is None:
        raise ValueError("the map is empty")
    ijk = np.random.default_rng(seed).integers(bounds[0], bounds[1] + 1, (n, 3))
    p = (ijk + 0.5) * cm.voxel_size_m  # centres of voxels of W's lattice (services/mapping/voxel_export.py)
    near, inside = truth.classify(p @ T_gt_W[:3, :3].T + T_gt_W[:3, 3])
    gt_free = ~near & ~inside
    got = cm.points(p)
    combined = _figures(got.state == FREE, gt_free, got.submaps > 0)
    per = {}
    for v in cm.views:
        one = CombinedMap([v], cm.voxel_size_m, cm.cfg).points(p)
        per[v.id] = _figures(one.state == FREE, gt_free, one.submaps > 0)
    return combined, per


def column_samples(grid: Grid2D, rows: np.ndarray, cols: np.ndarray, step_m: float) -> np.ndarray:
    """Points (len(rows), S, 3) in W sampling each cell's column over the band: an xy lattice of ``step_m`` that
    includes the cell's edges, and heights ``step_m`` apart including the band's ends."""
    r = grid.resolution_m
    k = max(int(np.ceil(r / step_m)), 1)
    a = np.linspace(0.0, r, k + 1)
    nz = max(int(np.ceil((grid.z_band_m[1] - grid.z_band_m[0]) / step_m)), 1)
    z = np.linspace(grid.z_band_m[0], grid.z_band_m[1], nz + 1)
    ax, ay, az = np.meshgrid(a, a, z, indexing="ij")
    offs = np.column_stack([ax.ravel(), ay.ravel(), az.ravel()])
    corner = np.column_stack([grid.origin_xy_m[0] + cols * r, grid.origin_xy_m[1] + rows * r, np.zeros(len(rows))])
    return corner[:, None, :] + offs[None, :, :]


def grid_figures(grid: Grid2D, cm: CombinedMap, truth: SceneTruth, T_gt_W: np.ndarray, max_cells: int = 6000,
                 seed: int = 0) -> SafetyFigures:
    """The grid's figures, each cell's column sampled at the voxel size: false free over (at most ``max_cells``,
    drawn at random) free cells, free recall over ``max_cells`` cells drawn at random from the whole grid."""
    rng = np.random.default_rng(seed)
    h, w = grid.cells.shape
    free_cells = np.flatnonzero(grid.cells.ravel() == FREE_CELL)
    a = rng.choice(free_cells, min(max_cells, len(free_cells)), replace=False)
    b = rng.choice(h * w, min(max_cells, h * w), replace=False)
    pick, where = np.unique(np.concatenate([a, b]), return_inverse=True)
    rows, cols = np.divmod(pick, w)
    pts = column_samples(grid, rows, cols, truth.voxel_size_m)
    flat = pts.reshape(-1, 3)
    near, inside = truth.classify(flat @ T_gt_W[:3, :3].T + T_gt_W[:3, 3])
    gt_free = ~(near | inside).reshape(pts.shape[:2]).any(axis=1)
    seen = (cm.log_odds_many(flat)[1] > 0).reshape(pts.shape[:2])
    observed, whole = seen.any(axis=1), seen.all(axis=1)
    free = grid.cells.ravel()[pick] == FREE_CELL
    ia, ib = where[: len(a)], where[len(a):]
    wrong = int((~gt_free[ia]).sum())
    base, base_whole = gt_free[ib] & observed[ib], gt_free[ib] & whole[ib]
    return SafetyFigures(wrong / max(len(ia), 1), float((free[ib] & base).sum()) / max(int(base.sum()), 1),
                         int(len(free_cells)), wrong, int(base.sum()),
                         float((free[ib] & base_whole).sum()) / max(int(base_whole.sum()), 1))
