"""Is the occupancy-to-point factor biased at the true poses?

    python -m tools.o2p_bias REPLICA [--frames N] [--stride S] [--warmup W] [--points N]

On a replica (data/replicas/*-d25-seed0), submaps are built at the ground-truth poses the way the mapping
service builds them (:class:`services.mapping.submaps.SubmapMapper`, sigma from the depth frame), in the
rectified left camera of the stereo network. For each frame after ``--warmup`` (before it is integrated, so a
frame never meets its own depth) the back end's frame-to-map points are selected
(:func:`shared.occupancy.o2p_points.select_depth_points`, the lowest-sigma pixels of the stereo frame), o(k) is
the oldest submap with >= M_min of them inside its near-surface field (covisibility by landmarks is left out),
and the factor (:class:`services.backend.o2p.factor.OccupancyToPoint`) is evaluated at the ground-truth poses.

Per variant (map depth x point depth; GT = ray-cast scene mesh at the same pixels, with the stereo network's
learned sigma so that map thickness and weights are those of the network):

- ``gt/gt``: map and points from GT depth (bias of the map model alone);
- ``stereo/stereo``: both from the stereo network (what the system sees);
- ``stereo/gt``: map from stereo, points GT (map bias from depth errors);
- ``gt/stereo``: map GT, points stereo (point depth bias).

It prints one JSON line per variant: the signed distance residual ``e = L / |grad L|`` [m] (mean, median,
std; positive = the point lies inside the occupied side, i.e. behind the surface), mean of ``e / sigma`` with
``sigma = sqrt(sigma_map^2 + sigma_d^2)`` (eq. 7), the fraction of factors whose Tukey weight is zero at the
truth, and the pose offset that the factor alone pulls a frame to (Gauss-Newton on the frame's pose, target
fixed, minimum-norm steps in directions the points leave free): the camera's translation [mm] and rotation
[mdeg], median over frames, and the mean translation vector in the camera frame [mm] (a consistent offset
along the viewing direction shows as z).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import gtsam
import numpy as np

from services.backend.o2p.factor import OccupancyToPoint
from shared.occupancy.query import BlockField, near_surface_field
from shared.geometry import inv_T, transform_points


def residuals(field: BlockField, l_min: float, p_A: np.ndarray, sigma_d: np.ndarray, T_WA: np.ndarray,
              T_WB: np.ndarray, grad_min: float = 1.0) -> dict:
    """Per-point signed distance ``e = L / |grad L|`` [m], ``e / sigma`` and the validity mask of the
    factor's points at the given poses (the factor's own evaluation)."""
    f = OccupancyToPoint(field, l_min, p_A, sigma_d, T_WA=T_WA, T_WB=T_WB, grad_min=grad_min)
    ev = f.evaluate(T_WA, T_WB)
    # r = 3 L / sqrt(l_min^2 + 9 g^2 s^2) = e / sigma with e = L / g and sigma^2 = (l_min / 3 g)^2 + s^2
    from services.backend.o2p.factor import trilinear_derivatives

    q = transform_points(inv_T(T_WB) @ T_WA, p_A)  # the points in the target's frame
    L, g, _, _ = trilinear_derivatives(field, q)
    gn = np.linalg.norm(g, axis=1)
    v = ev.valid
    e = np.where(v, L / np.where(v, gn, 1.0), np.nan)
    return {"e": e, "z": np.where(v, ev.r, np.nan), "valid": v}


def factor_offset(field: BlockField, l_min: float, p_A: np.ndarray, sigma_d: np.ndarray, T_WA: np.ndarray,
                  T_WB: np.ndarray, iterations: int = 5, grad_min: float = 1.0, tukey_k: float = 3.0) -> dict:
    """Where the factor alone pulls pose A from ``T_WA`` (target held fixed): Gauss-Newton with minimum-norm
    steps (directions the points leave free do not move). Returns ``T_WA_hat``, the body-frame step
    ``xi`` = [omega, v] of ``T_WA^-1 T_WA_hat``, and whether the factor's Tukey weight at ``T_WA`` is zero."""
    f = OccupancyToPoint(field, l_min, p_A, sigma_d, T_WA=T_WA, T_WB=T_WB, grad_min=grad_min, tukey_k=tukey_k)
    ev = f.evaluate(T_WA, T_WB)
    n0 = int(ev.valid.sum())
    off = bool(np.linalg.norm(ev.r) > tukey_k * np.sqrt(max(1, n0)))
    T = np.asarray(T_WA, float).copy()
    for _ in range(iterations):
        ev = f.evaluate(T, T_WB)
        J = ev.J_a[ev.valid]
        if len(J) < 6:
            break
        # minimum-norm least squares, relative cutoff so unconstrained directions (e.g. along a plane) stay put
        step = np.linalg.lstsq(J, -ev.r[ev.valid], rcond=1e-6)[0]
        T = T @ gtsam.Pose3.Expmap(step).matrix()
        if np.linalg.norm(step) < 1e-9:
            break
    xi = gtsam.Pose3.Logmap(gtsam.Pose3(inv_T(np.asarray(T_WA, float)) @ T))
    return {"T_WA_hat": T, "xi": np.asarray(xi), "n_valid": n0, "tukey_off": off}


def summarize(name: str, rows: list[dict], offsets: list[dict], T_SC: np.ndarray) -> dict:
    """One JSON-ready summary of a variant: residual statistics over all points, pose offsets over frames
    (camera translation [mm] and rotation [mdeg]; the mean translation vector in the camera frame)."""
    e = np.concatenate([r["e"][r["valid"]] for r in rows]) if rows else np.empty(0)
    z = np.concatenate([r["z"][r["valid"]] for r in rows]) if rows else np.empty(0)
    t_mm, r_mdeg, t_C = [], [], []
    for o in offsets:
        d = inv_T(T_SC) @ gtsam.Pose3.Expmap(o["xi"]).matrix() @ T_SC  # camera motion T_C C'
        t_C.append(d[:3, 3] * 1e3)
        t_mm.append(np.linalg.norm(d[:3, 3]) * 1e3)
        r_mdeg.append(np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(d[:3, :3])))) * 1e3)
    t_C = np.array(t_C).reshape(-1, 3)
    rnd = lambda x, k=4: None if x is None or not np.isfinite(x) else round(float(x), k)  # noqa: E731
    return {"variant": name, "frames": len(offsets), "points": int(len(e)),
            "e_mean_m": rnd(np.mean(e) if len(e) else np.nan), "e_median_m": rnd(np.median(e) if len(e) else np.nan),
            "e_std_m": rnd(np.std(e) if len(e) else np.nan), "z_mean": rnd(np.mean(z) if len(z) else np.nan, 3),
            "tukey_off_frac": rnd(np.mean([o["tukey_off"] for o in offsets]) if offsets else np.nan, 3),
            "offset_t_mm_median": rnd(np.median(t_mm) if t_mm else np.nan, 2),
            "offset_r_mdeg_median": rnd(np.median(r_mdeg) if r_mdeg else np.nan, 1),
            "offset_t_cam_mean_mm": [rnd(x, 2) for x in t_C.mean(axis=0)] if len(t_C) else None}


def oldest_target(fields: list[tuple[BlockField, np.ndarray]], p_A: np.ndarray, T_WA: np.ndarray, l_min: float,
                  min_points: int) -> int:
    """Index of the oldest field with >= ``min_points`` of the points inside it (o(k) without covisibility)."""
    from services.backend.o2p.factor import trilinear_derivatives

    for i, (field, T_WM) in enumerate(fields):
        q = transform_points(inv_T(T_WM) @ T_WA, p_A)
        if int(trilinear_derivatives(field, q)[3].sum()) >= min_points:
            return i
    return -1


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("replica")
    p.add_argument("--frames", type=int, default=100, help="camera frames used (after --skip, every --stride-th)")
    p.add_argument("--stride", type=int, default=4, help="every n-th camera frame (4: depth at 5 Hz, as the ablation)")
    p.add_argument("--skip", type=int, default=0, help="camera frames skipped at the start")
    p.add_argument("--warmup", type=int, default=10, help="frames only integrated before the first evaluation")
    p.add_argument("--points", type=int, default=200, help="points per frame-to-map factor (o2p.max_points_frame)")
    p.add_argument("--dump", default="", metavar="NPZ", help="also save per-frame residuals, sigmas and Jacobians at the truth")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="system config override (e.g. mapping.sensor.tau_k=0.1)")
    a = p.parse_args(argv)

    from services.depth.pipeline import DepthPipeline
    from shared.occupancy.o2p_points import SubmapPointPool, select_depth_points
    from services.mapping.submaps import SubmapMapper
    from services.app.system_config import load_system_config
    from shared.config import override
    from shared.rig import load_rig_config
    from tools.depth.evaluate import _replica_frames

    cfg = load_system_config(None, a.set)
    cfg = override(cfg, {"rig.calibration": a.replica})
    by_name = {c.name: c for c in load_rig_config(cfg.rig)}
    pipe = DepthPipeline(cfg.depth, by_name[cfg.depth.left_camera], by_name[cfg.depth.right_camera])
    K, T_SC = pipe.K, pipe.T_SC
    sensor, o2p = cfg.mapping.sensor, cfg.o2p
    mappers = {m: SubmapMapper(sensor, cfg.mapping.submaps) for m in ("gt", "stereo")}
    variants = [("gt", "gt"), ("stereo", "stereo"), ("stereo", "gt"), ("gt", "stereo")]
    rows: dict[str, list] = {f"{m}/{q}": [] for m, q in variants}
    offsets: dict[str, list] = {f"{m}/{q}": [] for m, q in variants}
    cache: dict[tuple[str, int], tuple[int, BlockField]] = {}
    # map-to-map: each submap's pooled points (as the mapping service pools them) against the oldest other
    # submap holding >= M_min of them, at the ground-truth submap poses, when the submap closes
    pools = {m: SubmapPointPool(o2p.max_points_map) for m in ("gt", "stereo")}
    m2m_rows: dict[str, list] = {"m2m gt": [], "m2m stereo": []}
    m2m_offsets: dict[str, list] = {"m2m gt": [], "m2m stereo": []}

    def map_to_map(m: str, sm) -> None:
        got = pools[m].pop(sm.id)
        if got is None:
            return
        pts, sg = got
        fields = [(near_surface_field(o.store), o.T_WM) for o in mappers[m].submaps if o.id < sm.id]
        i = oldest_target(fields, pts, sm.T_WM, sensor.l_min, o2p.min_points_in_field)
        if i < 0:
            return
        field, T_WM = fields[i]
        m2m_rows[f"m2m {m}"].append(residuals(field, sensor.l_min, pts, sg, sm.T_WM, T_WM, o2p.grad_min))
        m2m_offsets[f"m2m {m}"].append(factor_offset(field, sensor.l_min, pts, sg, sm.T_WM, T_WM,
                                                     grad_min=o2p.grad_min, tukey_k=o2p.tukey_k))
    for k, (left, right, gt, T_WC, _, stamp) in enumerate(_replica_frames(Path(a.replica), a.frames, a.stride, a.skip,
                                                                          pipe.rect, 0, np.random.default_rng(0))):
        d, s = pipe.stereo(left, right)
        T_WS = T_WC @ inv_T(T_SC)
        if k >= a.warmup:
            p_C, sig = select_depth_points(d, s, K, a.points)
            u = np.rint(p_C[:, 0] / p_C[:, 2] * K[0, 0] + K[0, 2]).astype(int)
            v = np.rint(p_C[:, 1] / p_C[:, 2] * K[1, 1] + K[1, 2]).astype(int)
            z_gt = gt[v, u].astype(np.float64)
            ok = np.isfinite(z_gt)
            pts = {"stereo": p_C[ok], "gt": p_C[ok] * (z_gt[ok] / p_C[ok, 2])[:, None]}
            sig = sig[ok]
            for m, q in variants:
                fields = []
                for sm in mappers[m].submaps:  # near-surface fields, as the mapping service exports them
                    key = (m, sm.id)
                    if key not in cache or cache[key][0] != sm.n_frames:
                        cache[key] = (sm.n_frames, near_surface_field(sm.store))
                    fields.append((cache[key][1], sm.T_WM))
                p_S = pts[q] @ T_SC[:3, :3].T + T_SC[:3, 3]
                i = oldest_target(fields, p_S, T_WS, sensor.l_min, o2p.min_points_in_field)
                if i < 0:
                    continue
                field, T_WM = fields[i]
                rows[f"{m}/{q}"].append(residuals(field, sensor.l_min, p_S, sig, T_WS, T_WM, o2p.grad_min))
                if a.dump:
                    ev = OccupancyToPoint(field, sensor.l_min, p_S, sig, T_WA=T_WS, T_WB=T_WM).evaluate(T_WS, T_WM)
                    rows[f"{m}/{q}"][-1].update(sigma_d=sig, r=ev.r, J_a=ev.J_a, frame=k, submap=i)
                offsets[f"{m}/{q}"].append(factor_offset(field, sensor.l_min, p_S, sig, T_WS, T_WM,
                                                         grad_min=o2p.grad_min, tukey_k=o2p.tukey_k))
        for m, depth in (("gt", gt), ("stereo", d)):
            rep = mappers[m].integrate(depth, s, K, T_WC, T_SC, stamp)
            if rep.new_submap and rep.submap_id > 0:
                map_to_map(m, mappers[m].submaps[rep.submap_id - 1])
            cur = mappers[m].current
            pools[m].add(cur.id, depth, s, K, inv_T(cur.T_WM) @ T_WC)
    if a.dump:
        np.savez_compressed(a.dump, T_SC=T_SC, **{f"{n}|{j}|{key}": val for n, rs in rows.items() for j, r in enumerate(rs)
                                                  for key, val in r.items()})
    for m, q in variants:
        name = f"{m}/{q}"
        out = summarize(name, rows[name], offsets[name], T_SC)
        out["replica"] = Path(a.replica).name
        out["submaps"] = len(mappers[m].submaps)
        print(json.dumps(out), flush=True)
    for name in m2m_rows:  # offsets of the submap m's anchor (body frame M), reported in the camera axes too
        out = summarize(name, m2m_rows[name], m2m_offsets[name], T_SC)
        out["replica"] = Path(a.replica).name
        print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
