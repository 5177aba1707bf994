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
