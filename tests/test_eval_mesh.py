"""Mesh accuracy/completeness (paper sec. V protocol) on shapes with known answers, and the CLI."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import open3d as o3d
import pytest

from tests.helpers_zenoh import REPO, child_env
from services.app.metrics.mesh import error_colors, evaluate_mesh_files, evaluate_points, load_points


def sphere(r: float, res: int = 60) -> o3d.geometry.TriangleMesh:
    return o3d.geometry.TriangleMesh.create_sphere(r, resolution=res)


def test_scaled_sphere_accuracy_is_the_radius_gap():
    gt = np.asarray(sphere(0.5).sample_points_uniformly(60000).points)
    est = np.asarray(sphere(0.53).sample_points_uniformly(30000).points)
    res = evaluate_points(est, gt, icp=True)
    # ICP cannot remove a scale error: every estimated point is 3 cm off the surface
    assert res.accuracy_m == pytest.approx(0.03, abs=0.004)
    assert res.completeness == 1.0 and res.completeness_5cm == 1.0


def test_partial_estimate_completeness_and_icp_removes_an_offset():
    gt = np.asarray(sphere(0.5).sample_points_uniformly(60000).points)
    half = gt[gt[:, 2] > 0.0][::2] + np.array([0.02, -0.01, 0.015])  # upper half, shifted 2.7 cm
    res = evaluate_points(half, gt, icp=True)
    # the lower half counts up to the elevation whose chord to the equator is 0.2 m: a band of area sin(theta) / 2
    band = lambda t: np.sin(2 * np.arcsin(t / (2 * 0.5))) / 2  # noqa: E731
    assert res.completeness == pytest.approx(0.5 + band(0.2), abs=0.02)
    assert res.completeness_5cm == pytest.approx(0.5 + band(0.05), abs=0.02)
    assert res.accuracy_m < 0.006  # after ICP the shift is gone (1 cm grid leaves a few mm)
    no_icp = evaluate_points(half, gt, icp=False)
    assert no_icp.accuracy_m > 0.01  # the shift, less its part along the surface


def test_run_frame_estimate_needs_the_trajectory_alignment(tmp_path):
    """A map in a SLAM run's own world frame (yawed and shifted by metres) is only comparable after the
    trajectory's alignment: with it the accuracy is that of the mesh, without it ICP cannot reach it."""
    from scipy.spatial.transform import Rotation

    from shared.metrics.ate import compute_ate

    box = o3d.geometry.TriangleMesh.create_box(2.0, 1.0, 0.5)
    o3d.io.write_triangle_mesh(str(tmp_path / "gt.ply"), box)
    T_run_gt = np.eye(4)
    T_run_gt[:3, :3] = Rotation.from_euler("z", 70, degrees=True).as_matrix()
    T_run_gt[:3, 3] = [3.0, -1.5, 0.2]
    est = o3d.geometry.TriangleMesh(box).subdivide_midpoint(4).transform(T_run_gt)
    o3d.io.write_triangle_mesh(str(tmp_path / "est.ply"), est)
    # the same motion seen by a trajectory: ground-truth positions and the run's positions of them
    p_gt = np.random.default_rng(3).uniform(-1, 1, (50, 3))
    p_run = p_gt @ T_run_gt[:3, :3].T + T_run_gt[:3, 3]
    stamps = np.arange(50, dtype=np.int64) * 50_000_000
    T0 = compute_ate(stamps, p_gt, stamps, p_run, mode="se3").alignment.matrix()
    aligned = evaluate_mesh_files(tmp_path / "est.ply", tmp_path / "gt.ply", T_gt_est_init=T0)
    assert aligned.accuracy_m < 0.005 and aligned.completeness > 0.99
    np.testing.assert_allclose(aligned.T_gt_est @ T_run_gt, np.eye(4), atol=1e-3)
    unaligned = evaluate_mesh_files(tmp_path / "est.ply", tmp_path / "gt.ply")
    assert unaligned.accuracy_m > 0.5


def test_error_colours_ramp():
    c = error_colors(np.array([0.0, 0.05, 0.2]), max_m=0.1)
    assert c.tolist() == [[0, 0, 255], [0, 255, 0], [255, 0, 0]]


def test_cli_and_outputs(tmp_path):
    gt_path, est_path = tmp_path / "gt.ply", tmp_path / "est.ply"
    o3d.io.write_triangle_mesh(str(gt_path), sphere(0.5))
    o3d.io.write_triangle_mesh(str(est_path), sphere(0.51, 80))
    res = evaluate_mesh_files(est_path, gt_path, out_dir=tmp_path / "ev")
    assert res.accuracy_m == pytest.approx(0.01, abs=0.004)
    assert (tmp_path / "ev" / "error_mesh.ply").is_file() and (tmp_path / "ev" / "error_top.png").is_file()
    assert len(load_points(gt_path, 0.005)) > 10 * len(load_points(gt_path))  # surface sampling of the GT mesh
    p = subprocess.run([sys.executable, "-m", "services.app.cli", "eval", "mesh", str(est_path), str(gt_path)], cwd=REPO,
                       env=child_env(), capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.startswith("accuracy 0.01")
    p = subprocess.run([sys.executable, "-m", "services.app.cli", "eval", "mesh", "--est", str(tmp_path / "nope.ply"),
                        "--gt", str(gt_path)], cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=120)
    assert p.returncode == 1 and "no such file" in p.stderr


def test_prepared_ground_truth_is_cached_and_gives_the_same_figures(tmp_path, monkeypatch):
    """The first evaluation prepares the ground truth (surface samples with their triangles' normals) and caches it;
    the second reads the cache and gives the same figures; a changed ground-truth file is prepared anew."""
    from services.app.metrics.mesh import load_ground_truth

    monkeypatch.setenv("SIGMASLAM_DATA", str(tmp_path / "data"))
    gt_path, est_path = tmp_path / "gt.ply", tmp_path / "est.ply"
    o3d.io.write_triangle_mesh(str(gt_path), sphere(0.5))
    o3d.io.write_triangle_mesh(str(est_path), sphere(0.52, 80))
    said: list[str] = []
    first = evaluate_mesh_files(est_path, gt_path, progress=said.append)
    assert any("once per scene" in s for s in said) and not any("(cached)" in s for s in said)
    assert len(list((tmp_path / "data" / "cache" / "mesh_gt").glob("*.npz"))) == 1
    said.clear()
    second = evaluate_mesh_files(est_path, gt_path, progress=said.append)
    assert any("(cached)" in s for s in said)
    # (ICP sums in parallel threads: the last digits may differ)
    assert second.accuracy_m == pytest.approx(first.accuracy_m, abs=1e-4) and second.n_gt == first.n_gt
    assert first.accuracy_m == pytest.approx(0.02, abs=0.004)
    # triangle normals of a sphere point along the radius
    gt = load_ground_truth(gt_path)
    radial = gt.points / np.linalg.norm(gt.points, axis=1, keepdims=True)
    assert np.median(np.abs(np.sum(radial * gt.normals, axis=1))) > 0.99
    o3d.io.write_triangle_mesh(str(gt_path), sphere(0.6))  # new contents: the old cache entry is not used
    said.clear()
    third = evaluate_mesh_files(est_path, gt_path, progress=said.append)
    assert any("once per scene" in s for s in said) and third.accuracy_m > 0.05


def test_icp_on_a_subset_recovers_the_same_correction():
    """The ICP estimated from a subset of the estimate removes a known offset as well as from all of it."""
    gt = np.asarray(o3d.geometry.TriangleMesh.create_box(2.0, 1.5, 1.0).sample_points_uniformly(200_000).points)
    est = gt[::2] + np.array([0.03, -0.02, 0.01])
    full = evaluate_points(est, gt, icp=True, icp_max_points=10**9)
    sub = evaluate_points(est, gt, icp=True, icp_max_points=5000)
    np.testing.assert_allclose(sub.T_gt_est[:3, 3], full.T_gt_est[:3, 3], atol=2e-3)
    np.testing.assert_allclose(sub.T_gt_est[:3, 3], [-0.03, 0.02, -0.01], atol=3e-3)
    assert sub.accuracy_m < 0.006
