"""The network path of the depth pipeline (no transport): weights from a JSON+pt pair, keyframes announced
after their frames become MVS sources, fusion of stereo and MVS never has a larger sigma than either, and no source
keeps depth on the stereo depth's flying pixels."""
import numpy as np

from tests.depth_nets import random_network_pipeline


def test_network_pipeline_with_keyframes(tmp_path):
    pipe = random_network_pipeline(tmp_path, 2.0, 0.5, mvs_sources=2)
    assert pipe.method == "network" and pipe.stereo_gain == 2.0 and pipe.mvs_gain == 0.5
    rng = np.random.default_rng(0)
    raw = [rng.integers(0, 255, (480, 752), dtype=np.uint8) for _ in range(4)]
    T_WS = [np.eye(4) for _ in range(4)]
    for i, T in enumerate(T_WS):
        T[0, 3] = 0.05 * i
    # without a pose: stereo only
    res = pipe.process(0, raw[0], raw[1], None)
    assert res.mvs is None and res.T_WC is None and res.fused is res.stereo
    assert res.stereo[0].shape == (384, 512)
    # frames 1..3 seen; keyframes 1 and 2 announced later (and one unknown stamp that is ignored)
    for i in (1, 2, 3):
        pipe.remember_frame(i, raw[i])
    pipe.update_keyframes(np.array([1, 2, 99]), np.stack([T_WS[1], T_WS[2], T_WS[0]]))
    assert pipe.n_keyframe_views == 2
    res = pipe.process(3, raw[3], raw[0], T_WS[3])
    assert res.n_sources == 2 and res.mvs is not None
    (ds, ss), (dm, sm), (df, sf) = res.stereo, res.mvs, res.fused
    both = np.isfinite(ds) & np.isfinite(dm)
    assert both.mean() > 0.5
    assert (sf[both] <= np.minimum(ss[both], sm[both]) * (1 + 1e-5)).all()
    lo, hi = np.minimum(ds, dm)[both], np.maximum(ds, dm)[both]
    assert ((df[both] >= lo * (1 - 1e-5)) & (df[both] <= hi * (1 + 1e-5))).all()  # a convex combination
    assert not (~np.isfinite(ds) & np.isfinite(dm)).any()  # stereo and MVS share the valid region
    # a silhouette in the stereo depth: its flying pixels have no depth from any source (MVS alone there would bring
    # the curtain back into the fused map), counted; the object and the background on either side keep theirs
    near, far, f_b = 1.5, 3.0, pipe.f_px * pipe.baseline_m
    disp = np.full(512, f_b / far)
    disp[:256] = f_b / near
    disp[256:262] = np.linspace(f_b / near, f_b / far, 8)[1:-1]  # the network's ramp over 6 px
    step = np.tile((f_b / disp).astype(np.float32), (384, 1))
    pipe.stereo = lambda left, right: (step, np.full_like(step, 0.02))
    before = pipe.flying_px
    (ds, _), (dm, _), (df, _) = (pipe.process(4, raw[0], raw[1], T_WS[3]).__getattribute__(n) for n in ("stereo", "mvs", "fused"))
    rows = np.isfinite(step[:, 0]) & pipe.valid[:, 250] & pipe.valid[:, 270]
    ramp = np.zeros_like(pipe.valid)
    ramp[np.ix_(rows, np.arange(257, 261))] = True
    assert pipe.flying_px - before >= ramp.sum() and ramp.any()
    assert np.isnan(ds[ramp]).all() and np.isnan(dm[ramp]).all() and np.isnan(df[ramp]).all()
    assert np.isfinite(df[rows, 240]).all() and np.isfinite(df[rows, 280]).all() and np.isfinite(dm[rows, 240]).all()
    np.testing.assert_allclose(res.T_WC, T_WS[3] @ pipe.T_SC)


def test_uncertain_pixels_are_kept_marked_for_free_space_only_and_counted(tmp_path):
    """depth.max_relative_sigma: a pixel whose sigma exceeds k x depth stays in stereo, MVS and fused alike (its free
    space is still known), the result says k so that a map takes no surface from it, and the fused map's surface
    and uncertain pixels are counted."""
    keep_all = random_network_pipeline(tmp_path, 1.0, 1.0, mvs_sources=1)
    rng = np.random.default_rng(1)
    raw = [rng.integers(0, 255, (480, 752), dtype=np.uint8) for _ in range(3)]
    T1, T2 = np.eye(4), np.eye(4)
    T2[0, 3] = 0.1
    outs = []
    for k in (0.0, None):
        pipe = keep_all if k == 0.0 else None
        if pipe is None:  # the same weights (fixed seed), so the same depth and sigma before the cap
            # k between two of the relative sigmas, splitting the pixels as evenly as their ties allow (an untrained
            # network's output takes few distinct values)
            rel = outs[0].stereo[1] / outs[0].stereo[0]
            u = np.unique(rel[np.isfinite(rel)])
            mids = (u[1:] + u[:-1]) / 2
            k = float(mids[np.argmin([abs(np.mean(rel[np.isfinite(rel)] > m) - 0.5) for m in mids])])
            pipe = random_network_pipeline(tmp_path, 1.0, 1.0, mvs_sources=1, max_relative_sigma=k)
        pipe.remember_frame(1, raw[0])
        pipe.update_keyframes(np.array([1]), T1[None])
        outs.append(pipe.process(2, raw[1], raw[2], T2))
    full, capped = outs
    assert keep_all.uncertain_px == 0 and keep_all.confident_px == 0  # k = 0: nothing dropped, nothing counted
    for name in ("stereo", "mvs", "fused"):
        (d0, s0), (d1, s1) = getattr(full, name), getattr(capped, name)
        with np.errstate(invalid="ignore"):
            bad = s0 > k * d0
        if name == "stereo":  # some stereo pixels over k, some under (the untrained MVS's may be all over or under)
            assert 0.1 < bad.sum() / np.isfinite(d0).sum() < 0.9
        np.testing.assert_array_equal(d1, d0)  # nothing dropped
        np.testing.assert_array_equal(s1, s0)
    assert full.surface_max_relative_sigma == 0.0 and capped.surface_max_relative_sigma == k
    d0, s0 = full.fused
    with np.errstate(invalid="ignore"):
        assert pipe.uncertain_px == int(np.count_nonzero(s0 > k * d0)) > 0
    assert pipe.confident_px == int(np.count_nonzero(np.isfinite(d0))) - pipe.uncertain_px > 0
    # only a learned sigma is capped: the heuristic one grows with depth alone (the cap would be a depth cut)
    heur = random_network_pipeline(tmp_path, 1.0, 1.0, mvs_sources=1, max_relative_sigma=k, stereo_sigma="heuristic",
                                   heuristic_sigma_coeff=50.0)  # 50 px: every pixel over the cap
    assert not heur.learned_sigma and pipe.learned_sigma
    res_h = heur.process(2, raw[1], raw[2], None)
    d_h, s_h = res_h.stereo
    with np.errstate(invalid="ignore"):
        assert (s_h > k * d_h).any()  # over the cap, and still every pixel places its surface
    assert heur.uncertain_px == 0 and res_h.surface_max_relative_sigma == 0.0
