"""Place recognition and PnP verification on rendered images (services/app/synth), no transport.

A rig of two EuRoC cameras flies a circle in a scene (seed 7: neither an evaluation replica, seed 0, nor a
vocabulary training scene, seeds 100-103) and comes back to its start slightly offset. The shipped
vocabulary must find the start keyframe for the revisit; PnP against the start keyframe's landmarks
(ground-truth depth) must recover the revisit's pose, and must reject a keyframe of another place.
"""

import cv2
import numpy as np
import pytest

from shared.vio.cameras import camera_from_calib
from services.frontend.config import FrontendConfig
from services.backend.loop.place_recognition import PlaceDatabase
from services.backend.loop.verification import FeatureSet, verify_pnp
from services.backend.loop.vocabulary import Vocabulary, hamming, k_majority, l1_score
from shared.geometry import inv_T
from tools.build_vocabulary import frontend_descriptors, look_pose

# e2e tier: a textured scene and a 25-keyframe flight rendered through the real rig (~30 s of CPU); the loop
# closer's logic on synthetic features is in the unit tier (tests/test_loop_closer.py)
pytestmark = pytest.mark.e2e

N_CIRCLE = 24


@pytest.fixture(scope="module")
def world():
    from shared.paths import euroc_files
    from services.app.synth.render import Renderer
    from services.app.synth.replica import load_calibration
    from services.app.synth.scene import build_scene, site_positions

    cams = load_calibration(euroc_files("V1_02")["calib"])[0][:2]
    renderer = Renderer(build_scene("vicon-b", seed=7), cams)
    centre = site_positions("vicon").mean(axis=0)
    centre[2] = 1.3
    T_SC0 = cams[0].T_SC

    def body_pose(angle, offset=(0.0, 0.0, 0.0), dyaw=0.0):
        p = centre + 0.8 * np.array([np.cos(angle), np.sin(angle), 0.0]) + offset
        T_WC = look_pose(p, angle + np.pi / 2 + dyaw, 0.1)  # looking along the path (tangent)
        return T_WC @ inv_T(T_SC0)

    cfg, orb = FrontendConfig(), cv2.ORB_create(nfeatures=1, edgeThreshold=19, patchSize=31)
    rng = np.random.default_rng(0)

    def keyframe(T_WS):
        ids, cidx, uvs, descs, p_W = [], [], [], [], []
        for c, cam in enumerate(cams):
            T_WC = T_WS @ cam.T_SC
            img = renderer.image([T_WC], c, 0.0, rng)
            uv, d = frontend_descriptors(img, cfg, orb)
            depth = renderer.depth(T_WC, c)
            z = depth[np.clip(np.round(uv[:, 1]).astype(int), 0, depth.shape[0] - 1),
                      np.clip(np.round(uv[:, 0]).astype(int), 0, depth.shape[1] - 1)]
            ray = cam.camera.unproject(uv.astype(float))
            ray = ray[:, :3] / ray[:, 2:3] if ray.shape[1] == 3 else np.c_[ray, np.ones(len(ray))]
            p_C = ray * z[:, None]
            p_W.append(p_C @ T_WC[:3, :3].T + T_WC[:3, 3])
            ids.append(np.arange(len(uv)) + 1000 * c)
            cidx.append(np.full(len(uv), c))
            uvs.append(uv)
            descs.append(d)
        return FeatureSet(np.concatenate(ids), np.concatenate(cidx), np.concatenate(uvs), np.concatenate(descs)), \
            np.concatenate(p_W)

    angles = np.arange(N_CIRCLE) * 2 * np.pi / N_CIRCLE
    poses = [body_pose(a) for a in angles]
    kfs = [keyframe(T) for T in poses]
    revisit_T = body_pose(0.0, offset=(0.05, -0.04, 0.02), dyaw=0.05)
    revisit = keyframe(revisit_T)[0]
    backend_cams = [camera_from_calib(c) for c in cams]
    return dict(poses=poses, kfs=kfs, revisit=revisit, revisit_T=revisit_T, cams=backend_cams)


def test_shipped_vocabulary_has_provenance():
    voc = Vocabulary.load()
    assert voc.size == 1024 and voc.leaves.shape[2] == 32
    assert "tools.build_vocabulary" in voc.provenance["command"]
    assert all(s["seed"] != 0 for s in voc.provenance["scenes"])  # disjoint from the evaluation replicas


def test_k_majority_recovers_planted_clusters():
    rng = np.random.default_rng(1)
    centres = rng.integers(0, 256, (4, 32), dtype=np.uint8)
    flips = np.packbits(rng.random((400, 256)) < 0.05, axis=1)  # 5 % of the bits flipped
    desc = centres[np.repeat(np.arange(4), 100)] ^ flips
    C, labels = k_majority(desc, 4, rng)
    assert np.sort(hamming(centres, C).min(axis=1)).max() <= 2  # each planted centre found almost exactly
    assert len(np.unique(labels[:100])) == 1


def test_bow_finds_the_revisited_keyframe(world):
    voc = Vocabulary.load()
    db = PlaceDatabase(voc.size)
    for k, (fs, _) in enumerate(world["kfs"]):
        db.add(k, k * 500_000_000, voc.bag(fs.descriptors))
    q = voc.bag(world["revisit"].descriptors)
    stamp = N_CIRCLE * 500_000_000
    ref = float(l1_score(q, voc.bag(world["kfs"][-1][0].descriptors)))  # score with the predecessor
    cands = db.query(q, stamp, min_age_s=2.0, min_score=0.05, min_normalised=0.8, reference_score=ref)
    assert cands and cands[0].key in (0, 1), cands  # the start (or its neighbour), not elsewhere on the circle
    s = db.scores(q)
    far = [k for k in range(N_CIRCLE) if min(k, N_CIRCLE - k) >= 6]  # 90 degrees or more away
    print(f"BoW: best {cands[0]}, score at the start {s[0]:.3f}, best 90+ deg away {s[far].max():.3f}")
    assert s[0] > 1.5 * s[far].max(), (s[0], s[far].max())
    # a place that is not in the database yields no candidate
    db2 = PlaceDatabase(voc.size)
    for k in far:
        db2.add(k, k * 1000, voc.bag(world["kfs"][k][0].descriptors))
    assert db2.query(q, stamp, 2.0, 0.05, 0.8, reference_score=ref) == []


def test_pnp_verifies_the_right_candidate_and_rejects_a_wrong_one(world):
    cams = world["cams"]
    und = [c.undistort for c in cams]
    T_SC = np.array([c.T_SC for c in cams])
    f = np.array([c.focal_px for c in cams])
    fs0, p0 = world["kfs"][0]
    res = verify_pnp(world["revisit"], fs0, p0, und, T_SC, f)
    assert res.accepted, res.reason
    err_t = np.linalg.norm(res.T_WS[:3, 3] - world["revisit_T"][:3, 3])
    R = res.T_WS[:3, :3].T @ world["revisit_T"][:3, :3]
    err_r = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
    print(f"PnP: {res.inliers}/{res.matches} inliers, error {err_t * 100:.1f} cm {err_r:.2f} deg")
    assert err_t < 0.03 and err_r < 0.5, (err_t, err_r)
    sig = np.sqrt(np.diag(res.covariance))
    assert np.all(sig[3:] < 0.05) and np.all(sig[3:] > 1e-4)
    fs_far, p_far = world["kfs"][N_CIRCLE // 2]  # the opposite side of the circle
    wrong = verify_pnp(world["revisit"], fs_far, p_far, und, T_SC, f)
    print(f"PnP wrong candidate: {wrong.reason}")
    assert not wrong.accepted, wrong
    # wrong 3D points (shuffled) for the right keyframe are rejected too
    perm = np.random.default_rng(3).permutation(len(p0))
    assert not verify_pnp(world["revisit"], fs0, p0[perm], und, T_SC, f).accepted


@pytest.mark.parametrize("n, k, width", [(40, 300, 32), (1, 7, 32), (0, 5, 32), (5, 0, 32), (9, 11, 5)])
def test_hamming_equals_the_bit_count_of_the_xor(n, k, width):
    """hamming's word-wise popcount (64-bit words for ORB's 32 bytes, bytes otherwise) against the definition."""
    rng = np.random.default_rng(n + k + width)
    a = rng.integers(0, 256, (n, width), dtype=np.uint8)
    b = rng.integers(0, 256, (2 * k, width), dtype=np.uint8)[::2]  # a strided view works too
    want = np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2).sum(axis=2)
    got = hamming(a, b)
    assert got.dtype == np.int32 and got.shape == (n, k) and np.array_equal(got, want)
