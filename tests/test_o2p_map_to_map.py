"""Map-to-map occupancy-to-point terms (eq. 5-7) in the loop closer: a submap whose anchor keyframe is off by
2 deg / 4 cm is pulled back onto the older submap by the term, in the pose graph (directly and through the
loop closer, where the term waits for its anchors to become nodes) and in the final bundle adjustment."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np

from services.backend.o2p.config import O2PConfig
from services.backend.loop.config import LoopConfig
from services.backend.loop.final_ba import bundle_adjust
from services.backend.loop.history import KeyframeRecord
from services.backend.loop.loop_closer import LoopCloser
from services.backend.loop.loop_thread import ThreadedLoopCloser
from services.backend.loop.pose_graph import PoseGraph
from tests.test_o2p_terms import S, err, map_to_map_term

# odometry between the two anchors, loose: the term has to do the pulling (3 deg, 10 cm); the anchor's error
# includes a tilt, which the loop closer's attitude factors (loop.attitude_sigma_deg) would hold, so they are off
# in the loop-closer tests here (tests/test_loop_pose_graph.py tests them)
REL_COV = np.diag([np.radians(3.0) ** 2] * 3 + [0.1**2] * 3)


def records(P_o, T_est):
    def rec(state, stamp, T, **kw):
        return KeyframeRecord(state, stamp, T, np.zeros(3), gtsam.imuBias.ConstantBias(), {}, {}, **kw)

    return [rec(1, 1 * S, P_o, next_state=7, rel_cov_to_next=REL_COV, T_WS_next=T_est), rec(7, 4 * S, T_est)]


def test_pose_graph_map_to_map_pulls_the_submap_anchor_back(o2p_room):
    term, P_o, T_true, T_est = map_to_map_term(o2p_room)
    for with_term in (False, True):
        pg = PoseGraph()
        pg.add_node(1, P_o)
        pg.add_node(7, T_est, REL_COV)
        if with_term:
            assert pg.add_map_to_map(term) and pg.map_to_map == [term]
        est = pg.optimise()
        rot, tr = err(est[7], T_true)
        print(f"term {with_term}: {rot:.3f} deg, {100 * tr:.2f} cm")
        if with_term:
            assert rot < 0.3 and tr < 0.01
            assert np.allclose(est[1], P_o, atol=1e-3)  # the first node holds the gauge
        else:
            assert rot > 1.5 and tr > 0.03  # odometry alone keeps the error
    # capped at N_eff = 10 points (the default) the term still pulls, less hard against the loose odometry
    capped, *_ = map_to_map_term(o2p_room, O2PConfig(enabled=True, frame_to_map=False, map_to_map=True, effective_points=10))
    pg = PoseGraph()
    pg.add_node(1, P_o)
    pg.add_node(7, T_est, REL_COV)
    assert pg.add_map_to_map(capped)
    rot, tr = err(pg.optimise()[7], T_true)
    assert rot < 1.0 and tr < 0.02


def test_map_to_map_waits_in_the_loop_closer_for_its_anchor_nodes(o2p_room):
    term, P_o, T_true, T_est = map_to_map_term(o2p_room)
    closer = LoopCloser(LoopConfig(attitude_sigma_deg=0), [])
    rec1, rec7 = records(P_o, T_est)
    assert not closer.add_map_to_map(term)  # no node yet
    closer.add_record(rec1)
    assert closer.counts["map_to_map_accepted"] == 0 and closer.map_to_map_for_final() == [term]
    assert closer.add_record(rec7)  # both anchors are nodes: the term joins and the graph is solved
    assert closer.counts["map_to_map_accepted"] == 1 and closer.map_to_map_for_final() == [term]
    rot, tr = err(closer.graph.estimate[7], T_true)
    assert rot < 0.3 and tr < 0.01
    # the correction of the newest node moves the published state by the same amount
    rot, tr = err(closer.correction() @ T_est, T_true)
    assert rot < 0.3 and tr < 0.01
    # a term whose points miss the target's field at the estimate is counted and left out
    T_far = term.T_KM_m.copy()
    T_far[0, 3] += 50.0  # submap m 50 m away from o
    closer.add_map_to_map(dataclasses.replace(term, T_KM_m=T_far))
    assert closer.counts["map_to_map_too_few_inside"] == 1 and len(closer.graph.map_to_map) == 1
    assert "map_to_map_chi2" not in closer.counts


def test_threaded_loop_closer_takes_map_to_map_terms(o2p_room):
    """Through the closer's thread (as the back end submits them): the correction and the corrected
    keyframes follow the solve that includes the term."""
    term, P_o, T_true, T_est = map_to_map_term(o2p_room)
    runner = ThreadedLoopCloser(LoopCloser(LoopConfig(attitude_sigma_deg=0), []))
    try:
        rec1, rec7 = records(P_o, T_est)
        runner.submit_record(rec1)
        runner.submit_map_to_map(term)
        runner.submit_record(rec7)
        assert runner.drain() and runner.errors == 0
        gen, (ids, _, T) = runner.corrected_keyframes()
        assert gen == 1 and list(ids) == [1, 7]
        rot, tr = err(T[1], T_true)
        assert rot < 0.3 and tr < 0.01
        assert err(runner.correction() @ T_est, T_true)[1] < 0.01
    finally:
        runner.close()


def test_final_bundle_adjustment_uses_map_to_map(o2p_room):
    term, P_o, T_true, T_est = map_to_map_term(o2p_room)
    recs = records(P_o, T_est)
    without = bundle_adjust(recs, [], prior_sigma_rot=1e-4, prior_sigma_pos=1e-4)
    res = bundle_adjust(recs, [], prior_sigma_rot=1e-4, prior_sigma_pos=1e-4, map_to_map=[term])
    assert without.map_to_map == 0 and res.map_to_map == 1
    assert err(without.T_WS[1], T_true)[0] > 1.5  # nothing else constrains the second keyframe
    rot, tr = err(res.T_WS[1], T_true)
    assert rot < 0.3 and tr < 0.01
    # a term whose anchors are not among the keyframes is left out
    assert bundle_adjust(recs, [], map_to_map=[dataclasses.replace(term, state_o=99)]).map_to_map == 0


def test_submap_anchor_uses_the_keyframe_pose_as_published():
    """The mapping's T_WM of a submap lives in the frame of the keyframe poses it last received, so the back end
    takes T_KM against the pose the last Keyframes message carried, not against a newer correction."""
    from services.backend.node import make_node
    from services.app.system_config import load_system_config
    from shared.geometry import make_T, so3_exp
    from shared.messages import Header, Keyframes
    from shared.rig import load_rig_config

    cfg = load_system_config(None, ["loop.synchronous=true", "o2p.enabled=true"])
    node = make_node(cfg, load_rig_config(cfg.rig))  # the composition root: the terms' anchoring is the loop's
    lb = node.loop_closure
    assert node.o2p.anchoring is lb.published
    try:
        T_window = make_T(so3_exp(np.array([0.0, 0.0, 0.3])), np.array([1.0, 2.0, 0.5]))  # the window's estimate
        lb.history.records.append(KeyframeRecord(5, 2 * S, T_window, np.zeros(3), gtsam.imuBias.ConstantBias(), {}, {}))
        T_pub = make_T(so3_exp(np.array([0.0, 0.0, 0.32])), np.array([1.05, 1.9, 0.5]))  # as published (corrected)
        lb.published.note_published(Keyframes(header=Header(stamp_ns=2 * S), ids=np.array([5]),
                                              stamps_ns=np.array([2 * S]), T_WS=T_pub[None]))
        T_WM = T_pub @ make_T(np.eye(3), np.array([0.1, 0.0, 0.0]))  # the mapping: the submap 10 cm ahead of it
        n, T_KM = lb.published.anchor_of(2 * S, T_WM)
        assert n == 5 and np.allclose(T_KM[:3, 3], [0.1, 0.0, 0.0]) and np.allclose(T_KM[:3, :3], np.eye(3))
    finally:
        node.close()
