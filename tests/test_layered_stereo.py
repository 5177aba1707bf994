"""The layered stereo generator renders exact pairs (the right view is the left one moved by the disparity,
occlusions where a nearer surface hides a farther one), its set is reproducible from the seed, and the SGBM-guided
network starts from SGBM's answer and learns from the set."""
import cv2
import numpy as np
import pytest
import torch

from services.depth.refine_net import RefineStereoNet, shift_right_image
from tools.depth.layered_stereo import Surface, camera_effects, random_frame, render_pair
from tools.depth.materials import fractal_noise, random_material



def _surface(rng, h, w_ext, u0, mask=None, gx=0.0, gy=0.0):
    tex = fractal_noise(rng, h, w_ext)
    return Surface(np.ones((h, w_ext), np.float32) if mask is None else mask, u0, gx, gy, 0.0, w_ext / 2, h / 2, tex)


def test_fronto_parallel_surfaces_move_by_their_disparity_and_occlude():
    rng = np.random.default_rng(1)
    h, w, u_max = 40, 80, 20.0
    w_ext = w + 28
    near = np.zeros((h, w_ext), np.float32)
    near[10:30, 40:60] = 1.0
    s = [_surface(rng, h, w_ext, 4.0), _surface(rng, h, w_ext, 12.0, near)]
    f = render_pair(s, h, w, u_max)
    assert np.all(f["disparity"][10:30, 40:60] == 12.0) and np.all(f["disparity"][:10] == 4.0)
    # the right image at x - u shows what the left image shows at x (integer disparities: exact)
    assert np.allclose(f["right"][20, 40 - 12:60 - 12], f["left"][20, 40:60], atol=1e-5)
    assert np.allclose(f["right"][5, 10:70], f["left"][5, 14:74], atol=1e-5)
    # background just left of the near square is hidden from the right camera (8 px = 12 - 4), the rest is seen
    assert not f["nonocc"][20, 32:40].any() and f["nonocc"][20, 20:31].all() and f["nonocc"][20, 40:60].all()
    assert not f["nonocc"][:, :4].any()  # leaves the right image's field of view


def test_slanted_surface_right_view_is_consistent():
    rng = np.random.default_rng(2)
    h, w = 32, 96
    s = [_surface(rng, h, w + 40, 10.0, gx=0.1, gy=0.05)]
    f = render_pair(s, h, w, 40.0)
    y, x = 16, 60
    u = f["disparity"][y, x]
    assert u == pytest.approx(10.0 + 0.1 * (x - (w + 40) / 2) + 0.05 * (y - h / 2), abs=1e-4)
    xr = x - u  # sample the right image there: the same surface point
    i = int(np.floor(xr))
    val = f["right"][y, i] * (i + 1 - xr) + f["right"][y, i + 1] * (xr - i)
    assert val == pytest.approx(f["left"][y, x], abs=0.02)


def test_random_frames_are_reproducible_and_plausible():
    a = random_frame(np.random.default_rng(7), [], 64, 96)
    b = random_frame(np.random.default_rng(7), [], 64, 96)
    assert np.array_equal(a["left"], b["left"]) and np.array_equal(a["disparity"], b["disparity"])
    assert a["left"].dtype == np.uint8 and a["left"].shape == (64, 96)
    assert 0 <= a["disparity"].min() and a["disparity"].max() <= a["u_max"] + 1e-4
    assert 0.3 < a["nonocc"].mean() <= 1.0
    mat = random_material(np.random.default_rng(3), [np.random.default_rng(0).random((50, 60)).astype(np.float32)], 30, 40)
    assert mat.shape == (30, 40) and np.isfinite(mat).all()
    left, right, fx = camera_effects(np.random.default_rng(4), np.full((20, 30), 0.5, np.float32),
                                     np.full((20, 30), 0.5, np.float32))
    assert left.dtype == np.uint8 and set(fx) >= {"blur", "gain_lr", "gamma", "noise", "jpeg"}


def test_shift_right_image_matches_an_integer_shift():
    right = torch.arange(2 * 1 * 4 * 10, dtype=torch.float32).view(2, 1, 4, 10)
    out = shift_right_image(right, torch.full((2, 1, 4, 10), 3.0))
    assert torch.allclose(out[..., 3:], right[..., :-3])
    half = shift_right_image(right, torch.full((2, 1, 4, 10), 0.5))
    assert torch.allclose(half[..., 1:], 0.5 * (right[..., 1:] + right[..., :-1]))


def test_refine_net_input_layer_equals_the_1x1_convolution_of_the_folded_features():
    torch.manual_seed(0)
    net = RefineStereoNet(max_disparity=16, width=16)
    feats = torch.randn(2, net.inp[0].in_channels // 16, 32, 48)
    expect = net.inp[0](torch.nn.functional.pixel_unshuffle(feats, 4))  # the layer as defined: 1x1 on the folded
    assert torch.allclose(net._fold_in(feats), expect, atol=1e-5)


@pytest.mark.e2e  # several seconds of CPU: out of the unit tier (tests/README.md)
def test_refine_net_starts_at_sgbm_and_learns():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    f = random_frame(rng, [], 48, 64, u_max=12.0)  # small: the unit tier's budget
    net = RefineStereoNet(max_disparity=16, width=16)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a)).float()[None]
    left, right, gt = t(f["left"])[:, None], t(f["right"])[:, None], t(f["disparity"])
    u, sigma = net(left, right)
    from services.depth.sgbm import SgbmParams, fill_background, sgbm_disparity

    d0 = fill_background(sgbm_disparity(f["left"], f["right"], SgbmParams(num_disparities=16)))
    assert np.allclose(u[0].detach().numpy(), d0)  # the correction head starts at zero
    assert (sigma > 0).all()
    from services.depth.losses import stereo_loss

    opt = torch.optim.Adam(net.parameters(), 3e-3)
    d0t, matched = t(d0), torch.from_numpy(np.isfinite(d0))[None]
    valid = torch.ones_like(gt, dtype=torch.bool)
    losses = []
    for _ in range(60):
        u, s = net.refine(left, right, d0t, matched)
        loss = stereo_loss(u, s, gt, valid)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.7 * losses[0]


def test_a_shard_is_written_whole_and_read_back(tmp_path):
    from tools.depth.make_stereo_data import render_shard
    from tools.depth.stereo_shards import load_shards, refine_batch

    msg = render_shard((str(tmp_path), "val", 3, 0, 2, None))
    assert "2 frames" in msg and not list((tmp_path / "val").glob("*.tmp*"))
    again = render_shard((str(tmp_path), "val", 3, 0, 2, None))
    assert again.endswith("kept")  # a shard is a function of its seed: kept, not rendered twice
    shards = load_shards(tmp_path, "val")
    assert len(shards) == 1 and shards[0]["left"].shape[0] == 2
    left, right, d0, matched, u, valid = refine_batch(shards, np.random.default_rng(0), 3, (128, 160))
    assert left.shape == (3, 1, 128, 160) and d0.shape == u.shape == (3, 128, 160)
    assert torch.isfinite(d0).all() and (u >= 0).all() and matched.dtype == torch.bool
    with pytest.raises(SystemExit, match="no complete shard"):
        load_shards(tmp_path, "train")


def test_occlusion_free_masks_the_background_hidden_left_of_a_foreground_block():
    from tools.depth.make_stereo_data import occlusion_free

    d = np.full((3, 80), 10.0, np.float32)
    d[:, 40:51] = 20.0  # lands at 20-30 in the right view, over the background of left columns 30-40
    seen = occlusion_free(d)
    assert not seen[:, :10].any()  # background x < 10 leaves the right image
    assert not seen[:, 31:40].any() and seen[:, 41:50].all()  # hidden behind the block / the block itself
    assert seen[:, 12:29].all() and seen[:, 52:].all()
    d[1, 5] = np.nan
    assert not occlusion_free(d)[1, 5]


def test_a_room_scene_becomes_a_training_shard_with_its_disparity(tmp_path):
    """make_stereo_data --rooms: a procedural room scene (make_dataset's npz) -> shard rooms_NNNN, disparity f b / z."""
    from tools.depth.make_stereo_data import room_shard
    from tools.depth.stereo_shards import frame, load_shards

    rng = np.random.default_rng(0)
    K = np.array([[100.0, 0, 80], [0, 100.0, 48], [0, 0, 1]])
    wide = cv2.GaussianBlur((rng.random((96, 216)) * 255).astype(np.uint8), (3, 3), 0)
    left, right = wide[:, 40:200], wide[:, 48:208]  # right[x - 8] = left[x]: disparity 8 px everywhere
    z = np.full((96, 160), 100.0 * 0.1 / 8.0, np.float32)
    np.savez(tmp_path / "scene_01000.npz", left=np.stack([left, left]), right=np.stack([right, right]),
             depth=np.stack([z, z]), T_WC=np.stack([np.eye(4)] * 2), K=K, baseline_m=0.1)
    job = (str(tmp_path / "out"), [str(tmp_path / "scene_01000.npz")], 0)
    assert "2 frames from 1 scenes" in room_shard(job) and room_shard(job).endswith("kept")
    shards = load_shards(tmp_path / "out", "train")
    assert [s["name"] for s in shards] == ["rooms_0000"]
    f = frame(shards[0], 1)
    np.testing.assert_allclose(f["disparity"], 8.0, atol=1 / 256)
    assert f["u_max"] == pytest.approx(8.0, abs=1e-4) and not f["nonocc"][:, :8].any() and f["nonocc"][:, 8:].all()
    m = np.isfinite(f["sgbm"])  # SGBM's search range (16 or 96 px) leaves that many left columns unmatched
    assert m[:, 96:].mean() > 0.8 and np.median(np.abs(f["sgbm"][m] - 8.0)) < 0.5
    np.savez(tmp_path / "left_only.npz", left=np.stack([left]), depth=np.stack([z]), K=K, baseline_m=0.1)
    with pytest.raises(SystemExit, match="no right views"):
        room_shard((str(tmp_path / "out"), [str(tmp_path / "left_only.npz")], 1))


def test_loader_processes_give_seeded_batches_that_differ_per_process(tmp_path):
    """train.py --loader-workers: each DataLoader process cuts crops from its own (seed, worker) generator, so two
    runs with the same seed see the same batches and two processes never repeat each other's."""
    import itertools

    from tools.depth.make_stereo_data import render_shard
    from tools.depth.stereo_shards import RefineBatches

    render_shard((str(tmp_path), "train", 3, 0, 2, None))

    def first_batches(n: int) -> list:
        loader = torch.utils.data.DataLoader(RefineBatches(tmp_path, 2, (64, 96), seed=5), batch_size=None,
                                             num_workers=2)
        return list(itertools.islice(loader, n))

    a, b = first_batches(4), first_batches(4)
    assert a[0][0].shape == (2, 1, 64, 96) and a[0][4].shape == (2, 64, 96)
    for x, y in zip(a, b):  # same seed: the same crops, in the same order
        assert all(torch.equal(p, q) for p, q in zip(x, y))
    # batches alternate between the two processes: process 0's first against process 1's first
    assert not torch.equal(a[0][0], a[1][0])


def test_recalibrate_sets_the_median_rule_gain_and_keeps_the_old_one_on_record(tmp_path):
    import json

    from services.depth import weights
    from services.depth.sgbm import fill_background
    from tools.depth import recalibrate
    from tools.depth.make_stereo_data import render_shard
    from tools.depth.stereo_shards import load_shards, validation_frames

    render_shard((str(tmp_path / "data"), "val", 3, 0, 2, None))
    torch.manual_seed(0)
    weights.save(RefineStereoNet(), tmp_path / "w", "stereo_refine", {"max_disparity": 96},
                 {"gain": 7.0, "gain_domain": "old", "command": "python -m tools.depth.train ..."})
    assert recalibrate.main([str(tmp_path / "w.pt"), "--data", str(tmp_path / "data"), "--rule", "median"]) == 0
    meta = json.loads((tmp_path / "w.json").read_text())
    assert meta["command"] == "python -m tools.depth.train ..."  # the training provenance stays
    (rec,) = meta["recalibrations"]
    assert rec["previous_gain"] == 7.0 and rec["gain"] == meta["gain"] and rec["rule"] == "median"
    net, meta2 = weights.load(tmp_path / "w.pt", "cpu")
    ratios = []
    with torch.inference_mode():  # with the new gain the validation pixels' median |e| / sigma is ln 2
        for f in validation_frames(load_shards(tmp_path / "data", "val")):
            t = lambda a: torch.from_numpy(np.ascontiguousarray(a))[None]
            u, su = net.refine(t(f["left"]).float()[:, None], t(f["right"]).float()[:, None],
                               t(fill_background(f["sgbm"])), t(np.isfinite(f["sgbm"])))
            ratios.append((np.abs(u[0].numpy() - f["disparity"]) / (meta2["gain"] * su[0].numpy())).ravel())
    assert np.median(np.concatenate(ratios)) == pytest.approx(np.log(2), rel=1e-3)
    from services.depth.stereo_net import StereoNet

    weights.save(StereoNet(96), tmp_path / "s", "stereo", {"max_disparity": 96}, {"gain": 1.0})
    with pytest.raises(SystemExit, match="only 'stereo_refine'"):
        recalibrate.main([str(tmp_path / "s.pt"), "--data", str(tmp_path / "data")])


def test_a_stereo_net_hole_fill_starts_from_sgbm_and_the_fillers_disparity_and_survives_save_and_load(tmp_path):
    """hole_fill='stereo_net': untrained (zero correction) the output is SGBM where it matched and the held
    StereoNet's disparity in SGBM's holes; the filler's weights travel in the same file."""
    from services.depth import weights
    from services.depth.sgbm import SgbmParams, sgbm_disparity

    torch.manual_seed(0)
    f = random_frame(np.random.default_rng(1), [], 64, 96, u_max=12.0)
    net = RefineStereoNet(max_disparity=16, width=16, hole_fill="stereo_net").eval()
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a)).float()[None, None]
    with torch.inference_mode():
        u, sigma = net(t(f["left"]), t(f["right"]))
        fill = net.filler(t(f["left"]), t(f["right"]))[0][0].numpy()
    sg = sgbm_disparity(f["left"], f["right"], SgbmParams(num_disparities=16))
    m = np.isfinite(sg)
    assert 0 < m.mean() < 1
    np.testing.assert_allclose(u[0].numpy()[m], sg[m], atol=1e-5)
    np.testing.assert_allclose(u[0].numpy()[~m], np.maximum(fill[~m], 0), atol=1e-5)
    assert not any(p.requires_grad for p in net.filler.parameters())
    weights.save(net, tmp_path / "w", "stereo_refine", {"max_disparity": 16, "width": 16, "hole_fill": "stereo_net"},
                 {"gain": 1.0})
    again, meta = weights.load(tmp_path / "w.pt")
    with torch.inference_mode():
        np.testing.assert_allclose(again(t(f["left"]), t(f["right"]))[0].numpy(), u.numpy(), atol=1e-4)
    with pytest.raises(ValueError, match="hole_fill"):
        RefineStereoNet(hole_fill="nearest")


def test_shards_with_a_fill_start_the_holes_from_it_and_training_must_match_it(tmp_path):
    """stereo_shards DATA --fill-weights W writes fill.npy + fill.json; the crops' d0 then takes SGBM's holes from
    it, and train.py refuses data whose fill is not the one --hole-fill names (or a fill it was not given)."""
    from services.depth import weights
    from services.depth.stereo_net import StereoNet
    from tools.depth.make_stereo_data import render_shard
    from tools.depth.stereo_shards import add_fill, frame, initial_disparity, load_shards
    from tools.depth.train import check_hole_fill

    render_shard((str(tmp_path), "train", 3, 0, 2, None))
    f = frame(load_shards(tmp_path, "train")[0], 0)
    holes = ~np.isfinite(f["sgbm"])
    assert "fill" not in f and holes.any() and np.isfinite(initial_disparity(f)).all()
    assert check_hole_fill(tmp_path, "") == {}
    torch.manual_seed(0)
    w = weights.save(StereoNet(96), tmp_path / "sn", "stereo", {"max_disparity": 96}, {"gain": 1.0})
    assert add_fill(tmp_path, str(w), threads=1) == 2 and add_fill(tmp_path, str(w), threads=1) == 0  # kept
    f = frame(load_shards(tmp_path, "train")[0], 0)
    d0 = initial_disparity(f)
    np.testing.assert_array_equal(d0[holes], f["fill"][holes])
    np.testing.assert_array_equal(d0[~holes], f["sgbm"][~holes])
    assert check_hole_fill(tmp_path, str(w)) == {"hole_fill_weights": str(w)}
    with pytest.raises(SystemExit, match="--hole-fill"):
        check_hole_fill(tmp_path, "")
    with pytest.raises(SystemExit, match="has a fill from"):
        check_hole_fill(tmp_path, str(tmp_path / "other.pt"))
    with pytest.raises(SystemExit, match="not .*other.pt"):
        add_fill(tmp_path, str(tmp_path / "other.pt"))
