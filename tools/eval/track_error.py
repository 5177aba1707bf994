"""How far the frontend's tracks are from where the ground truth puts them, on a replica with depth.

    python -m tools.eval.track_error REPLICA [--first F] [--frames N] [--shift-ms S] [--set frontend.K=V] [--json OUT]

Runs the frontend's tracker (services/frontend/tracker.py, the configured `frontend` settings) over the replica's
frames, with the ground truth's rotation between frames as the gyro prior. Every camera-0 track is lifted into the
world at its first pixel with the replica's true depth (mav0/depth0) and pose, and projected into each later frame
with that frame's true pose: the distance to the tracked pixel is the track's error there. A feature born on a depth
edge (its 3x3 depth neighbourhood spans more than 2 %) is left out, since its depth is not defined.

``--shift-ms`` looks the true poses up that much later than the frame stamps: a replica rendered with a camera-IMU
clock offset (the ``hard`` profile's 1 ms) shows its images at the stamp plus the offset.

Prints the median / p90 error over all observations, per track age and at keyframes only (the frames the
estimator's window takes); ``--json`` writes them. The errors are in
(distorted) pixels; a drift that grows with age points to frame-to-frame accumulation, a floor at age 1 to the
matching itself.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

AGE_BINS = ((1, 2), (3, 5), (6, 10), (11, 20), (21, 40), (41, 80), (81, 10**9))


def pose_lookup(stamps_ns: np.ndarray, p_WS: np.ndarray, q_WS_wxyz: np.ndarray):
    """T_WS(t) for int64 t [ns]: linear position, spherical rotation between the two nearest samples."""
    from scipy.spatial.transform import Rotation, Slerp

    rot = Rotation.from_quat(np.asarray(q_WS_wxyz, float)[:, [1, 2, 3, 0]])  # scipy wants x, y, z, w
    t_s = (np.asarray(stamps_ns, np.int64) - int(stamps_ns[0])) * 1e-9
    slerp = Slerp(t_s, rot)

    def T_WS(t_ns: int) -> np.ndarray:
        t = (int(t_ns) - int(stamps_ns[0])) * 1e-9
        if not t_s[0] <= t <= t_s[-1]:
            raise ValueError(f"{t_ns}: outside the ground truth's span")
        T = np.eye(4)
        T[:3, :3] = slerp([t]).as_matrix()[0]
        T[:3, 3] = [np.interp(t, t_s, p_WS[:, k]) for k in range(3)]
        return T

    return T_WS


def depth_at(depth: np.ndarray, uv: np.ndarray, max_spread: float = 0.02) -> np.ndarray:
    """Depth [m] at the nearest pixel of each uv (N,2); NaN where it is missing or the 3x3 neighbourhood spans more
    than ``max_spread`` of it (a depth edge)."""
    h, w = depth.shape
    out = np.full(len(uv), np.nan)
    for k, (u, v) in enumerate(np.rint(np.asarray(uv, float)).astype(int)):
        if 1 <= u < w - 1 and 1 <= v < h - 1:
            patch = depth[v - 1:v + 2, u - 1:u + 2]
            if np.all(patch > 0) and np.all(np.isfinite(patch)) and np.ptp(patch) <= max_spread * patch[1, 1]:
                out[k] = patch[1, 1]
    return out


def _stats(e: np.ndarray) -> dict:
    return {"n": int(len(e)), "median_px": float(np.median(e)) if len(e) else float("nan"),
            "p90_px": float(np.percentile(e, 90)) if len(e) else float("nan")}


def summarise(errors_px: np.ndarray, ages: np.ndarray) -> dict:
    """Median, p90 and count over all observations and per age bin (frames since the track's first pixel)."""
    out = {"all": _stats(errors_px)}
    for lo, hi in AGE_BINS:
        sel = (ages >= lo) & (ages <= hi)
        out[f"{lo}-{hi}" if hi < 10**9 else f">={lo}"] = _stats(errors_px[sel])
    return out


def measure(replica: str | Path, first: int = 0, frames: int = 0, shift_ms: float = 0.0,
            overrides: list[str] | None = None) -> dict:
    """Run the tracker over the replica; per observation its error [px] and age [frames], summarised."""
    from services.frontend.tracker import MultiCameraTracker
    from services.app.system_config import load_system_config
    from shared.camera import load_rig
    from services.app.synth.depth_io import DepthFolder
    from shared.euroc import read_euroc_csv
    from shared.euroc_reader import EurocDataset
    from shared.geometry import inv_T, transform_points

    root = Path(replica)
    cfg = load_system_config(None, list(overrides or []))
    ds = EurocDataset(root)
    if ds.groundtruth_path is None:
        raise ValueError(f"{root}: no ground truth (mav0/state_groundtruth_estimate0/data.csv)")
    depth = DepthFolder(root / "mav0" / "depth0")
    cams = load_rig(root)
    gt = read_euroc_csv(ds.groundtruth_path)
    T_WS = pose_lookup(gt.stamps_ns, gt.p_WS, gt.q_WS_wxyz)
    shift_ns = int(round(shift_ms * 1e6))
    stamps = ds.frame_stamps_ns[first:first + frames if frames else None]
    stamps = stamps[(stamps + shift_ns > gt.stamps_ns[0]) & (stamps + shift_ns < gt.stamps_ns[-1])]
    if len(stamps) < 2:
        raise ValueError(f"{root}: fewer than two frames inside the ground truth from frame {first}")
    tracker = MultiCameraTracker(cfg.frontend, cams)
    cam0 = cams[0]
    birth: dict[int, tuple[int, np.ndarray] | None] = {}  # landmark id -> (frame index, point in W)
    depth_stamps = set(depth.stamps_ns.tolist())
    errors, ages, at_kf = [], [], []
    T_prev = None
    for n, stamp in enumerate(stamps):
        images = ds.load_frame(int(stamp))
        if images is None:
            continue
        T = T_WS(int(stamp) + shift_ns)
        T_WC = T @ cam0.T_SC
        out = tracker.process(int(stamp), images, None if T_prev is None else T_prev[:3, :3].T @ T[:3, :3])
        T_prev = T
        sel = out.camera_index == 0
        ids, uv = out.landmark_ids[sel], out.uv[sel]
        known = np.array([birth.get(int(i)) is not None for i in ids], bool)
        if known.any():
            pts = np.array([birth[int(i)][1] for i in ids[known]])
            proj, valid = cam0.camera.project(transform_points(inv_T(T_WC), pts))
            errors.append(np.linalg.norm(uv[known][valid] - proj[valid], axis=1))
            ages.append(n - np.array([birth[int(i)][0] for i in ids[known]])[valid])
            at_kf.append(np.full(int(valid.sum()), out.is_keyframe))
        new = np.array([int(i) not in birth for i in ids], bool)
        if new.any() and int(stamp) in depth_stamps:
            d = depth_at(depth.read(int(stamp)), uv[new])
            p_W = transform_points(T_WC, cam0.camera.unproject(uv[new]) * d[:, None])
            for i, p, ok in zip(ids[new], p_W, np.isfinite(d)):
                birth[int(i)] = (n, p) if ok else None  # None: born on a depth edge, never scored
    if not errors:
        raise ValueError(f"{root}: no track lived two frames")
    e, a, k = np.concatenate(errors), np.concatenate(ages), np.concatenate(at_kf)
    summary = summarise(e, a)
    summary["keyframes"] = _stats(e[k])
    return {"replica": str(root), "frames": int(len(stamps)), "first": first, "shift_ms": shift_ms,
            "overrides": list(overrides or []), "tracks": sum(v is not None for v in birth.values()),
            "errors": summary}


def _table(res: dict) -> str:
    lines = ["| ages [frames] | observations | median [px] | p90 [px] |", "|---|---:|---:|---:|"]
    for k, s in res["errors"].items():
        lines.append(f"| {k} | {s['n']} | {s['median_px']:.3f} | {s['p90_px']:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("replica", help="replica folder (with mav0/depth0 and ground truth)")
    ap.add_argument("--first", type=int, default=0, help="first frame index")
    ap.add_argument("--frames", type=int, default=300, help="frames to track (0: to the end)")
    ap.add_argument("--shift-ms", type=float, default=0.0, help="look true poses up this much after the stamps [ms]")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override")
    ap.add_argument("--json", help="write the figures here")
    a = ap.parse_args(argv)
    res = measure(a.replica, a.first, a.frames, a.shift_ms, a.set)
    print(f"{res['replica']}: {res['frames']} frames from {a.first}, {res['tracks']} camera-0 tracks, "
          f"shift {a.shift_ms} ms, {' '.join(a.set) or 'defaults'}")
    print(_table(res))
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
