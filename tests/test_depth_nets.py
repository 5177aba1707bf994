"""Depth networks: output shapes and positivity, the correlation volume and the plane sweep find a known
shift / plane, convex upsampling preserves constants, weights round trip with provenance, view choice."""
import cv2
import numpy as np
import pytest
import torch

from services.depth import weights
from services.depth.mvs_net import MVSNet, plane_sweep_cost
from services.depth.net_blocks import SCALE, box_mean3, convex_upsample, normalise_image
from services.depth.stereo_net import StereoNet, correlation_volume
from services.depth.views import select_sources


def test_stereo_net_shapes_and_positive_sigma():
    torch.manual_seed(0)
    net = StereoNet(max_disparity=32).eval()
    with torch.no_grad():
        u, s = net(torch.rand(2, 1, 64, 96) * 255, torch.rand(2, 1, 64, 96) * 255)
    assert u.shape == s.shape == (2, 64, 96)
    assert (s > 0).all() and torch.isfinite(u).all()
    assert (u >= 0).all() and (u <= 32).all()  # soft-argmin and convex upsampling stay in the searched range
    with pytest.raises(ValueError):
        net(torch.rand(1, 1, 60, 96), torch.rand(1, 1, 60, 96))


def test_mvs_net_shapes_with_and_without_prior():
    torch.manual_seed(0)
    net = MVSNet(n_planes=16).eval()
    K = torch.tensor([[[80.0, 0, 47.5], [0, 80.0, 31.5], [0, 0, 1]]])
    T = torch.eye(4).repeat(1, 3, 1, 1)
    T[0, :, 0, 3] = torch.tensor([0.05, -0.1, 0.2])
    prior = torch.zeros(1, 64, 96)
    prior[0, 10, 20] = 2.0
    with torch.no_grad():
        for p in (None, prior):
            ld, s = net(torch.rand(1, 1, 64, 96) * 255, torch.rand(1, 3, 1, 64, 96) * 255, K, T, p)
            assert ld.shape == s.shape == (1, 64, 96)
            d = torch.exp(ld)
            assert (s > 0).all() and (d >= net.min_depth * 0.999).all() and (d <= net.max_depth * 1.001).all()


def test_correlation_volume_peaks_at_the_true_disparity():
    torch.manual_seed(1)
    f = torch.nn.functional.normalize(torch.randn(1, 8, 6, 20), dim=1)
    right = torch.roll(f, -3, dims=-1)  # right(x) = left(x + 3): disparity 3
    vol = correlation_volume(f, right, 8)
    assert (vol[0, :, :, 3:-3].argmax(0) == 3).all()


def test_correlation_volume_equals_its_definition():
    """The row-matrix form against the definition, slice by slice (and zero where x - d < 0)."""
    torch.manual_seed(3)
    fl, fr = torch.randn(2, 5, 4, 11), torch.randn(2, 5, 4, 11)
    vol = correlation_volume(fl, fr, 6)
    assert vol.shape == (2, 6, 4, 11)
    for d in range(6):
        want = torch.zeros(2, 4, 11)
        want[..., d:] = (fl[..., d:] * fr[..., : 11 - d]).mean(1)
        assert torch.allclose(vol[:, d], want, atol=1e-6), d


def test_plane_sweep_finds_the_fronto_parallel_plane():
    torch.manual_seed(2)
    h, w = 8, 24
    K = torch.tensor([[[312.0, 0, 47.5], [0, 312.0, 15.5], [0, 0, 1]]])  # coarse fx 78
    f_ref = torch.nn.functional.normalize(torch.randn(1, 8, h, w), dim=1)
    f_src = torch.roll(f_ref, 2, dims=-1)[:, None]  # a plane at depth 78 * 0.1 / 2 = 3.9 m shifts by 2 coarse px
    T = torch.eye(4)[None, None].clone()
    T[0, 0, 0, 3] = 0.1
    depths = torch.tensor([1.0, 2.0, 3.0, 3.9, 5.0, 8.0])
    cost = plane_sweep_cost(f_ref, f_src, K, T, depths)
    assert (cost[0, :, :, 4:-4].argmax(0) == 3).all()
    assert torch.allclose(cost[0, 3, :, 4:-4], torch.full((h, w - 8), 1 / 8), atol=1e-5)  # mean over 8 channels


def test_plane_sweep_is_the_same_whatever_the_planes_per_pass():
    torch.manual_seed(5)
    K = torch.tensor([[[312.0, 0, 47.5], [0, 312.0, 15.5], [0, 0, 1]]])
    f_ref = torch.randn(1, 8, 8, 24).contiguous(memory_format=torch.channels_last)  # as the encoder gives them
    f_src = torch.randn(1, 2, 8, 8, 24)
    T = torch.eye(4).repeat(1, 2, 1, 1)
    T[0, 0, 0, 3], T[0, 1, 1, 3] = 0.1, -0.05
    depths = torch.tensor([1.0, 2.0, 3.0, 3.9, 5.0, 8.0])
    whole = plane_sweep_cost(f_ref, f_src, K, T, depths, planes_per_pass=len(depths))
    for n in (1, 4, 5):  # 4 and 5: a last pass with fewer planes
        assert torch.allclose(plane_sweep_cost(f_ref, f_src, K, T, depths, planes_per_pass=n), whole, atol=1e-6)


def test_convex_upsample_keeps_constants_and_range():
    x = torch.full((1, 2, 5, 7), 3.0)
    up = convex_upsample(x, torch.randn(1, 9 * 16, 5, 7))
    assert up.shape == (1, 2, 20, 28) and torch.allclose(up, x.new_full(up.shape, 3.0))
    x = torch.rand(1, 1, 5, 7)
    up = convex_upsample(x, torch.randn(1, 9 * 16, 5, 7) * 5)
    assert up.min() >= x.min() - 1e-6 and up.max() <= x.max() + 1e-6


@pytest.mark.parametrize("channels_last", [False, True])
def test_convex_upsample_equals_its_definition(channels_last):
    """Fine pixel (S i + sy, S j + sx) = sum over the 3x3 neighbours k = 3 ky + kx of softmax_k(mask[9-way channel
    k S^2 + S sy + sx]) x the coarse value at (i + ky - 1, j + kx - 1), edges repeated; either memory layout."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=(2, 2, 3, 4)).astype(np.float32)
    mask = (rng.normal(size=(2, 9 * SCALE * SCALE, 3, 4)) * 3).astype(np.float32)
    m = torch.from_numpy(mask)
    up = convex_upsample(torch.from_numpy(x), m.contiguous(memory_format=torch.channels_last) if channels_last else m)
    xp = np.pad(x, ((0, 0), (0, 0), (1, 1), (1, 1)), mode="edge")
    want = np.zeros((2, 2, 3 * SCALE, 4 * SCALE))
    for i in range(3):
        for j in range(4):
            for sy in range(SCALE):
                for sx in range(SCALE):
                    logits = mask[:, np.arange(9) * SCALE * SCALE + sy * SCALE + sx, i, j].astype(np.float64)
                    wgt = np.exp(logits - logits.max(1, keepdims=True))
                    wgt /= wgt.sum(1, keepdims=True)
                    nb = np.stack([xp[:, :, i + k // 3, j + k % 3] for k in range(9)], -1)  # (B, C, 9)
                    want[:, :, SCALE * i + sy, SCALE * j + sx] = np.einsum("bck,bk->bc", nb, wgt)
    assert np.allclose(up.numpy(), want, atol=1e-5)


def test_normalise_image_gives_zero_mean_unit_std_per_image():
    img = torch.from_numpy(np.random.default_rng(4).uniform(0, 255, (2, 1, 8, 6)).astype(np.float32))
    img[1] = img[1] * 0.1 + 40
    out = normalise_image(img).numpy()
    ref = img.numpy().astype(np.float64)
    for b in range(2):
        assert np.allclose(out[b], (ref[b] - ref[b].mean()) / ref[b].std(ddof=1), atol=1e-5)
    assert torch.all(normalise_image(torch.full((1, 1, 4, 4), 7.0)) == 0)  # a flat image: no division by 0


@pytest.mark.parametrize("shape", [(2, 3, 7, 9), (1, 1, 1, 5), (1, 1, 2, 2), (1, 4, 1, 1)])
def test_box_mean3_is_the_3x3_mean_over_pixels_inside_the_image(shape):
    x = torch.randn(shape, dtype=torch.float64)
    h, w = shape[-2:]
    expect = torch.empty_like(x)
    for i in range(h):  # the definition, pixel by pixel
        for j in range(w):
            expect[..., i, j] = x[..., max(i - 1, 0):i + 2, max(j - 1, 0):j + 2].mean(dim=(-2, -1))
    assert torch.allclose(box_mean3(x), expect, atol=1e-12)
    assert torch.allclose(box_mean3(x), torch.nn.functional.avg_pool2d(x, 3, 1, 1, count_include_pad=False), atol=1e-12)


def test_weights_round_trip_with_provenance(tmp_path):
    net = StereoNet(max_disparity=16)
    weights.save(net, tmp_path / "st", "stereo", {"max_disparity": 16}, {"gain": 1.7, "seed": 3, "command": "x"})
    loaded, meta = weights.load(tmp_path / "st.pt")
    assert meta["gain"] == 1.7 and meta["seed"] == 3
    for a, b in zip(net.state_dict().values(), loaded.state_dict().values()):
        assert torch.equal(a, b)
    with pytest.raises(weights.WeightsError):
        weights.load(tmp_path / "missing.pt")
    (tmp_path / "st.json").write_text('{"arch": "stereo", "arch_args": {"max_disparity": 32}}')
    with pytest.raises(weights.WeightsError, match="does not fit"):
        weights.load(tmp_path / "st.pt")


def _pose(x, yaw_deg=0.0):
    T = np.eye(4)
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[0, 3] = x
    return T


def test_source_views_respect_baselines_and_angle():
    cands = np.stack([_pose(x) for x in (0.5, 0.2, 0.1, 0.08, 0.06, 0.01)] + [_pose(0.15, 60)])
    idx = select_sources(_pose(0.0), cands, n_max=7, min_baseline_m=0.03, max_baseline_m=0.3, max_angle_deg=35)
    chosen = cands[idx, 0, 3]
    assert 6 not in idx  # rotated by 60 deg
    assert 0 not in idx and 5 not in idx  # too far, too close
    assert np.all(np.abs(np.diff(np.sort(chosen))) >= 0.03 - 1e-12)
    assert list(idx) == [4, 2, 1]  # newest first: 0.06; 0.08 is within 3 cm of it; 0.1; 0.2


def test_bfloat16_inference_gives_the_float32_disparity():
    """The shipped stereo network under bfloat16 autocast (depth.stereo_precision) against float32 on a textured pair
    with a known shift: same disparity to a few hundredths of a pixel, outputs in float32."""
    from services.depth.stereo_net import predict_disparity

    net, _ = weights.load(weights.WEIGHTS_DIR / "stereo.pt")
    rng = np.random.default_rng(4)
    left = cv2.GaussianBlur(rng.integers(0, 255, (128, 192)).astype(np.float32), (0, 0), 1.5)
    right = np.roll(left, -6, axis=1)
    u32, s32 = predict_disparity(net, left, right)
    u16, s16 = predict_disparity(net, left, right, precision="bfloat16")
    assert u16.dtype == np.float32 and s16.dtype == np.float32
    inner = (slice(8, -8), slice(24, -8))
    assert abs(np.median(u32[inner]) - 6.0) < 0.3
    assert np.median(np.abs(u16 - u32)[inner]) < 0.05 and np.percentile(np.abs(u16 - u32)[inner], 99) < 0.3
    assert np.median(np.abs(s16 / s32 - 1)[inner]) < 0.05
    assert weights.resolve_precision("float32", "cpu") == "float32"
    assert weights.resolve_precision("auto", "cuda") == "float32"
    assert weights.resolve_precision("auto", "cpu") == ("bfloat16" if weights.cpu_has_fast_bfloat16() else "float32")
