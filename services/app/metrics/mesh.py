"""Mesh accuracy and completeness as in the paper's sec. V.

Protocol: the estimated mesh's vertices and points of the ground truth are downsampled on a 1 cm
voxel grid; point-to-plane ICP aligns the estimate to the ground truth; accuracy is the mean
distance from every (aligned) estimated point to its nearest ground-truth point (no threshold);
completeness is the fraction of ground-truth points within 0.2 m (also reported at 5 cm) of the
estimate. A ground-truth *mesh* with large triangles has too few vertices to measure against, so its
surface is sampled densely first (``gt_sample_spacing_m``, each sample with its triangle's normal); a point cloud
is used as it is (normals estimated). The prepared ground truth is cached per file (:func:`load_ground_truth`),
and the ICP is estimated from a fixed subset of the estimate: a 25 s demo map is evaluated in seconds.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree


@dataclasses.dataclass(frozen=True)
class MeshEvalResult:
    accuracy_m: float  # mean distance estimate -> ground truth [m]
    completeness: float  # fraction of ground truth within completeness_threshold_m
    completeness_5cm: float
    completeness_threshold_m: float
    accuracy_median_m: float
    n_est: int
    n_gt: int
    icp_fitness: float
    T_gt_est: np.ndarray  # ICP correction applied to the estimate (4x4)

    def summary(self) -> dict:
        d = dataclasses.asdict(self)
        d["T_gt_est"] = self.T_gt_est.tolist()
        return d


def load_points(path: str | Path, sample_spacing_m: float | None = None, max_points: int = 4_000_000) -> np.ndarray:
    """Points of a PLY/OBJ mesh or point cloud: mesh vertices, or (with ``sample_spacing_m``) points
    sampled uniformly on the mesh surface at about that spacing."""
    return _read_cloud(path, sample_spacing_m, max_points)[0]


def _read_cloud(path: str | Path, sample_spacing_m: float | None, max_points: int = 4_000_000):
    """(points, normals or None) of a mesh or point cloud file; surface samples carry their triangle's normal."""
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        pts = np.asarray(o3d.io.read_point_cloud(str(path)).points)
        return (pts if len(pts) else np.asarray(mesh.vertices)), None
    if sample_spacing_m is None:
        return np.asarray(mesh.vertices), None
    n = int(min(max_points, max(1000, mesh.get_surface_area() / sample_spacing_m ** 2)))
    mesh.compute_triangle_normals()
    o3d.utility.random.seed(0)  # the same samples every time
    pc = mesh.sample_points_uniformly(n, use_triangle_normal=True)
    return np.asarray(pc.points), np.asarray(pc.normals)


def _downsample(points: np.ndarray, voxel_m: float, normals: np.ndarray | None = None):
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    pc = pc.voxel_down_sample(voxel_m) if voxel_m > 0 else pc
    if normals is not None:
        pc.normalize_normals()  # the voxel's mean normal
    return pc


@dataclasses.dataclass(frozen=True)
class GroundTruthCloud:
    """Ground truth ready for the protocol: downsampled points with normals (point-to-plane ICP) and a k-d tree."""

    points: np.ndarray  # (N, 3) float64 [m], on the ``voxel_m`` grid
    normals: np.ndarray  # (N, 3) float64, unit
    voxel_m: float
    tree: cKDTree = dataclasses.field(repr=False, compare=False)

    @classmethod
    def from_arrays(cls, points: np.ndarray, normals: np.ndarray, voxel_m: float) -> "GroundTruthCloud":
        points = np.asarray(points, np.float64)
        return cls(points, np.asarray(normals, np.float64), voxel_m, cKDTree(points, balanced_tree=False))

    @functools.cached_property
    def _nns(self):
        import open3d as o3d

        nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(self.points))
        nns.knn_index()
        return nns

    def distances(self, query: np.ndarray) -> np.ndarray:
        """Exact distance [m] from each query point (M, 3) to its nearest ground-truth point (open3d's multithreaded
        search: far points make scipy's unbounded query slow)."""
        import open3d as o3d

        _, d2 = self._nns.knn_search(o3d.core.Tensor(np.asarray(query, np.float64)), 1)
        return np.sqrt(d2.numpy()[:, 0].astype(np.float64))

    def cloud(self):
        import open3d as o3d

        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points))
        pc.normals = o3d.utility.Vector3dVector(self.normals)
        return pc


def prepare_points(gt: np.ndarray, voxel_m: float, normals: np.ndarray | None = None) -> GroundTruthCloud:
    """A ground truth from points (normals estimated from the neighbourhood when not given)."""
    import open3d as o3d

    pg = _downsample(gt, voxel_m, normals)
    if normals is None:
        pg.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=max(5 * voxel_m, 0.05), max_nn=30))
    return GroundTruthCloud.from_arrays(np.asarray(pg.points), np.asarray(pg.normals), voxel_m)


_GT_PREPARED: dict = {}
CACHE_VERSION = 1  # bump when the preparation changes: older cache files are then not read


def _cache_file(path: Path, voxel_m: float, sample_spacing_m: float | None) -> Path:
    import hashlib

    from shared.paths import data_dir

    st = path.stat()
    key = f"{CACHE_VERSION}|{path.resolve()}|{st.st_size}|{st.st_mtime_ns}|{voxel_m}|{sample_spacing_m}"
    return data_dir() / "cache" / "mesh_gt" / f"{hashlib.sha1(key.encode()).hexdigest()[:16]}.npz"


def load_ground_truth(path: str | Path, voxel_m: float = 0.01, sample_spacing_m: float | None = 0.005,
                      cache: bool = True, progress=None) -> GroundTruthCloud:
    """The ground truth of a mesh or point-cloud file, prepared once and then cached on disk (under
    ``shared.paths.data_dir()/cache/mesh_gt``, keyed by the file's path, size and modification time).

    A mesh is sampled on its surface (``sample_spacing_m``) with the triangles' own normals; a point cloud gets
    normals estimated from its neighbourhood. ``progress(str)`` is told what is being done."""
    say = progress or (lambda msg: None)
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    cf = _cache_file(path, voxel_m, sample_spacing_m) if cache else None
    if cf is not None and cf.is_file():
        try:
            with np.load(cf) as z:
                gt = GroundTruthCloud.from_arrays(z["points"], z["normals"], voxel_m)
            say(f"ground truth {path.name}: {len(gt.points)} points (cached)")
            return gt
        except (OSError, ValueError, KeyError):
            say(f"ground-truth cache {cf} unreadable: preparing again")
    say(f"ground truth {path.name}: sampling the surface and downsampling to {voxel_m * 100:g} cm (once per scene)")
    points, normals = _read_cloud(path, sample_spacing_m)
    gt = prepare_points(points, voxel_m, normals)
    if cf is not None:
        cf.parent.mkdir(parents=True, exist_ok=True)
        tmp = cf.with_suffix(".partial.npz")
        np.savez(tmp, points=gt.points.astype(np.float32), normals=gt.normals.astype(np.float32))
        tmp.replace(cf)  # whole or nothing: a concurrent reader never sees half a file
        gt = GroundTruthCloud.from_arrays(gt.points.astype(np.float32), gt.normals.astype(np.float32), voxel_m)
    say(f"ground truth {path.name}: {len(gt.points)} points")
    return gt


def _prepared_gt(gt: np.ndarray, voxel_m: float) -> GroundTruthCloud:
    """:func:`prepare_points` kept for the last few ground truths given as arrays, since an evaluation of
    several runs of one scene prepares the same cloud each time."""
    key = (gt.shape, voxel_m, hash(np.ascontiguousarray(gt[:: max(1, len(gt) // 4096)]).tobytes()))
    if key not in _GT_PREPARED:
        while len(_GT_PREPARED) >= 3:
            _GT_PREPARED.pop(next(iter(_GT_PREPARED)))
        _GT_PREPARED[key] = prepare_points(gt, voxel_m)
    return _GT_PREPARED[key]


def evaluate_points(est: np.ndarray, gt: np.ndarray | GroundTruthCloud, voxel_m: float = 0.01, icp: bool = True,
                    icp_max_distance_m: float = 0.1, completeness_threshold_m: float = 0.2,
                    icp_max_points: int = 150_000, progress=None) -> MeshEvalResult:
    """Accuracy/completeness of estimated points (N, 3) in W against the ground truth (points, or prepared).

    The point-to-plane ICP is estimated from at most ``icp_max_points`` of the downsampled estimate (a fixed
    random subset: the same correction, a fraction of the time); the metrics use every downsampled point."""
    import open3d as o3d

    say = progress or (lambda msg: None)
    n_gt = len(gt.points if isinstance(gt, GroundTruthCloud) else gt)
    if len(est) == 0 or n_gt == 0:
        raise ValueError(f"empty point set (estimate {len(est)}, ground truth {n_gt})")
    g = gt if isinstance(gt, GroundTruthCloud) else _prepared_gt(gt, voxel_m)
    pe = _downsample(est, voxel_m)
    T = np.eye(4)
    fitness = float("nan")
    if icp:
        n = len(pe.points)
        src = pe
        if n > icp_max_points:
            idx = np.sort(np.random.default_rng(0).choice(n, icp_max_points, replace=False))
            src = pe.select_by_index(idx.tolist())
        say(f"point-to-plane ICP ({len(src.points)} of {n} estimated points)")
        reg = o3d.pipelines.registration.registration_icp(
            src, g.cloud(), icp_max_distance_m, np.eye(4), o3d.pipelines.registration.TransformationEstimationPointToPlane(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50))
        T = np.asarray(reg.transformation)
        pe.transform(T)
    say("distances estimate -> ground truth and back")
    e = np.asarray(pe.points)
    d_eg = g.distances(e)
    if icp:  # ICP fitness over every estimated point, not only the subset it was estimated from
        fitness = float(np.mean(d_eg < icp_max_distance_m))
    d_ge, _ = cKDTree(e).query(g.points, workers=-1, distance_upper_bound=max(completeness_threshold_m, 0.05) * 1.01)
    return MeshEvalResult(float(d_eg.mean()), float(np.mean(d_ge <= completeness_threshold_m)), float(np.mean(d_ge <= 0.05)),
                          completeness_threshold_m, float(np.median(d_eg)), len(e), len(g.points), fitness, T)


def error_colors(d: np.ndarray, max_m: float = 0.1) -> np.ndarray:
    """uint8 RGB per distance: blue (0) through green (max_m / 2) to red (>= max_m)."""
    x = np.clip(np.asarray(d, float) / max_m, 0.0, 1.0)
    r = np.clip(2 * x - 1, 0, 1)
    g = 1 - np.abs(2 * x - 1)
    b = np.clip(1 - 2 * x, 0, 1)
    return np.round(np.stack([r, g, b], axis=1) * 255).astype(np.uint8)


def write_error_mesh(est_path: str | Path, gt: GroundTruthCloud, T_gt_est: np.ndarray, out_ply: str | Path,
                     out_png: str | Path | None = None, max_m: float = 0.1) -> None:
    """The estimated mesh (after the ICP correction) coloured by distance to the ground truth, as PLY,
    and a top-down PNG view of it."""
    import open3d as o3d

    from services.mapping.io import write_ply

    mesh = o3d.io.read_triangle_mesh(str(est_path))
    v = np.asarray(mesh.vertices) @ T_gt_est[:3, :3].T + T_gt_est[:3, 3]
    d, _ = gt.tree.query(v, workers=-1, distance_upper_bound=max_m)  # farther ones are all red: inf is enough
    colors = error_colors(np.minimum(d, max_m), max_m)
    write_ply(out_ply, v, np.asarray(mesh.triangles), colors)
    if out_png is not None:
        _top_view_png(v, colors, Path(out_png))


def _top_view_png(v: np.ndarray, colors: np.ndarray, path: Path, size: int = 1024) -> None:
    import cv2

    img = np.full((size, size, 3), 255, np.uint8)
    if len(v):
        lo, hi = v[:, :2].min(axis=0), v[:, :2].max(axis=0)
        s = (size - 20) / max(float((hi - lo).max()), 1e-6)
        px = ((v[:, :2] - lo) * s + 10).astype(int)
        order = np.argsort(v[:, 2])  # higher points drawn last
        img[size - 1 - px[order, 1], px[order, 0]] = colors[order][:, ::-1]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img)


def evaluate_mesh_files(est_path: str | Path, gt_path: str | Path, voxel_m: float = 0.01, icp: bool = True,
                        gt_sample_spacing_m: float = 0.005, out_dir: str | Path | None = None,
                        T_gt_est_init: np.ndarray | None = None, progress=None, cache: bool = True) -> MeshEvalResult:
    """The paper's protocol on two files; with ``out_dir`` also error_mesh.ply, error_top.png, mesh_eval.json.

    ``T_gt_est_init`` first moves the estimate into the ground truth's frame (e.g. the run's trajectory
    alignment, :func:`shared.metrics.ate.run_alignment`); ICP then refines from there. A SLAM run's world frame is
    its own (gravity-aligned, arbitrary yaw and origin), so without it ICP starts metres away. The prepared
    ground truth is cached (:func:`load_ground_truth`); ``progress(str)`` hears each step.
    """
    import json

    say = progress or (lambda msg: None)
    est = load_points(est_path)
    T0 = np.eye(4) if T_gt_est_init is None else np.asarray(T_gt_est_init, float)
    est = est @ T0[:3, :3].T + T0[:3, 3]
    gt = load_ground_truth(gt_path, voxel_m, gt_sample_spacing_m, cache=cache, progress=say)
    res = evaluate_points(est, gt, voxel_m, icp, progress=say)
    res = dataclasses.replace(res, T_gt_est=res.T_gt_est @ T0)
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        say(f"error-coloured mesh and top view into {out}")
        write_error_mesh(est_path, gt, res.T_gt_est, out / "error_mesh.ply", out / "error_top.png")
        (out / "mesh_eval.json").write_text(json.dumps(res.summary(), indent=1))
    return res
