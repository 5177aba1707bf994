"""Guided matching of loop verification (services/backend/loop/verification.py), on simulated features.

Landmarks on a cylinder carry random ORB-like codes; a query keyframe observes them with a few flipped bits and
pixel noise through a two-camera rig with distortion. Checked against the ground-truth pose and identities:

* matching by projection pairs each feature with its own landmark at the true pose, even when a twin landmark
  with the same code lies elsewhere, and finds almost nothing at a pose 0.5 m and 10 deg off;
* a revisit that shares too few descriptor matches with the candidate keyframe is rejected without guidance and
  accepted with it (the wider set's landmarks found where they project), with the right pose and landmark ids;
* a wrong candidate (the same codes at shuffled positions) stays rejected with guidance.
"""

import numpy as np

import vio_sim as sim
from services.backend.loop.verification import FeatureSet, Guide, match_by_projection, normalised_xy, verify_pnp
from shared.geometry import inv_T, so3_exp

RNG = np.random.default_rng(11)
PTS = sim.landmarks_cylinder(800, seed=12)
CODES = RNG.integers(0, 256, (len(PTS), 32), dtype=np.uint8)
CAMS = sim.rig(2, dist=(-0.1, 0.01, 0.0005, -0.0003))
T_SC = np.array([c.T_SC for c in CAMS])
FOCAL = np.array([c.K[0, 0] for c in CAMS])
UNDISTORT = [c.undistort for c in CAMS]


def _pose(yaw: float, p=(0.3, -0.2, 0.1)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = so3_exp(np.array([0.02, -0.01, yaw])), p
    return T


def _flipped(codes: np.ndarray, rng, share=0.04) -> np.ndarray:
    return codes ^ np.packbits(rng.random((len(codes), 256)) < share, axis=1)


def _query(T_WS: np.ndarray, rng) -> FeatureSet:
    ids, cams, uv = sim.observe(T_WS, PTS, CAMS, 0.5, rng, 80)
    return FeatureSet(ids, cams, uv, _flipped(CODES[ids], rng))


def _stored(ids: np.ndarray, rng, p_W=None) -> tuple[FeatureSet, np.ndarray]:
    """A stored set of landmarks ``ids`` (their features' pixels do not matter to verification)."""
    fs = FeatureSet(ids, np.zeros(len(ids), np.int16), np.zeros((len(ids), 2)), _flipped(CODES[ids], rng))
    return fs, (PTS[ids] if p_W is None else p_W).astype(float)


def test_match_by_projection_pairs_features_with_their_own_landmarks():
    rng = np.random.default_rng(1)
    T = _pose(0.4)
    q = _query(T, rng)
    seen = np.unique(q.landmark_ids)
    # every seen landmark has a twin with its code, far from it (another part of the cylinder)
    twins = PTS[seen] * np.array([-1.0, -1.0, 1.0])
    p_W = np.concatenate([PTS[seen], twins])
    desc = np.concatenate([_flipped(CODES[seen], rng), _flipped(CODES[seen], rng)])
    xy = normalised_xy(q, UNDISTORT)
    cams = np.asarray(q.camera_index, np.int64)
    iq, il = match_by_projection(T, cams, xy, q.descriptors, p_W, desc, T_SC, FOCAL, 8.0, 50)
    own = il < len(seen)
    assert len(iq) >= 0.9 * len(q.landmark_ids), (len(iq), len(q.landmark_ids))
    assert own.all()  # never a twin
    np.testing.assert_array_equal(seen[il], q.landmark_ids[iq])
    off = T @ np.block([[so3_exp(np.array([0.0, 0.0, np.deg2rad(10)])), np.array([[0.5], [0.0], [0.0]])],
                        [np.zeros((1, 3)), np.ones((1, 1))]])
    iq_off, _ = match_by_projection(off, cams, xy, q.descriptors, p_W, desc, T_SC, FOCAL, 8.0, 50)
    assert len(iq_off) < 0.1 * len(iq), len(iq_off)


def _revisit():
    rng = np.random.default_rng(2)
    T = _pose(1.1)
    q = _query(T, rng)
    seen = np.unique(q.landmark_ids)
    old = _stored(seen[:16], rng)  # the candidate keyframe shares 16 landmarks with the query
    others = np.setdiff1d(np.arange(len(PTS)), seen)[:300]
    wide = _stored(np.concatenate([seen[:16], seen[16:], others]), rng)  # its neighbours see the rest (and more)
    return T, q, old, wide, rng


def test_guided_matching_accepts_a_revisit_that_shares_few_matches():
    T, q, old, wide, _ = _revisit()
    args = (UNDISTORT, T_SC, FOCAL, 1.0, 50, 3.0, 25, 0.35, 4.0)
    plain = verify_pnp(q, *old, *args)
    assert not plain.accepted and not plain.expanded, plain.reason
    res = verify_pnp(q, *old, *args, guide=Guide(*wide, seed_inliers=10, radius_px=8.0))
    assert res.accepted and res.expanded, res.reason
    assert res.inliers >= 0.8 * len(q.landmark_ids), (res.inliers, len(q.landmark_ids))
    # old_index indexes the guide's set: the inliers pair each feature with its own landmark
    np.testing.assert_array_equal(wide[0].landmark_ids[res.old_index], q.landmark_ids[res.query_index])
    err = inv_T(T) @ res.T_WS
    assert np.linalg.norm(err[:3, 3]) < 0.01
    assert np.degrees(np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1))) < 0.2


def test_guided_matching_keeps_a_wrong_candidate_rejected():
    T, q, old, wide, rng = _revisit()
    perm = rng.permutation(len(wide[1]))
    wrong_old = _stored(old[0].landmark_ids, rng, PTS[rng.permutation(len(PTS))[:len(old[1])]])
    wrong_wide = (wide[0], wide[1][perm])
    res = verify_pnp(q, *wrong_old, UNDISTORT, T_SC, FOCAL, 1.0, 50, 3.0, 25, 0.35, 4.0,
                     guide=Guide(*wrong_wide, seed_inliers=6, radius_px=8.0))
    assert not res.accepted, res
