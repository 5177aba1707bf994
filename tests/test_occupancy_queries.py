"""Queries of the combined map (services/mapping/combined.py) on a ray-cast room with known truth: points, segments
and boxes across two overlapping submaps, the largest-L rule where they overlap, answers that follow a submap when
a loop closure moves it, and bad queries refused with a clear error."""

from __future__ import annotations

import numpy as np
import pytest

from occupancy_room import BALL, BOX, mapped_room, observed_points, views
from services.mapping.combined import FREE, OCCUPIED, UNKNOWN, CombinedMap
from services.mapping.config import QueryConfig


@pytest.fixture(scope="module")
def room():
    return mapped_room()


def _shift(x=0.0, y=0.0, z=0.0, yaw=0.0) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = x, y, z
    return T


def test_points_match_the_rooms_truth(room):
    mapper, renderer = room
    cm = CombinedMap.of(mapper)
    rng = np.random.default_rng(1)
    for k in (0, 1):
        free, surface = observed_points(renderer, k, rng)
        got = cm.points(free)
        assert np.mean(got.state == FREE) > 0.99 and not (got.state == OCCUPIED).any()
        assert np.isfinite(got.log_odds[got.state == FREE]).all() and (got.submaps[got.state == FREE] >= 1).all()
        on = cm.points(surface).state
        assert np.mean(on == FREE) < 0.02, "points on a surface reported free"
        assert np.mean(on == OCCUPIED) > 0.3
    # never observed: behind the walls, inside the box and the ball (more than tau behind their surfaces)
    hidden = np.array([[6.5, 2.0, 1.0], [3.0, 2.5, -0.4], [3.0, 5.4, 1.0], [*(BOX[0] + BOX[1]) / 2], [*BALL[0]]])
    got = cm.points(hidden)
    assert (got.state == UNKNOWN).all() and np.isnan(got.log_odds).all() and (got.submaps == 0).all()


def test_overlapping_submaps_answer_with_their_largest_log_odds():
    """Submap 1 placed 4 cm too high: its floor lies in submap 0's free space just above the floor. Where submap 0
    says free and submap 1 occupied, the combined map says occupied (never the free answer an average gives)."""
    mapper, _ = mapped_room(drift=_shift(z=0.04))
    g = np.mgrid[2.0:4.5:0.02, 1.0:3.0:0.02, 0.0:0.12:0.01].reshape(3, -1).T
    both = CombinedMap.of(mapper)
    one, two = CombinedMap.of(mapper, submap_ids=[0]), CombinedMap.of(mapper, submap_ids=[1])
    L, L0, L1 = both.points(g).log_odds, one.points(g).log_odds, two.points(g).log_odds
    np.testing.assert_array_equal(L, np.fmax(L0, L1))  # NaN (unobserved) in one: the other's
    conflict = (one.classify(L0) == FREE) & (two.classify(L1) == OCCUPIED)
    assert conflict.sum() > 50
    assert (both.classify(L)[conflict] == OCCUPIED).all()
    assert ((L0[conflict] + L1[conflict]) / 2 < 0).mean() > 0.5  # what an average would have said
    n = both.points(g).submaps
    assert ((n == 2) == (np.isfinite(L0) & np.isfinite(L1))).all()


def test_answers_follow_a_submap_moved_by_a_loop_closure():
    """Submap 1 (the only one that saw the ball) drifted 0.5 m and 5 deg; after the keyframe update of a loop
    closure the combined map answers as the map built without drift does, and the ball is where it really is."""
    true_map, renderer = mapped_room()
    drift = _shift(x=0.5, y=-0.2, yaw=np.radians(5))
    mapper, _ = mapped_room(drift=drift)
    T0, T1 = views(0)[0], views(1)[0]
    assert mapper.update_keyframes(np.array([7, 8]), np.array([0, 10_000_000_000]), np.stack([T0, drift @ T1])) == []
    centre, radius = BALL
    d = np.random.default_rng(2).normal(size=(4000, 3))
    ball = centre + radius * d / np.linalg.norm(d, axis=1, keepdims=True)
    ball = ball[ball[:, 0] > centre[0]]  # the side the cameras of submap 1 face
    before = CombinedMap.of(mapper)
    seen_drifted = before.points(ball @ drift[:3, :3].T + drift[:3, 3]).state
    assert np.mean(seen_drifted == OCCUPIED) > 0.3
    assert np.mean(before.points(ball).state == OCCUPIED) < 0.1  # only where drifted walls happen to be
    assert mapper.update_keyframes(np.array([8]), np.array([10_000_000_000]), T1[None]) == [1]
    after, truth = CombinedMap.of(mapper), CombinedMap.of(true_map)
    assert np.mean(after.points(ball).state == OCCUPIED) > 0.3
    p = np.random.default_rng(3).uniform([0, 0, 0], [6, 5, 3], (20000, 3))
    La, Lt = after.points(p).log_odds, truth.points(p).log_odds
    assert np.mean(np.isclose(La, Lt, atol=1e-6, equal_nan=True)) > 0.999


def test_segments(room):
    cm = CombinedMap.of(room[0])
    start = np.array([[2.5, 1.5, 1.4], [3.0, 2.9, 0.5], [3.35, 2.9, 0.5], [2.5, 1.5, 1.4], [5.0, 1.5, 1.4]])
    end = np.array([[7.0, 1.5, 1.4], [3.0, 3.6, 0.5], [3.35, 3.6, 0.5], [2.5, 1.5, 1.4], [8.0, 1.5, 1.4]])
    got = cm.segments(start, end, np.array([0.0, 0.1, 0.3, 0.05, 0.0]))
    # through the far wall (x = 6): first occupied point 3.5 m from the start, within a voxel
    assert got.hit[0] and abs(got.hit_distance_m[0] - 3.5) <= 0.025 and abs(got.hit_point_W[0, 0] - 6.0) <= 0.025
    assert not got.free[0]
    # beside the box (its face at x = 3.6): 0.6 m away with a 0.1 m radius is free all the way
    assert got.free[1] and not got.hit[1] and got.unknown_fraction[1] == 0 and np.isnan(got.hit_distance_m[1])
    # 0.25 m from the face with a 0.3 m radius touches it from the start, at the face
    assert got.hit[2] and got.hit_distance_m[2] == 0 and abs(got.hit_point_W[2, 0] - 3.6) <= 0.03
    assert got.free[3] and not got.hit[3]  # a point-like segment in free space
    # from free space out through the wall into the unobserved outside: hit, not free, partly unknown
    assert got.hit[4] and not got.free[4] and got.unknown_fraction[4] > 0.3


def test_boxes(room):
    cm = CombinedMap.of(room[0])
    lo = np.array([[2.8, 1.3, 1.2], [5.8, 1.0, 0.5], [6.3, 1.0, 0.5], [3.4, 2.5, 0.3]])
    hi = np.array([[3.1, 1.6, 1.5], [6.2, 1.3, 0.8], [6.8, 1.5, 1.0], [3.8, 3.0, 0.6]])
    got = cm.boxes(lo, hi)
    assert got.any_occupied.tolist() == [False, True, False, True]
    assert got.unknown_fraction[0] == 0 and got.occupied_fraction[0] == 0
    assert 0.2 < got.occupied_fraction[1] < 0.8  # the wall's surface band; behind it unknown
    assert got.unknown_fraction[2] == 1.0  # outside the room


def test_bad_queries_get_a_clear_error(room):
    cm = CombinedMap.of(room[0], QueryConfig(max_points=10, max_samples=1000))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        cm.points(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="NaN"):
        cm.points(np.array([[1.0, 2.0, np.nan]]))
    with pytest.raises(ValueError, match="max_points"):
        cm.points(np.zeros((11, 3)))
    with pytest.raises(ValueError, match="not numbers"):
        cm.points([["a", "b", "c"]])
    with pytest.raises(ValueError, match="radii"):
        cm.segments(np.zeros((1, 3)), np.ones((1, 3)), -0.1)
    with pytest.raises(ValueError, match="max_samples"):
        cm.segments(np.zeros((1, 3)), np.full((1, 3), 5.0), 0.5)
    with pytest.raises(ValueError, match="lo <= hi"):
        cm.boxes(np.ones((1, 3)), np.zeros((1, 3)))
    empty = CombinedMap([], 0.025)
    assert (empty.points(np.zeros((3, 3))).state == UNKNOWN).all()
