"""The 2D grid of the combined map (services/mapping/grid.py) on the ray-cast room: floor, band, walls and objects
occupied, no free cell over an object or outside the room, rasters that follow a moved submap, and the map_server
files read back by an independent reader (Pillow + PyYAML + map_server's documented thresholds)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from PIL import Image

from occupancy_room import BALL, BOX, ROOM, mapped_room, views
from services.mapping.config import GridConfig
from services.mapping.grid import FREE_CELL, OCCUPIED_CELL, UNKNOWN_CELL, GridBuilder, _combine_rasters
from services.mapping.grid_files import read_grid, write_grid


@pytest.fixture(scope="module")
def room_grid():
    mapper, _ = mapped_room()
    return mapper, GridBuilder().build(mapper)


def _cell_boxes(grid, mask):
    r, c = np.nonzero(mask)
    lo = grid.origin_xy_m + np.column_stack([c, r]) * grid.resolution_m
    return lo, lo + grid.resolution_m


def test_floor_band_and_what_is_occupied(room_grid):
    _, g = room_grid
    assert abs(g.floor_z_m) <= 0.025 + 1e-9  # the room's floor is z = 0
    np.testing.assert_allclose(g.z_band_m, g.floor_z_m + np.array([0.1, 1.5]))
    assert set(np.unique(g.cells)) <= {FREE_CELL, OCCUPIED_CELL, UNKNOWN_CELL}
    xs, ys = g.centres_W()
    # the far wall (x = 6) where submap 0 looks, and the front face of the box (x = 3.6)
    col = int(np.argmin(np.abs(xs - 5.99)))
    rows = (ys > 1.0) & (ys < 2.5)
    assert np.mean(g.cells[rows, col] == OCCUPIED_CELL) > 0.9
    col = int(np.argmin(np.abs(xs - 3.61)))
    rows = (ys > BOX[0][1] + 0.1) & (ys < BOX[1][1] - 0.1)
    assert np.mean(g.cells[rows, col] == OCCUPIED_CELL) > 0.9
    assert (g.cells == FREE_CELL).sum() * g.resolution_m**2 > 4.0  # m^2 of free floor seen


def test_no_free_cell_over_an_object_or_outside_the_room(room_grid):
    _, g = room_grid
    lo, hi = _cell_boxes(g, g.cells == FREE_CELL)
    inside = (lo[:, 0] >= 0) & (lo[:, 1] >= 0) & (hi[:, 0] <= ROOM[0]) & (hi[:, 1] <= ROOM[1])
    assert inside.all()
    over_box = (hi[:, 0] > BOX[0][0]) & (lo[:, 0] < BOX[1][0]) & (hi[:, 1] > BOX[0][1]) & (lo[:, 1] < BOX[1][1])
    assert not over_box.any()
    nearest = np.clip(BALL[0][:2], lo, hi)  # the point of each cell nearest the ball's centre
    # a cell may touch the ball's outline by less than a voxel (the map's resolution); the ball's unseen far side
    # is unknown, which keeps the cells over it from being free (grid.min_free_fraction)
    assert (np.linalg.norm(nearest - BALL[0][:2], axis=1) >= BALL[1] - 0.025).all()


def test_a_few_uncertain_voxels_leave_a_column_free_many_make_it_unknown():
    """Two submaps over a 1 x 3 strip of 5 cm cells, 2.5 cm voxels, a 1.4 m band (56 levels, 224 voxel centres a
    cell): every level observed free in every cell; submap 1 also holds uncertain voxels, 5 in cell 0 (2 %), 40 in
    cell 1 (18 %), and an occupied voxel in cell 2."""
    band, res, vs = (0.1, 1.5), 0.05, 0.025
    full = int(round((res / vs) ** 2 * (band[1] - band[0]) / vs))
    levels = np.full((1, 3), np.uint64(2**56 - 1))
    n_free = np.full((1, 3), full, np.int32)
    occ0, occ1 = np.zeros((1, 3), bool), np.array([[False, False, True]])
    unsure0, unsure1 = np.zeros((1, 3), np.int32), np.array([[5, 40, 0]], np.int32)
    rasters = [(0, 0, occ0, unsure0, levels, n_free), (0, 0, occ1, unsure1, levels, n_free - unsure1)]
    tolerant = _combine_rasters(rasters, band, res, vs, 0.0, 0.95, 0.1).cells[0]
    assert list(tolerant) == [FREE_CELL, UNKNOWN_CELL, OCCUPIED_CELL]
    strict = _combine_rasters(rasters, band, res, vs, 0.0, 0.95, 0.0).cells[0]
    assert list(strict) == [UNKNOWN_CELL, UNKNOWN_CELL, OCCUPIED_CELL]


def test_tolerating_uncertain_voxels_frees_more_of_the_room_and_nothing_over_an_object():
    mapper, _ = mapped_room()
    strict = GridBuilder(GridConfig(max_uncertain_fraction=0.0)).build(mapper)
    tolerant = GridBuilder(GridConfig(max_uncertain_fraction=0.1)).build(mapper)
    assert (tolerant.cells == FREE_CELL).sum() > (strict.cells == FREE_CELL).sum()
    assert ((strict.cells == FREE_CELL) <= (tolerant.cells == FREE_CELL)).all()  # what was free stays free
    lo, hi = _cell_boxes(tolerant, tolerant.cells == FREE_CELL)
    over_box = (hi[:, 0] > BOX[0][0]) & (lo[:, 0] < BOX[1][0]) & (hi[:, 1] > BOX[0][1]) & (lo[:, 1] < BOX[1][1])
    assert not over_box.any()


def test_rasters_follow_a_moved_submap():
    mapper, _ = mapped_room()
    builder = GridBuilder()
    before = builder.build(mapper)
    mapper.update_keyframes(np.array([7, 8]), np.array([0, 10_000_000_000]), np.stack([views(0)[0], views(1)[0]]))
    T = np.eye(4)
    T[:3, 3] = 0.4, 0.0, 0.0
    assert mapper.update_keyframes(np.array([8]), np.array([10_000_000_000]), (T @ views(1)[0])[None]) == [1]
    after, fresh = builder.build(mapper), GridBuilder().build(mapper)
    np.testing.assert_array_equal(after.cells, fresh.cells)
    np.testing.assert_array_equal(after.origin_xy_m, fresh.origin_xy_m)
    assert after.cells.shape != before.cells.shape or (after.cells != before.cells).any()


def test_fixed_floor_and_resolution():
    mapper, _ = mapped_room()
    g = GridBuilder(GridConfig(floor="fixed", floor_z_m=0.5, resolution_m=0.1, band_min_m=0.0,
                               band_max_m=0.4)).build(mapper)
    np.testing.assert_allclose(g.z_band_m, [0.5, 0.9])
    assert g.resolution_m == 0.1
    with pytest.raises(ValueError, match="finer than the voxels"):
        GridBuilder(GridConfig(resolution_m=0.01)).build(mapper)


def test_map_server_files_read_by_an_independent_reader(room_grid, tmp_path):
    _, g = room_grid
    pgm, ym = write_grid(g, tmp_path)
    meta = yaml.safe_load(ym.read_text())
    assert meta["image"] == pgm.name and meta["resolution"] == g.resolution_m and meta["negate"] == 0
    assert meta["origin"] == [g.origin_xy_m[0], g.origin_xy_m[1], 0.0]
    assert meta["frame"] == "W" and meta["height_band"] == list(g.z_band_m)
    img = np.asarray(Image.open(tmp_path / meta["image"]))
    assert img.dtype == np.uint8 and img.shape == g.cells.shape
    assert set(np.unique(img)) <= {0, 205, 254}
    # map_server: p = (255 - v) / 255; occupied above occupied_thresh, free below free_thresh; the image's first
    # row is the highest y, its lower-left pixel's corner at origin
    p = (255 - img.astype(float)) / 255
    occ, free = p > meta["occupied_thresh"], p < meta["free_thresh"]
    np.testing.assert_array_equal(occ[::-1], g.cells == OCCUPIED_CELL)
    np.testing.assert_array_equal(free[::-1], g.cells == FREE_CELL)
    # a point on the far wall lands on an occupied pixel by the map_server's origin and resolution
    x, y = 5.99, 1.8
    col = int((x - meta["origin"][0]) / meta["resolution"])
    row = img.shape[0] - 1 - int((y - meta["origin"][1]) / meta["resolution"])
    assert occ[row, col]
    back = read_grid(ym)
    np.testing.assert_array_equal(back.cells, g.cells)
    np.testing.assert_allclose(back.origin_xy_m, g.origin_xy_m)


def test_grid_message(room_grid):
    _, g = room_grid
    msg = g.message(123)
    assert msg.header.frame_id == "W" and msg.width == g.cells.shape[1] and msg.height == g.cells.shape[0]
    assert set(np.unique(msg.cells)) <= {0, 100, 255}
