"""The grid planner (services/app/planner.py) on the ray-cast room's grid: a path around the box that keeps the robot
radius from every surface of the real room within the height band, shortest on the grid, and the cases it must
refuse (a goal inside the box, a robot too wide for the room)."""

from __future__ import annotations

import numpy as np
import pytest

from occupancy_room import mapped_room
from raycast_depth import room_scene
from services.app.metrics.occupancy import SceneTruth
from services.app.planner import path_clearance, plan, traversable
from services.mapping.grid import GridBuilder

RADIUS = 0.2


@pytest.fixture(scope="module")
def grid_and_truth():
    g = GridBuilder().build(mapped_room()[0])
    mesh = room_scene()
    truth = SceneTruth.in_band(np.asarray(mesh.vertices), np.asarray(mesh.triangles), np.eye(4), g.z_band_m, 0.025)
    return g, truth


def test_a_path_around_the_box_keeps_the_robot_radius(grid_and_truth):
    g, truth = grid_and_truth
    start, goal = np.array([3.3, 2.9]), np.array([5.4, 2.9])  # the box (x 3.6-4.6, y 2.75-3.75) is in the way
    p = plan(g, start, goal, RADIUS)
    assert p.found, p.reason
    assert np.linalg.norm(p.path_xy[0] - start) < 0.15 and np.linalg.norm(p.path_xy[-1] - goal) < 0.15
    straight = np.linalg.norm(goal - start)
    assert straight < p.length_m < 2 * straight  # around the box, not through it
    assert path_clearance(p.path_xy, g.z_band_m, truth.distance) >= RADIUS
    ok = traversable(g, RADIUS)
    rc = g.cell_of(p.path_xy)
    assert ok[rc[:, 0], rc[:, 1]].all()
    steps = np.linalg.norm(np.diff(p.path_xy, axis=0), axis=1)
    assert np.allclose(steps[steps < 1.2 * g.resolution_m], g.resolution_m)  # 8-connected moves


def test_what_the_planner_refuses(grid_and_truth):
    g, _ = grid_and_truth
    inside_box = plan(g, np.array([3.3, 2.9]), np.array([4.1, 3.25]), RADIUS, snap_m=0.2)
    assert not inside_box.found and "goal" in inside_box.reason
    too_wide = plan(g, np.array([3.3, 2.9]), np.array([5.2, 3.3]), 2.0)
    assert not too_wide.found and len(too_wide.path_xy) == 0


def test_a_run_plans_between_the_farthest_poses_that_free_cells_connect(tmp_path):
    """A wall splits the free space: the trajectory's farthest poses lie on either side, so the run's plan takes the
    farthest pair on one side and says how far apart the farthest pair overall was."""
    from services.app.planner import plan_run
    from services.mapping.grid import FREE_CELL, OCCUPIED_CELL, Grid2D
    from services.mapping.grid_files import write_grid
    from shared.euroc import PoseSeries, write_tum

    cells = np.full((40, 100), FREE_CELL, np.uint8)  # 2 m x 5 m at 5 cm
    cells[:, 60:62] = OCCUPIED_CELL  # a wall at x = 3.0-3.1 m
    write_grid(Grid2D(cells, 0.05, np.zeros(2), np.array([0.1, 1.5]), 0.0), tmp_path)
    x = np.array([0.5, 1.0, 2.0, 2.6, 4.5])  # four poses left of the wall, the last (the farthest) right of it
    p = np.column_stack([x, np.full(5, 1.0), np.full(5, 1.2)])
    q = np.tile([1.0, 0.0, 0.0, 0.0], (5, 1))
    write_tum(tmp_path / "trajectory.txt", PoseSeries(np.arange(5, dtype=np.int64) * 10**9, p, q))
    got = plan_run(tmp_path, radius_m=0.2)
    assert got["found"] and np.allclose(got["start_xy"], [0.5, 1.0]) and np.allclose(got["goal_xy"], [2.6, 1.0])
    assert got["straight_m"] == pytest.approx(2.1) and got["farthest_straight_m"] == pytest.approx(4.0)
    assert max(xy[0] for xy in got["path_xy"]) < 3.0  # never through the wall
    write_grid(Grid2D(np.full((40, 100), FREE_CELL, np.uint8), 0.05, np.zeros(2), np.array([0.1, 1.5]), 0.0), tmp_path)
    got = plan_run(tmp_path, radius_m=0.2)  # nothing in the way: the farthest pair
    assert got["found"] and np.allclose(got["goal_xy"], [4.5, 1.0]) and got["straight_m"] == pytest.approx(4.0)
