"""Occupancy field: inverse sensor model (eq. 3), running mean (eq. 4), integration of ray-cast depth of
known geometry, free/unknown space, sigma and the surface band, trilinear L and its gradient."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from shared.occupancy.blocks import BlockStore, pack_keys, unpack_keys
from services.mapping.config import SensorModelConfig
from services.mapping.integrate import integrate
from shared.occupancy.query import FREE, OCCUPIED, UNKNOWN, BlockField, interpolate, near_surface_field, state
from services.mapping.sensor_model import log_odds, prepare_depth, surface_thickness
from raycast_depth import DepthRenderer, intrinsics, look_at, room_scene

W, H = 512, 384
K = intrinsics(W, H)


def wall(z: float, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    return np.full((H, W), z, np.float32), np.full((H, W), sigma, np.float32)


def integrate_once(depth, sigma, T_MC=np.eye(4), cfg=None, store=None):
    cfg = cfg or SensorModelConfig()
    store = store or BlockStore(cfg.voxel_size_m)
    d, s, _ = prepare_depth(depth, sigma, cfg)
    res = integrate(store, d, s, K, T_MC, cfg)
    return store, res


def test_pack_unpack_and_insert_lookup():
    rng = np.random.default_rng(1)
    ijk = rng.integers(-2**20, 2**20, (500, 3))
    assert np.array_equal(unpack_keys(pack_keys(ijk)), ijk)
    store = BlockStore(0.025)
    keys = pack_keys(ijk[:300])
    s1 = store.insert(keys)
    s2 = store.insert(pack_keys(ijk[200:]))  # 100 existing, 200 new
    assert np.array_equal(s2[:100], s1[200:]) and store.n_blocks == len(np.unique(pack_keys(ijk)))
    assert np.array_equal(store.lookup(pack_keys(ijk[:300])), s1)
    absent = rng.integers(-2**20, 2**20, (200, 3))
    absent = absent[~np.isin(pack_keys(absent), pack_keys(ijk))]
    assert (store.lookup(pack_keys(absent)) == -1).all()
    with pytest.raises(ValueError):
        pack_keys(np.array([[2**20, 0, 0]]))


def test_inverse_sensor_model_shape():
    l_min, s = -5.015, 0.03
    tau = 0.1
    l, upd = log_odds(np.array([-1.0, -3 * s, 0.0, 0.02, tau / 2, 0.09, tau, 0.5]), s, tau, l_min)
    assert np.allclose(l[:5], [l_min, l_min, 0.0, -l_min * 0.02 / (3 * s), -l_min * tau / (6 * s)])
    assert l[5] == l[4]  # l_max between tau/2 and tau (continuity)
    assert upd.tolist() == [True] * 6 + [False, False]  # beyond tau: no update


def test_wall_profile_matches_eq3_and_running_mean():
    cfg = SensorModelConfig()
    depth, sigma = wall(2.0, 0.04)
    store, res = integrate_once(depth, sigma, cfg=cfg)
    f = BlockField.of(store)
    # voxels on the optical axis: centres at (0.0125, 0.0125, z); the ray scale there is ~1
    z = (np.arange(0, 100) + 0.5) * cfg.voxel_size_m
    ijk = np.column_stack([np.zeros(100, int), np.zeros(100, int), np.arange(100)])
    L, w = f.voxels(ijk)
    p = (ijk + 0.5) * cfg.voxel_size_m
    scale = np.linalg.norm(p, axis=1) / p[:, 2]
    tau = surface_thickness(2.0 * scale, cfg, 0.04 * scale)
    ref, upd = log_odds((z - 2.0) * scale, 0.04 * scale, tau, cfg.l_min)
    near = z >= cfg.near_m
    assert np.allclose(L[upd & near], ref[upd & near], atol=1e-5)
    assert (w[upd & near] == 1).all() and (w[~upd] == 0).all()
    # a second identical frame keeps the mean; a frame of a wall 10 cm closer averages (eq. 4)
    integrate_once(depth, sigma, cfg=cfg, store=store)
    L2, w2 = BlockField.of(store).voxels(ijk)
    assert np.allclose(L2[upd & near], ref[upd & near], atol=1e-5) and (w2[upd & near] == 2).all()
    d3, s3 = wall(1.9, 0.04)
    integrate_once(d3, s3, cfg=cfg, store=store)
    ref3, upd3 = log_odds((z - 1.9) * scale, 0.04 * scale, surface_thickness(1.9 * scale, cfg, 0.04 * scale), cfg.l_min)
    L3, w3 = BlockField.of(store).voxels(ijk)
    both = upd & upd3 & near
    assert np.allclose(L3[both], (2 * ref[both] + ref3[both]) / 3, atol=1e-4)
    assert res.n_clear > 0 and res.n_voxel_blocks > 0


def test_a_pixel_without_depth_updates_nothing_along_its_ray():
    """Pixels without depth (NaN: outside the range, dropped as uncertain or at an edge) leave their rays alone, also
    among valid pixels. The kernel's fast-math once assumed no NaN and carved every such ray free, through and behind
    the surfaces (a tenth of a real frame's voxel updates)."""
    cfg = SensorModelConfig()
    depth, sigma = wall(2.0, 0.03)
    cols = np.arange(W)
    no_depth = (cols // 6) % 2 == 1  # stripes of 6 px without depth between stripes with
    depth[:, no_depth] = np.nan
    store, _ = integrate_once(depth, sigma, cfg=cfg)
    f = BlockField.of(store)
    ijk = np.stack(np.meshgrid(np.arange(-30, 30), [0], np.arange(20, 90), indexing="ij"), -1).reshape(-1, 3)
    p = (ijk + 0.5) * cfg.voxel_size_m
    u = np.floor(K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2] + 0.5).astype(int)
    v = np.floor(K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2] + 0.5).astype(int)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    L, w = f.voxels(ijk)
    # near and behind the wall (in front of it, whole blocks far enough from it are carved as one: min_valid_fraction)
    on_nan = inside & no_depth[np.clip(u, 0, W - 1)] & (p[:, 2] > 1.85)
    on_valid = inside & ~no_depth[np.clip(u, 0, W - 1)] & (p[:, 2] < 1.9)
    assert on_nan.sum() > 200 and on_valid.sum() > 500
    assert (w[on_nan] == 0).all(), f"{int((w[on_nan] > 0).sum())} voxels on rays without depth were updated"
    assert (w[on_valid] > 0).all() and (L[on_valid] < 0).all()


def test_w_saturates_at_w_max():
    cfg = SensorModelConfig(w_max=3)
    depth, sigma = wall(1.0, 0.03)
    store = None
    for _ in range(5):
        store, _ = integrate_once(depth, sigma, cfg=cfg, store=store)
    f = BlockField.of(store)
    _, w = f.voxels(np.array([[0, 0, 20], [0, 0, 39]]))  # 0.51 m (free, voxel), 0.99 m (band)
    assert w.max() == 3


def test_sigma_widens_the_surface_band():
    widths, slopes = [], []
    for s in (0.03, 0.09):  # both above sigma_min_m (0.025)
        store, _ = integrate_once(*wall(2.0, s))
        p = np.column_stack([np.full(400, 0.0125), np.full(400, 0.0125), np.linspace(1.4, 2.04, 400)])
        L, g, v = interpolate(BlockField.of(store), p)
        band = v & (L > -5.0) & (L < 0.0)
        widths.append(np.ptp(p[band, 2]))
        at = np.argmin(np.abs(np.where(v, L, np.inf)))
        slopes.append(g[at, 2])
    # the free-to-surface ramp is 3 sigma long (plus up to one voxel of interpolation)
    assert 0.09 <= widths[0] <= 0.09 + 0.03 and 0.27 <= widths[1] <= 0.27 + 0.03
    # |grad L| at the surface = |l_min| / (3 sigma): sigma_map of eq. 7 recovers sigma
    assert slopes[0] == pytest.approx(5.015 / (3 * 0.03), rel=0.05) and slopes[1] == pytest.approx(5.015 / (3 * 0.09), rel=0.05)


@pytest.fixture(scope="module")
def room_map():
    mesh = room_scene()
    renderer = DepthRenderer(mesh)
    cfg = SensorModelConfig()
    store = BlockStore(cfg.voxel_size_m)
    poses = []
    for a in np.linspace(0, 2 * np.pi, 10, endpoint=False):
        eye = np.array([3.0 + 0.8 * np.cos(a), 2.5 + 0.8 * np.sin(a), 1.5])
        T = look_at(eye, eye + np.array([np.cos(a + 0.5), np.sin(a + 0.5), -0.2]))
        d, s, _ = prepare_depth(renderer.render(K, W, H, T), np.full((H, W), 0.02, np.float32), cfg)
        integrate(store, d, s, K, T, cfg)
        poses.append(T)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return store, scene, poses, cfg


def test_room_mesh_within_a_voxel(room_map):
    from services.mapping.mesh import ChunkMesher

    store, scene, _, cfg = room_map
    mesher = ChunkMesher(4)
    mesher.mark(store, np.arange(store.n_blocks))
    mesher.update(store)
    v, f = mesher.mesh()
    assert len(f) > 10000
    dist = scene.compute_distance(o3d.core.Tensor(v)).numpy()
    assert dist.mean() < 0.25 * cfg.voxel_size_m and np.percentile(dist, 99) < cfg.voxel_size_m


def test_free_unknown_occupied(room_map):
    store, scene, poses, cfg = room_map
    f = BlockField.of(store)
    rng = np.random.default_rng(0)
    # points on the rays of a seen view, well in front of the surface: free
    T = poses[3]
    d = DepthRenderer(room_scene()).render(K, W, H, T)
    v, u = rng.integers(0, H, 300), rng.integers(0, W, 300)
    z = d[v, u] * rng.uniform(0.2, 0.8, 300)
    ok = np.isfinite(z) & (d[v, u] * 0.2 > 0.3) & (d[v, u] - z > 0.2)
    p_C = np.column_stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])[ok]
    p_W = p_C @ T[:3, :3].T + T[:3, 3]
    assert np.mean(state(f, p_W) == FREE) > 0.99
    # outside the room (behind walls) and inside the box: never observed -> unknown
    outside = rng.uniform([-3, -3, -3], [-0.5, 8, 6], (300, 3))
    in_box = rng.uniform([3.6 + 0.4, 2.75 + 0.4, 0.4], [4.6 - 0.4, 3.75 - 0.4, 0.6], (100, 3))
    assert (state(f, outside) == UNKNOWN).all() and (state(f, in_box) == UNKNOWN).all()
    # just behind a seen wall surface (within tau/2): occupied
    wall_pts = np.column_stack([np.full(50, 6.0 + 0.02), rng.uniform(1.5, 3.5, 50), rng.uniform(0.5, 2.5, 50)])
    st = state(f, wall_pts)
    assert np.mean(st[st != UNKNOWN] == OCCUPIED) > 0.95 and np.mean(st != UNKNOWN) > 0.5


def test_gradient_matches_finite_differences(room_map):
    store, _, _, cfg = room_map
    f = BlockField.of(store)
    rng = np.random.default_rng(2)
    vs = cfg.voxel_size_m
    # points near the x = 6 m wall, kept away from cell faces so that central differences stay in one cell
    cell = np.floor(np.column_stack([rng.uniform(5.9, 6.05, 400), rng.uniform(1, 4, 400), rng.uniform(0.5, 2.5, 400)]) / vs - 0.5)
    p = (cell + 0.5 + rng.uniform(0.2, 0.8, cell.shape)) * vs
    L, g, valid = interpolate(f, p)
    assert valid.sum() > 100
    h = 1e-5
    for axis in range(3):
        e = np.zeros(3)
        e[axis] = h
        Lp, _, _ = interpolate(f, p + e, with_gradient=False)
        Lm, _, _ = interpolate(f, p - e, with_gradient=False)
        fd = (Lp - Lm) / (2 * h)
        assert np.allclose(fd[valid], g[valid, axis], rtol=1e-4, atol=1e-3)
    # at voxel centres the interpolation returns the voxel values
    ijk = np.floor(p[valid] / vs).astype(np.int64)
    Lc, _, vc = interpolate(f, (ijk + 0.5) * vs, with_gradient=False)
    Lv, _ = f.voxels(ijk)
    assert np.allclose(Lc[vc], Lv[vc], atol=1e-5)
    # the compact near-surface export answers the same near surfaces
    Ln, gn, vn = interpolate(near_surface_field(store), p)
    both = valid & vn
    assert both.sum() > 0.9 * valid.sum()
    assert np.allclose(Ln[both], L[both]) and np.allclose(gn[both], g[both])


def test_linear_field_is_reproduced_exactly():
    store = BlockStore(0.1, 4)
    slots = store.insert(pack_keys(np.array([[0, 0, 0], [1, 0, 0]])))
    store.refine(slots)
    a, b = np.array([0.7, -1.3, 2.1]), 0.4
    for s in slots:
        bijk = store.block_coords([s])[0]
        idx = np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), -1)
        centres = (bijk * 4 + idx + 0.5) * 0.1
        store.Lv[store.vox_slot[s]] = centres @ a + b
        store.wv[store.vox_slot[s]] = 1
    p = np.random.default_rng(3).uniform([0.06, 0.06, 0.06], [0.74, 0.34, 0.34], (200, 3))
    L, g, v = interpolate(BlockField.of(store), p)
    assert v.all() and np.allclose(L, p @ a + b, atol=1e-5) and np.allclose(g, a[None], atol=1e-4)
    _, _, v_out = interpolate(BlockField.of(store), np.array([[0.9, 0.1, 0.1]]))
    assert not v_out[0]
    # points with negative coordinates, and points beyond the range blocks can be packed in, are unknown, not errors
    far = np.array([[-0.05, 0.1, 0.1], [1e6, 0.0, 0.0], [0.0, -1e6, 0.0]])
    L, g, v = interpolate(BlockField.of(store), far)
    assert not v.any() and np.isnan(L).all() and np.isnan(g).all()
    Lf, wf = BlockField.of(store).voxels(np.array([[2**24, 0, 0], [-1, 0, 0], [0, 0, 0]]))
    assert wf.tolist() == [0, 0, 1] and Lf[2] == pytest.approx(store.Lv[store.vox_slot[slots[0]], 0, 0, 0])


def test_bad_input():
    cfg = SensorModelConfig()
    with pytest.raises(ValueError):
        prepare_depth(np.ones((4, 5), np.float32), np.ones((5, 4), np.float32), cfg)
    store, res = integrate_once(np.full((H, W), np.nan, np.float32), np.full((H, W), 0.02, np.float32))
    assert store.n_blocks == 0 and res.n_pixels == 0
    # NaN sigma with valid depth: pixel unusable; negative and huge depths are ignored
    d = np.full((H, W), 2.0, np.float32)
    d[:10] = -1.0
    d[10:20] = 1e6
    s = np.full((H, W), 0.02, np.float32)
    s[20:30] = np.nan
    _, _, n = prepare_depth(d, s, cfg)
    assert n == (H - 30) * W


def test_coarsening_free_blocks_keeps_mesh_and_states(room_map):
    from services.mapping.mesh import ChunkMesher

    store, _, _, cfg = room_map
    copy = BlockStore.from_arrays(store.arrays())
    n = copy.coarsen_free(0.7 * cfg.l_min)
    assert n > 100 and copy.nbytes() < 0.8 * store.nbytes()
    meshes = []
    for s in (store, copy):
        mesher = ChunkMesher(4)
        mesher.mark(s, np.arange(s.n_blocks))
        mesher.update(s)
        meshes.append(mesher.mesh())
    assert np.array_equal(meshes[0][1], meshes[1][1]) and np.allclose(meshes[0][0], meshes[1][0])
    p = np.random.default_rng(5).uniform([0, 0, 0], [6, 5, 3], (20000, 3))
    assert np.array_equal(state(BlockField.of(store), p), state(BlockField.of(copy), p))


@pytest.mark.service
def test_warm_up_loads_the_query_kernels_a_fresh_process_needs():
    """shared.occupancy.query.warm_up leaves both compiled kernels ready in a fresh process (the back end calls it
    before its first heartbeat, so its first occupancy-to-point terms do not stall it for ~0.3 s)."""
    import subprocess
    import sys

    code = ("from shared.occupancy import query as q\n"
            "before = (len(q._trilinear.signatures), len(q._voxels.signatures))\n"
            "q.warm_up()\n"
            "print(before, (len(q._trilinear.signatures), len(q._voxels.signatures)))\n")
    from pathlib import Path

    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True,
                         cwd=Path(__file__).resolve().parents[1])
    assert out.stdout.split("\n")[0] == "(0, 0) (1, 1)", out.stdout + out.stderr


def test_pixels_too_uncertain_for_a_surface_only_free_the_space_in_front():
    """A depth frame's pixels whose sigma exceeds k x depth (DepthFrame.surface_max_relative_sigma) place no surface:
    they free the ray up to depth - 3 sigma, so a phantom surface that a bad frame put in front of them is carved,
    and the voxels around their own depth stay as they were."""
    from shared.occupancy.uncertain_pixels import carve_only_pixels

    cfg = SensorModelConfig()
    ijk = np.column_stack([np.zeros(160, int), np.zeros(160, int), np.arange(160)])  # the optical axis, 0-4 m
    z = (ijk[:, 2] + 0.5) * cfg.voxel_size_m
    far_d, far_s = wall(3.0, 0.2)  # relative sigma 0.067
    carve = carve_only_pixels(far_d, far_s, 0.05)
    assert carve.all() and carve_only_pixels(far_d, far_s, 0.0) is None and carve_only_pixels(far_d, far_s, 0.1).sum() == 0
    nan_d = far_d.copy()
    nan_d[:10] = np.nan
    assert not carve_only_pixels(nan_d, far_s, 0.05)[:10].any()  # NaN depth: no pixel at all

    phantom_d, phantom_s = wall(1.5, 0.03)
    stores = {}
    for name, mask in (("surface", None), ("carve", carve)):
        store, _ = integrate_once(phantom_d, phantom_s, cfg=cfg)
        L0, _ = BlockField.of(store).voxels(ijk)
        assert L0[np.abs(z - 1.5) < 0.02].max() > 0  # the phantom is a surface
        d, s, _ = prepare_depth(far_d, far_s, cfg)
        for _ in range(5):
            res = integrate(store, d, s, K, np.eye(4), cfg, mask)
        assert res.n_carve_only == (res.n_pixels if mask is not None else 0)
        stores[name] = BlockField.of(store).voxels(ijk)
    L_s, w_s = stores["surface"]
    L_c, w_c = stores["carve"]
    phantom = np.abs(z - 1.5) < 0.02
    assert (L_c[phantom] < 0).all() and (L_s[phantom] < 0).all()  # carved either way: 2.4 m < 3 m - 3 sigma
    at_wall = np.abs(z - 3.0) < 0.05
    assert (L_s[at_wall] > 0).any()  # as a surface, the uncertain wall is drawn
    assert (w_c[at_wall] == 0).all()  # carve only: nothing there was touched
    free_end = z < 3.0 - 3 * 0.2 - 0.05
    assert (L_c[free_end & (z > 0.2) & (np.abs(z - 1.5) > 0.1)] < cfg.l_min * 0.9).all()  # free in front (not the phantom's band)
    unsure = (z > 3.0 - 3 * 0.2 + 0.05) & (z < 3.0)
    assert (w_c[unsure] == 0).all()  # the ramp within 3 sigma of the depth is not applied
