"""Consistency gates of the occupancy-to-point factors (services/backend/o2p/terms.py): a factor whose depth is
grossly inconsistent with the map at the current estimate never enters the graph (chi-square on its whitened
error, counted), nor one whose points barely overlap the target's observed field; consistent ones pass."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X
from scipy.stats import chi2

from services.backend.o2p.config import O2PConfig
from services.backend.o2p.factor import OccupancyToPoint
from services.backend.o2p.gates import consistency
from services.backend.o2p.terms import OccupancyTerms
from services.mapping.export import field_message
from shared.occupancy.message import field_of_message
from services.mapping.mesh import ChunkMesher
from shared.occupancy.o2p_points import select_depth_points
from services.mapping.submaps import Submap
from shared.geometry import make_T, so3_exp
from tests.o2p_room import H, K, W, mapped_room, view

S = 1_000_000_000  # 1 s in ns
VIEW = 4.0  # a view of the room whose points spread over three walls


@pytest.fixture(scope="module")
def room():
    """The room mapped with a 0.15 m depth sigma: a wide observed band around the surfaces, so that points a
    few decimetres off still lie inside the field (and only the residual can tell them apart)."""
    store, renderer, cfg = mapped_room(0.15)
    return field_message(Submap(0, np.eye(4), 1 * S, store, ChunkMesher(4)), cfg.l_min), renderer


def perturbed(T, seed, rot_deg=2.0, trans_m=0.04):
    rng = np.random.default_rng(seed)
    a, t = rng.normal(size=3), rng.normal(size=3)
    return T @ make_T(so3_exp(a / np.linalg.norm(a) * np.radians(rot_deg)), t / np.linalg.norm(t) * trans_m)


def terms_with_depth(msg, depth, cfg=None):
    """Terms holding the room as submap 0 (covisible with the frame at 5 s) and a depth frame at 5 s."""
    terms = OccupancyTerms(cfg or O2PConfig(enabled=True))
    for t in range(1, 4):
        terms.note_frame(t * S, np.arange(0, 50))
    terms.add_field(msg)
    terms.note_frame(5 * S, np.arange(40, 90))
    terms.add_depth(5 * S, depth, np.full((H, W), 0.03, np.float32), K, np.eye(4))
    return terms


def test_grossly_inconsistent_frame_to_map_factor_is_rejected_and_counted(room):
    msg, renderer = room
    T_true = view(VIEW)
    depth = renderer.render(K, W, H, T_true)
    values = gtsam.Values()
    values.insert(X(5), gtsam.Pose3(perturbed(T_true, 3)))
    # consistent: the true depth at a 2 deg / 4 cm estimate enters and pulls the state back
    ok = terms_with_depth(msg, depth)
    fs = ok.factors({5: 5 * S}, values)
    assert len(fs) == 1 and ok.counts["frame_to_map"] == 1 and ok.counts["gated_chi2"] == 0
    (_, g), = ok.gate_log
    assert g.reason == "" and g.chi2 < g.limit and g.n_valid >= 180
    # depth 20 % short (the scale error of a monocular estimate, or a biased network): most points still lie
    # inside the wide observed band, so overlap alone would let it in, but its whitened error is implausible
    bad = terms_with_depth(msg, depth * 0.8)
    assert bad.factors({5: 5 * S}, values) == []
    assert bad.counts["gated_chi2"] == 1 and bad.counts["frame_to_map"] == 0
    assert bad.counts["frame_to_map_no_target"] == 1
    (_, g), = bad.gate_log
    assert g.reason == "chi2" and g.n_valid >= 150 and g.chi2 > 1.5 * g.limit
    assert g.limit == pytest.approx(chi2.ppf(0.999, 10)) and g.dof == 10  # min(n_valid, N_eff)
    assert bad.factors({5: 5 * S}, values) == [] and bad.counts["gated_chi2"] == 1  # decided once per state
    # the gate off: the same factor enters (what the graph got before the gate)
    off = terms_with_depth(msg, depth * 0.8, O2PConfig(enabled=True, gate_chi2_p=0))
    assert len(off.factors({5: 5 * S}, values)) == 1 and off.counts["frame_to_map"] == 1


def test_chi2_statistic_is_the_capped_whitened_error_the_graph_sees(room):
    msg, renderer = room
    T = view(VIEW)
    p, s = select_depth_points(renderer.render(K, W, H, T) * 0.9, np.full((H, W), 0.03, np.float32), K, 200)
    field = field_of_message(msg)
    for n_eff in (10.0, 0.0):
        cfg = O2PConfig(enabled=True, effective_points=n_eff, gate_chi2_p=0)
        f = OccupancyToPoint(field, msg.l_min, p, s, key_a=X(1), T_WB=np.eye(4), effective_points=n_eff)
        g = consistency(f, T, np.eye(4), cfg)
        assert g.reason == "" and g.limit == np.inf
        values = gtsam.Values()
        values.insert(X(1), gtsam.Pose3(T))
        plain = f.factor(g.n_valid)  # Tukey off at this error: its error is the plain quadratic one
        rows = plain.unwhitenedError(values)
        assert g.chi2 == pytest.approx(float(rows @ rows), rel=1e-9)
        assert g.dof == (min(g.n_valid, n_eff) if n_eff else g.n_valid)


def test_points_barely_overlapping_the_observed_field_are_rejected(room):
    msg, renderer = room
    T_true = view(VIEW)
    depth = renderer.render(K, W, H, T_true)
    depth[:, : int(0.6 * W)] = 40.0  # 60 % of the image far beyond the room: outside every observed voxel
    cfg = O2PConfig(enabled=True, max_points_frame=400)
    values = gtsam.Values()
    values.insert(X(5), gtsam.Pose3(T_true))
    terms = terms_with_depth(msg, depth, cfg)
    assert terms.factors({5: 5 * S}, values) == []
    (_, g), = terms.gate_log
    assert g.reason == "overlap" and terms.counts["gated_overlap"] == 1
    assert cfg.min_points_in_field <= g.n_valid < 0.5 * g.n_points  # M_min alone would have let it in
    loose = terms_with_depth(msg, depth, O2PConfig(enabled=True, max_points_frame=400, min_inside_fraction=0.2))
    assert len(loose.factors({5: 5 * S}, values)) == 1


def test_map_to_map_term_is_gated_at_the_anchor_estimate(room):
    """The loop closer builds a map-to-map term at its graph's anchor poses: consistent there it is a factor;
    with submap m's points 20 % short of o's surfaces it is None (the closer counts and skips it)."""
    from services.backend.o2p.map_to_map import MapToMap

    msg, renderer = room
    field = field_of_message(msg)
    T_m = view(VIEW)  # m's anchor keyframe = its submap frame's camera; o's anchor at the identity
    depth = renderer.render(K, W, H, T_m)
    cfg = O2PConfig(enabled=True)
    for scale, accepted in ((1.0, True), (0.8, False)):
        p_C, sig = select_depth_points(depth * scale, np.full((H, W), 0.03, np.float32), K, 1000)
        term = MapToMap(1, 0, 7, 1, np.eye(4), np.eye(4), p_C, sig, field, msg.l_min, cfg)
        f = term.build(X(7), X(1), perturbed(T_m, 5, 1.0, 0.02), np.eye(4))
        assert (f is not None) == accepted
    # consecutive submaps overlap little by design (a new one starts where the overlap fell below eps_vol): a
    # consistent term with 30 % of its points inside o's field is built (the frame-to-map overlap gate would refuse)
    far = depth.copy()
    far[:, : int(0.7 * W)] = 40.0
    p_C, sig = select_depth_points(far, np.full((H, W), 0.03, np.float32), K, 1000)
    term = MapToMap(1, 0, 7, 1, np.eye(4), np.eye(4), p_C, sig, field, msg.l_min, cfg)
    g = consistency(OccupancyToPoint(field, msg.l_min, p_C, sig, key_a=X(7), T_WB=np.eye(4), effective_points=10),
                    T_m, np.eye(4), cfg)
    assert g.reason == "overlap" and g.n_valid >= cfg.min_points_in_field
    assert term.build(X(7), X(1), perturbed(T_m, 5, 1.0, 0.02), np.eye(4)) is not None
