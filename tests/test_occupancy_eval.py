"""The safety figures (services/app/metrics/occupancy.py) on the ray-cast room, whose mesh is the truth: the ground
truth tests of points, low false free and high recall for a map made at the true poses, and a clearly higher false
free when a submap is misplaced (the figure sees the error it is meant to catch)."""

from __future__ import annotations

import numpy as np
import pytest

from occupancy_room import BALL, BOX, mapped_room
from raycast_depth import room_scene
from services.app.metrics.occupancy import SceneTruth, grid_figures, voxel_figures
from services.mapping.combined import CombinedMap
from services.mapping.grid import GridBuilder


@pytest.fixture(scope="module")
def truth():
    mesh = room_scene()
    return SceneTruth(np.asarray(mesh.vertices), np.asarray(mesh.triangles), 0.025)


def test_ground_truth_of_points(truth):
    p = np.array([[2.0, 1.5, 1.4], [5.99, 1.5, 1.4], [*(BOX[0] + BOX[1]) / 2], [*BALL[0]], [6.5, 2.0, 1.0],
                  [3.0, 2.5, -0.3], [2.0, 1.5, 0.01]])
    near, inside = truth.classify(p)
    assert near.tolist() == [False, True, False, False, False, False, True]
    assert inside.tolist() == [False, False, True, True, True, True, False]


def test_figures_of_a_good_map(truth):
    mapper, _ = mapped_room()
    cm = CombinedMap.of(mapper)
    combined, per = voxel_figures(cm, truth, np.eye(4), n=30_000)
    assert combined.false_free < 0.005 and combined.free_recall > 0.8 and combined.free > 2000
    assert sorted(per) == [0, 1] and all(s.false_free < 0.005 for s in per.values())
    cells = grid_figures(GridBuilder().build(mapper), cm, truth, np.eye(4), max_cells=300)
    assert cells.false_free < 0.02 and cells.free_recall > 0.5
    # the cells whose whole band the camera saw are nearly all free: the rest of the gap is coverage
    assert cells.free_recall_whole_band > 0.9 and cells.free_recall_whole_band > cells.free_recall


def test_a_misplaced_submap_raises_false_free(truth):
    drift = np.eye(4)
    drift[:3, 3] = 0.5, 0.3, 0.0
    mapper, _ = mapped_room(drift=drift)
    combined, per = voxel_figures(CombinedMap.of(mapper), truth, np.eye(4), n=30_000)
    assert per[1].false_free > 0.02 and combined.false_free > 0.01
    assert per[0].false_free < 0.005
