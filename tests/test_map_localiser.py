"""The saved-map localiser's bookkeeping (services/backend/loop/map_localiser.py): which matches place the session
in the map, and when."""

from __future__ import annotations

import collections
from types import SimpleNamespace

import numpy as np

from services.backend.loop.config import LoopConfig
from services.backend.loop.map_localiser import MapLocaliser
from shared.geometry import inv_T

S = 1_000_000_000
T0 = 100 * S  # the first 'tracking' state


def pose(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    c, s = np.cos(np.deg2rad(yaw_deg)), np.sin(np.deg2rad(yaw_deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = [x, 0.5 * x, 1.0]
    return T


# the session's window frame lies at T_MAP_WINDOW in the map; a match of a keyframe at window pose T_W says the
# keyframe is at T_MAP_WINDOW @ T_W in the map (PnP against the map's landmarks)
T_MAP_WINDOW = pose(2.0, 30.0)


def match(T_W: np.ndarray, error: np.ndarray | None = None) -> SimpleNamespace:
    return SimpleNamespace(T_WS_query=(T_MAP_WINDOW if error is None else error) @ T_W)


def localiser(early: int = 0) -> tuple[MapLocaliser, collections.Counter]:
    counts: collections.Counter = collections.Counter()
    cfg = LoopConfig(relocalise_confirmations=2, relocalise_settle_s=2.0, relocalise_early_confirmations=early)
    loc = MapLocaliser(cfg, counts)
    loc.note_state(T0, "tracking", pose(0.0))
    return loc, counts


def test_two_settled_matches_that_agree_align_the_session():
    loc, counts = localiser()
    t1, t2 = T0 + 3 * S, T0 + 3 * S + S // 10
    loc.note_state(t1, "tracking", pose(0.3))
    assert loc.note_match(t1, match(pose(0.3))) is None  # one guess is not enough
    loc.note_state(t2, "tracking", pose(0.35))
    T = loc.note_match(t2, match(pose(0.35)))
    assert T is not None and np.allclose(T, T_MAP_WINDOW, atol=1e-9)
    assert counts["map_matches"] == 2 and counts["map_matches_before_settled"] == 0


def test_matches_of_the_first_seconds_wait_for_their_nodes_and_count_once_one_settled_match_agrees():
    """A back end restarted beside its saved map matches every keyframe of its first seconds; the window is short,
    so their nodes come before it settles. Those early guesses alone do not align the session, but the first
    settled match that agrees with them does (instead of waiting for another settled one)."""
    loc, counts = localiser()
    early = [T0 + k * S // 5 for k in range(1, 6)]  # keyframes in the first second
    for k, t in enumerate(early):
        loc.note_state(t, "tracking", pose(0.1 * k))
        assert loc.note_match(t, match(pose(0.1 * k))) is None  # waits for its node: state not trusted yet
    for k, t in enumerate(early):  # they leave the window within the first 2 s
        loc.note_state(t + S // 2, "tracking", pose(1.0))
        assert loc.note_node(t, pose(0.1 * k)) is None  # early, and early ones may not align on their own
    assert counts["map_matches_before_settled"] == 10  # deferred at the state, then early at the node
    t = T0 + 3 * S  # settled
    loc.note_state(t, "tracking", pose(2.0))
    T = loc.note_match(t, match(pose(2.0)))
    assert T is not None and np.allclose(T, T_MAP_WINDOW, atol=1e-9)
    assert loc.last_agreeing == 6


def test_early_guesses_that_disagree_with_the_settled_one_do_not_count():
    """A window just initialised in motion may be off (scale, gravity): its early guesses do not agree with the
    settled ones and do not help them."""
    loc, _ = localiser()
    off = pose(0.8, 10.0) @ inv_T(pose(0.0))  # 0.9 m and 10 deg away from the truth
    for k in range(3):
        t = T0 + (k + 1) * S // 5
        loc.note_state(t, "tracking", pose(0.1 * k))
        loc.note_match(t, match(pose(0.1 * k), error=off @ T_MAP_WINDOW))
        assert loc.note_node(t, pose(0.1 * k)) is None
    t = T0 + 3 * S
    loc.note_state(t, "tracking", pose(2.0))
    assert loc.note_match(t, match(pose(2.0))) is None  # one settled guess; the early ones disagree
    loc.note_state(t + S // 10, "tracking", pose(2.1))
    T = loc.note_match(t + S // 10, match(pose(2.1)))
    assert T is not None and np.allclose(T, T_MAP_WINDOW, atol=1e-9) and loc.last_agreeing == 2


def test_enough_early_guesses_that_agree_align_the_session_without_a_settled_one():
    """The drone may leave the saved map's part of the world before the window settles: enough early guesses that
    agree (loop.relocalise_early_confirmations) align the session then; fewer wait for a settled one."""
    loc, counts = localiser(early=4)
    out = []
    for k in range(4):
        t = T0 + (k + 1) * S // 5
        loc.note_state(t, "tracking", pose(0.1 * k))
        loc.note_match(t, match(pose(0.1 * k)))
        loc.note_state(t + S // 2, "tracking", pose(1.0))
        out.append(loc.note_node(t, pose(0.1 * k)))
    assert all(T is None for T in out[:3]) and out[3] is not None and np.allclose(out[3], T_MAP_WINDOW, atol=1e-9)
    assert loc.last_agreeing == 4 and counts["map_matches_before_settled"] == 8
