"""One camera: the occupancy-to-point factors wait for the window's metric hold (services/backend/o2p/terms.py,
OccupancyTerms.window_factors, the terms being the estimator's extra-factor source). A real one-camera
WindowedVioEstimator on a rig standing still: before its first still keyframe it has no scale, and depth frames and
submaps of that time are never used, even later; once it stood still and ``o2p.mono_settle_s`` passed, a covisible
submap begun after the hold gets a frame-to-map factor."""

from __future__ import annotations

import numpy as np
import pytest

import vio_sim as sim
from services.backend.config import BackendConfig
from services.backend.window.estimator import WindowedVioEstimator
from shared.vio.cameras import VioCamera
from services.backend.window.mono_init import metric_hold
from services.backend.o2p.config import O2PConfig
from services.backend.o2p.terms import OccupancyTerms
from services.mapping.export import field_message
from services.mapping.mesh import ChunkMesher
from services.mapping.submaps import Submap
from shared.geometry import inv_T
from tests.o2p_room import H, K, W, mapped_room, view

S = 1_000_000_000


@pytest.fixture(scope="module")
def room():
    store, renderer, cfg = mapped_room(0.02)
    return store, renderer, cfg.l_min


def test_dense_factors_wait_for_the_metric_hold_of_a_one_camera_window(room):
    store, renderer, l_min = room
    cam = sim.rig(1)[0]
    terms = OccupancyTerms(O2PConfig(enabled=True, mono_settle_s=0.5))
    est = WindowedVioEstimator(BackendConfig(), [VioCamera(cam.T_SC, cam.undistort, cam.K[0, 0])],
                               extra_factors=[terms])  # as the back end's composition root wires it
    still = sim.Trajectory(scale=0.0)  # standing still at the origin (rotors off: no vibration)
    st, om, ac = sim.imu(still, 0.0, 4.0, 200.0)
    pts = sim.landmarks_cylinder(300, seed=2)
    # the room as the depth camera sees it from view(4.0), placed so that the rig's camera at the (identity)
    # estimate is that camera: T_WM = T_WC T_CM
    T_WM = cam.T_SC @ inv_T(view(4.0))
    depth = renderer.render(K, W, H, view(4.0))
    sigma = np.full((H, W), 0.03, np.float32)

    def submap(sid, start_ns):
        return field_message(Submap(sid, T_WM, start_ns, store, ChunkMesher(4)), l_min)

    est.initialise(int(0.5 * S), np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), static=True)
    assert not metric_hold(est)  # one camera: no scale until it stood still or was rebuilt
    j, hold_seen, built_at = 0, None, None
    for i, t in enumerate(np.arange(0.5, 3.5, 0.1)):
        stamp = int(round(t * S))
        while j < len(st) and st[j] <= stamp:
            est.add_imu(st[j], om[j], ac[j])
            j += 1
        ids, c, uv = sim.observe(np.eye(4), pts, [cam], 0.0, None, 40)
        terms.note_frame(stamp, ids)
        if i == 1:  # submap 0 begun while the window had no scale: covisible, the depth fits it exactly
            terms.add_field(submap(0, stamp))
        res = est.process_frame(stamp, ids, c, uv, is_keyframe=(i % 2 == 0))
        assert res is not None
        if hold_seen is None and metric_hold(est):
            hold_seen = stamp
        if i <= 1:  # the first still keyframe (i = 2) gives the hold
            assert terms.counts["window_without_metric_hold"] >= 1 and hold_seen is None
        if i <= 2:  # before the hold, or inside its settling time: dropped
            assert terms.add_depth(stamp, depth, sigma, K, cam.T_SC, np.eye(4), est.stamps, est.values) == 0
        if hold_seen is not None and built_at is None and stamp >= hold_seen + 0.8 * S:
            if 1 not in terms.submaps:
                terms.add_field(submap(1, stamp))  # submap 1 begun after the hold and the settling time
            terms.add_depth(stamp, depth, sigma, K, cam.T_SC, np.eye(4), est.stamps, est.values)
        if built_at is None and terms.counts["frame_to_map"]:
            built_at = stamp
    assert terms.counts["depth_before_hold"] == 3
    assert hold_seen == int(round(0.7 * S)) and terms.hold_from_ns == hold_seen + int(0.5 * S)
    assert terms.counts["window_settling"] >= 3  # 0.5 s of frames after the hold without dense factors
    # the factor came only after the hold, on submap 1; submap 0 (begun without scale) was never a target
    assert built_at is not None and built_at > terms.hold_from_ns
    assert {k[2] for k in terms._built if terms._built[k] is not None} == {1}
    assert all(sid == 1 for sid, _ in terms.gate_log)
