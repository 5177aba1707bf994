"""Occupancy-to-point factor (eq. 6-7): residual and Jacobians against finite differences, a perturbed pose
pulled back onto a mapped surface by the factor alone, points outside the observed field dropping out."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X

from services.backend.o2p.factor import OccupancyToPoint, trilinear_derivatives
from shared.occupancy.blocks import BlockStore
from shared.occupancy.query import BlockField, interpolate, near_surface_field
from shared.geometry import inv_T, make_T, so3_exp
from tests.o2p_room import H, K, W, mapped_room, view

SIGMA = 0.02


@pytest.fixture(scope="module")
def room():
    """Occupancy of a box room with a box inside, integrated from ray-cast depth (map frame = world)."""
    store, renderer, cfg = mapped_room(SIGMA)
    return near_surface_field(store), renderer, cfg


def frame_points(renderer, T_WC, step=6, rng=None):
    """Back-projected depth pixels of one view (camera frame) on a pixel grid."""
    d = renderer.render(K, W, H, T_WC)
    v, u = np.mgrid[3:H:step, 3:W:step]
    z = d[v, u]
    ok = np.isfinite(z)
    u, v, z = u[ok], v[ok], z[ok]
    return np.column_stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])


def perturb(T, rot_rad, trans_m, seed):
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    direction = rng.normal(size=3)
    dT = make_T(so3_exp(axis / np.linalg.norm(axis) * rot_rad), direction / np.linalg.norm(direction) * trans_m)
    return T @ dT


def test_trilinear_derivatives_match_interpolate_and_differences(room):
    field = room[0]
    rng = np.random.default_rng(0)
    vs = field.voxel_size
    cell = np.floor(np.column_stack([rng.uniform(5.9, 6.05, 300), rng.uniform(1, 4, 300), rng.uniform(0.5, 2.5, 300)]) / vs - 0.5)
    q = (cell + 0.5 + rng.uniform(0.2, 0.8, cell.shape)) * vs
    L, g, mixed, valid = trilinear_derivatives(field, q)
    L0, g0, v0 = interpolate(field, q)
    assert valid.sum() > 100 and np.array_equal(valid, v0)
    assert np.allclose(L[valid], L0[valid]) and np.allclose(g[valid], g0[valid])
    h = 1e-5
    for i, j, k in ((0, 1, 0), (0, 2, 1), (1, 2, 2)):  # d(g_i)/dx_j = mixed[k]
        e = np.zeros(3)
        e[j] = h
        gp = trilinear_derivatives(field, q + e)[1][:, i]
        gm = trilinear_derivatives(field, q - e)[1][:, i]
        assert np.allclose((gp - gm) / (2 * h), mixed[:, k], rtol=1e-4, atol=1e-2)


def test_residual_and_jacobians_match_finite_differences(room):
    field, renderer, cfg = room
    T_WB = make_T(so3_exp(np.array([0.02, -0.01, 0.03])), np.array([0.01, -0.02, 0.0]))
    T_BM = inv_T(T_WB)  # the map stays where it was integrated
    T_WC = view(0.7)
    T_SC = make_T(so3_exp(np.array([0.1, -0.2, 0.05])), np.array([0.05, 0.01, -0.02]))
    T_WA = perturb(T_WC @ inv_T(T_SC), 0.01, 0.01, 3)
    p_C = frame_points(renderer, T_WC)
    p_A = p_C @ T_SC[:3, :3].T + T_SC[:3, 3]
    sig = np.random.default_rng(1).uniform(0.01, 0.1, len(p_A))
    f = OccupancyToPoint(field, cfg.l_min, p_A, sig, key_a=X(0), key_b=X(1), T_BM=T_BM)
    ev = f.evaluate(T_WA, T_WB)
    assert ev.valid.sum() > 100
    # eq. 6-7 directly: (L / |g|) / sqrt(sigma_map^2 + sigma_d^2), sigma_map = |l_min| / (3 |g|)
    q = (inv_T(T_WB @ T_BM) @ T_WA @ np.c_[p_A, np.ones(len(p_A))].T).T[:, :3]
    L, g, _ = interpolate(field, q)
    gn = np.linalg.norm(g, axis=1)
    expect = (L / gn) / np.sqrt((cfg.l_min / (3 * gn)) ** 2 + sig**2)
    assert np.allclose(ev.r[ev.valid], expect[ev.valid])
    h = 1e-6
    for which, J in (("a", ev.J_a), ("b", ev.J_b)):
        fd = np.zeros_like(J)
        for k in range(6):
            xi = np.zeros(6)
            xi[k] = h
            Tp = gtsam.Pose3.Expmap(xi).matrix()
            Tm = gtsam.Pose3.Expmap(-xi).matrix()
            if which == "a":
                rp, rm = f.evaluate(T_WA @ Tp, T_WB), f.evaluate(T_WA @ Tm, T_WB)
            else:
                rp, rm = f.evaluate(T_WA, T_WB @ Tp), f.evaluate(T_WA, T_WB @ Tm)
            fd[:, k] = (rp.r - rm.r) / (2 * h)
        # rows whose point crosses an interpolation cell face within +-h have a kink: compare the rest
        rel = np.linalg.norm(fd - J, axis=1) / (np.linalg.norm(J, axis=1) + 1e-3)
        assert np.median(rel[ev.valid]) < 1e-4 and np.mean(rel[ev.valid] < 1e-3) > 0.97, which
    # the gtsam factor returns the same rows and Jacobians (Tukey reweighting aside: whitened at small error)
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(T_WA))
    values.insert(X(1), gtsam.Pose3(T_WB))
    lin = f.factor(ev.valid.sum()).linearize(values)
    A, b = lin.jacobian()
    w = np.sqrt(gtsam.noiseModel.mEstimator.Tukey.Create(3.0 * np.sqrt(ev.valid.sum())).weight(np.linalg.norm(ev.r)))
    assert np.allclose(-b, w * ev.r) and np.allclose(A, w * np.hstack([ev.J_a, ev.J_b]))


def test_effective_points_cap_scales_rows_and_keeps_jacobians_exact(room):
    """N_eff caps a factor at the information of N_eff independent points: rows scaled by sqrt(N_eff / n),
    the Jacobians of the gtsam factor still match central differences of its error."""
    field, renderer, cfg = room
    T_WA = perturb(view(1.3), 0.01, 0.01, 5)
    p_A = frame_points(renderer, view(1.3), step=5)
    sig = np.random.default_rng(2).uniform(0.01, 0.05, len(p_A))
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(T_WA))
    full = OccupancyToPoint(field, cfg.l_min, p_A, sig, key_a=X(0), T_WB=np.eye(4))
    capped = OccupancyToPoint(field, cfg.l_min, p_A, sig, key_a=X(0), T_WB=np.eye(4), effective_points=20)
    n = full.n_valid(values)
    assert n > 100
    A0, b0 = full.factor(n).linearize(values).jacobian()
    fac = capped.factor(n)
    A1, b1 = fac.linearize(values).jacobian()
    s = np.sqrt(20 / n)
    assert np.allclose(A1, s * A0) and np.allclose(b1, s * b0)  # same Tukey weight: threshold scales with s
    assert np.isclose(np.trace(A1.T @ A1) / np.trace(A0.T @ A0), 20 / n)
    # Jacobian of the capped factor's rows vs central differences of its error (before Tukey); after
    # factor() the evaluation carries the cap
    ev = capped.evaluate(T_WA, np.eye(4))
    assert np.allclose(ev.r, s * full.evaluate(T_WA, np.eye(4)).r)
    h = 1e-6
    fd = np.zeros((len(p_A), 6))
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = h
        rs = []
        for sgn in (1, -1):
            v = gtsam.Values()
            v.insert(X(0), gtsam.Pose3(T_WA @ gtsam.Pose3.Expmap(sgn * xi).matrix()))
            rs.append(fac.unwhitenedError(v))
        fd[:, k] = (rs[0] - rs[1]) / (2 * h)
    rel = np.linalg.norm(fd - ev.J_a, axis=1) / (np.linalg.norm(ev.J_a, axis=1) + 1e-3)
    assert np.median(rel[ev.valid]) < 1e-4 and np.mean(rel[ev.valid] < 1e-3) > 0.97
    # a cap above the point count changes nothing
    assert np.allclose(OccupancyToPoint(field, cfg.l_min, p_A, sig, key_a=X(0), T_WB=np.eye(4),
                                        effective_points=10 * n).factor(n).linearize(values).jacobian()[0], A0)
    with pytest.raises(ValueError):
        OccupancyToPoint(field, cfg.l_min, p_A, sig, key_a=X(0), T_WB=np.eye(4), effective_points=-1)


def solve(graph, values):
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(50)
    return gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()


def pose_err(T, T_true):
    dT = inv_T(T_true) @ T
    return np.degrees(np.linalg.norm(gtsam.Rot3(dT[:3, :3]).ypr())), np.linalg.norm(dT[:3, 3])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_perturbed_frame_is_pulled_back_to_the_surface(room, seed):
    field, renderer, cfg = room
    T_WC = view(0.3 + 1.7 * seed)
    p_C = frame_points(renderer, T_WC, step=4)
    sig = np.full(len(p_C), 0.02)
    # 200 lowest-sigma points of the frame (all equal here: a random subset)
    pick = np.random.default_rng(seed).choice(len(p_C), 200, replace=False)
    start = perturb(T_WC, np.radians(2.0), 0.04, seed)
    f = OccupancyToPoint(field, cfg.l_min, p_C[pick], sig[pick], key_a=X(0), T_WB=np.eye(4))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(f.factor(f.evaluate(start, np.eye(4)).valid.sum()))
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(start))
    est = solve(graph, values).atPose3(X(0)).matrix()
    rot0, tr0 = pose_err(start, T_WC)
    rot, tr = pose_err(est, T_WC)
    print(f"seed {seed}: start {rot0:.2f} deg {100 * tr0:.1f} cm -> {rot:.3f} deg {100 * tr:.2f} cm")
    assert rot < 0.3 and tr < 0.008


def test_moving_the_map_instead_of_the_frame(room):
    """The target pose is the variable: the map is moved back under a fixed frame (map-to-map geometry)."""
    field, renderer, cfg = room
    T_WA = view(2.2)
    p_A = frame_points(renderer, T_WA, step=4)
    start = perturb(np.eye(4), np.radians(1.5), 0.03, 7)
    f = OccupancyToPoint(field, cfg.l_min, p_A, np.full(len(p_A), 0.03), T_WA=T_WA, key_b=X(5))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(f.factor(f.evaluate(T_WA, start).valid.sum()))
    values = gtsam.Values()
    values.insert(X(5), gtsam.Pose3(start))
    est = solve(graph, values).atPose3(X(5)).matrix()
    rot, tr = pose_err(est, np.eye(4))
    assert rot < 0.3 and tr < 0.008


def test_points_outside_the_field_drop_out(room):
    field, renderer, cfg = room
    T_WC = view(1.0)
    p_in = frame_points(renderer, T_WC)
    rng = np.random.default_rng(4)
    T = perturb(T_WC, 0.01, 0.01, 1)
    # world points outside the room (never observed), expressed in the frame of the points
    p_out_W = np.vstack([rng.uniform([-3, -3, -3], [-0.5, 8, 6], (150, 3)), rng.uniform([0, 0, 3.6], [6, 5, 6], (50, 3))])
    p_out = (inv_T(T) @ np.c_[p_out_W, np.ones(len(p_out_W))].T).T[:, :3]
    f_in = OccupancyToPoint(field, cfg.l_min, p_in, 0.02, key_a=X(0), T_WB=np.eye(4))
    f_all = OccupancyToPoint(field, cfg.l_min, np.vstack([p_in, p_out]), 0.02, key_a=X(0), T_WB=np.eye(4))
    e_in, e_all = f_in.evaluate(T, np.eye(4)), f_all.evaluate(T, np.eye(4))
    n = len(p_in)
    assert not e_all.valid[n:].any()
    assert (e_all.r[n:] == 0).all() and (e_all.J_a[n:] == 0).all() and (e_all.J_b[n:] == 0).all()
    assert np.array_equal(e_all.r[:n], e_in.r) and np.array_equal(e_all.J_a[:n], e_in.J_a)
    # an empty field: every point drops out, the factor is zero (no NaN, no crash)
    empty = near_surface_field(BlockStore(cfg.voxel_size_m))
    f0 = OccupancyToPoint(empty, cfg.l_min, p_in, 0.02, key_a=X(0), T_WB=np.eye(4))
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose3(T))
    fac = f0.factor()
    assert fac.error(v) == 0.0 and np.isfinite(fac.linearize(v).jacobian()[0]).all()


def test_bad_input_is_a_clear_error(room):
    field, _, cfg = room
    p = np.zeros((3, 3))
    with pytest.raises(ValueError):
        OccupancyToPoint(field, cfg.l_min, p, 0.02, key_a=X(0), key_b=X(0))
    with pytest.raises(ValueError):
        OccupancyToPoint(field, cfg.l_min, np.full((3, 3), np.nan), 0.02, key_a=X(0), T_WB=np.eye(4))
    with pytest.raises(ValueError):
        OccupancyToPoint(field, cfg.l_min, p, 0.02, key_a=X(0))
    with pytest.raises(ValueError):
        OccupancyToPoint(field, cfg.l_min, np.zeros((0, 3)), 0.02, key_a=X(0), T_WB=np.eye(4))
    assert isinstance(field, BlockField)
