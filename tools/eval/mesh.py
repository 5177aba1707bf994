"""Mesh accuracy and completeness as in the paper's sec. V.

Protocol: the estimated mesh's vertices and points of the ground truth are downsampled on a 1 cm
voxel grid; point-to-plane ICP aligns the estimate to the ground truth; accuracy is the mean
distance from every (aligned) estimated point to its nearest ground-truth point (no threshold);
completeness is the fraction of ground-truth points within 0.2 m (also reported at 5 cm) of the
estimate. A ground-truth *mesh* with large triangles has too few vertices to measure against, so its
surface is sampled densely first (``gt_sample_spacing_m``); a point cloud is used as it is.
"""

from __future__ import annotations

import dataclasses
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
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        pts = np.asarray(o3d.io.read_point_cloud(str(path)).points)
        if len(pts) == 0:
            pts = np.asarray(mesh.vertices)
        return pts
    if sample_spacing_m is None:
        return np.asarray(mesh.vertices)
    n = int(min(max_points, max(1000, mesh.get_surface_area() / sample_spacing_m ** 2)))
    return np.asarray(mesh.sample_points_uniformly(n).points)


def _downsample(points: np.ndarray, voxel_m: float):
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    return pc.voxel_down_sample(voxel_m) if voxel_m > 0 else pc


_GT_PREPARED: dict = {}


def _prepared_gt(gt: np.ndarray, voxel_m: float):
    """The ground truth downsampled, with normals (point-to-plane ICP) and a k-d tree; kept for the last few
    ground truths, since an evaluation of several runs of one scene prepares the same cloud each time."""
    import open3d as o3d

    key = (gt.shape, voxel_m, hash(np.ascontiguousarray(gt[:: max(1, len(gt) // 4096)]).tobytes()))
    if key not in _GT_PREPARED:
        pg = _downsample(gt, voxel_m)
        pg.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=max(5 * voxel_m, 0.05), max_nn=30))
        while len(_GT_PREPARED) >= 3:
            _GT_PREPARED.pop(next(iter(_GT_PREPARED)))
        _GT_PREPARED[key] = (pg, cKDTree(np.asarray(pg.points)))
    return _GT_PREPARED[key]


def evaluate_points(est: np.ndarray, gt: np.ndarray, voxel_m: float = 0.01, icp: bool = True,
                    icp_max_distance_m: float = 0.1, completeness_threshold_m: float = 0.2) -> MeshEvalResult:
    """Accuracy/completeness of estimated points against ground-truth points (both (N, 3) in W)."""
    import open3d as o3d

    if len(est) == 0 or len(gt) == 0:
        raise ValueError(f"empty point set (estimate {len(est)}, ground truth {len(gt)})")
    pe = _downsample(est, voxel_m)
    pg, g_tree = _prepared_gt(gt, voxel_m)
    T = np.eye(4)
    fitness = float("nan")
    if icp:
        reg = o3d.pipelines.registration.registration_icp(
            pe, pg, icp_max_distance_m, np.eye(4), o3d.pipelines.registration.TransformationEstimationPointToPlane(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50))
        T, fitness = np.asarray(reg.transformation), float(reg.fitness)
        pe.transform(T)
    e, g = np.asarray(pe.points), np.asarray(pg.points)
    d_eg, _ = g_tree.query(e, workers=1)
    d_ge, _ = cKDTree(e).query(g, workers=1, distance_upper_bound=max(completeness_threshold_m, 0.05) * 1.01)
    return MeshEvalResult(float(d_eg.mean()), float(np.mean(d_ge <= completeness_threshold_m)), float(np.mean(d_ge <= 0.05)),
                          completeness_threshold_m, float(np.median(d_eg)), len(e), len(g), fitness, T)


def error_colors(d: np.ndarray, max_m: float = 0.1) -> np.ndarray:
    """uint8 RGB per distance: blue (0) through green (max_m / 2) to red (>= max_m)."""
    x = np.clip(np.asarray(d, float) / max_m, 0.0, 1.0)
    r = np.clip(2 * x - 1, 0, 1)
    g = 1 - np.abs(2 * x - 1)
    b = np.clip(1 - 2 * x, 0, 1)
    return np.round(np.stack([r, g, b], axis=1) * 255).astype(np.uint8)


def write_error_mesh(est_path: str | Path, gt_points: np.ndarray, T_gt_est: np.ndarray, out_ply: str | Path,
                     out_png: str | Path | None = None, max_m: float = 0.1) -> None:
    """The estimated mesh (after the ICP correction) coloured by distance to the ground truth, as PLY,
    and a top-down PNG view of it."""
    import open3d as o3d

    from services.mapping.io import write_ply

    mesh = o3d.io.read_triangle_mesh(str(est_path))
    v = np.asarray(mesh.vertices) @ T_gt_est[:3, :3].T + T_gt_est[:3, 3]
    d, _ = cKDTree(gt_points).query(v, workers=1)
    colors = error_colors(d, max_m)
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
                        T_gt_est_init: np.ndarray | None = None) -> MeshEvalResult:
    """The paper's protocol on two files; with ``out_dir`` also error_mesh.ply, error_top.png, mesh_eval.json.

    ``T_gt_est_init`` first moves the estimate into the ground truth's frame (e.g. the run's trajectory
    alignment, :func:`tools.eval.ate.run_alignment`); ICP then refines from there. A SLAM run's world frame is
    its own (gravity-aligned, arbitrary yaw and origin), so without it ICP starts metres away.
    """
    import json

    est = load_points(est_path)
    T0 = np.eye(4) if T_gt_est_init is None else np.asarray(T_gt_est_init, float)
    est = est @ T0[:3, :3].T + T0[:3, 3]
    gt = load_points(gt_path, gt_sample_spacing_m)
    res = evaluate_points(est, gt, voxel_m, icp)
    res = dataclasses.replace(res, T_gt_est=res.T_gt_est @ T0)
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        write_error_mesh(est_path, np.asarray(_downsample(gt, voxel_m).points), res.T_gt_est, out / "error_mesh.ply",
                         out / "error_top.png")
        (out / "mesh_eval.json").write_text(json.dumps(res.summary(), indent=1))
    return res
