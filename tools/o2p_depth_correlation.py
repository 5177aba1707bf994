"""How correlated are the depth errors of one frame-to-map factor's points?  (o2p.effective_points)

    python -m tools.o2p_depth_correlation REPLICA [--frames N] [--stride S] [--points N]

Eq. 7 weights the N points of an occupancy-to-point factor as independent. For frames of a replica (ground
truth ray-cast in the rectified left camera at the ground-truth pose, tools/depth/evaluate.py), the stereo
network's depth and learned sigma, and the ``--points`` lowest-sigma pixels the back end would take
(:func:`shared.occupancy.o2p_points.select_depth_points`), this measures the normalised errors
``z_i = (d_i - d_gt_i) / sigma_i`` and their mean pairwise correlation (biases shared by a frame's points
count as correlation, as they should: they do not average out)

    rho = mean_frames[((sum z)^2 - sum z^2) / (n (n - 1))] / mean(z^2),

and the equivalent number of independent points of an equicorrelated factor, ``N_eff = n / (1 + (n - 1) rho)``
(-> 1 / rho for large n). Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("replica")
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--stride", type=int, default=10, help="every n-th camera frame")
    p.add_argument("--skip", type=int, default=20, help="camera frames skipped at the start")
    p.add_argument("--points", type=int, default=200, help="points per factor (o2p.max_points_frame)")
    a = p.parse_args()

    from services.depth.pipeline import DepthPipeline
    from shared.occupancy.o2p_points import select_depth_points
    from services.app.system_config import load_system_config
    from shared.config import override
    from shared.rig import load_rig_config
    from tools.depth.evaluate import _replica_frames

    cfg = override(load_system_config(None, []), {"rig.calibration": a.replica})
    by_name = {c.name: c for c in load_rig_config(cfg.rig)}
    pipe = DepthPipeline(cfg.depth, by_name[cfg.depth.left_camera], by_name[cfg.depth.right_camera])
    K = pipe.K
    rho_num, z2, n_used, bias, per_frame, zs, errs, sigs = [], [], [], [], [], [], [], []
    for left, right, gt, _, _, _ in _replica_frames(Path(a.replica), a.frames, a.stride, a.skip, pipe.rect, 0,
                                                    np.random.default_rng(0)):
        d, s = pipe.stereo(left, right)
        pts, sig = select_depth_points(d, s, K, a.points)
        u = np.rint(pts[:, 0] / pts[:, 2] * K[0, 0] + K[0, 2]).astype(int)
        v = np.rint(pts[:, 1] / pts[:, 2] * K[1, 1] + K[1, 2]).astype(int)
        g = gt[v, u]
        ok = np.isfinite(g)
        z = (pts[ok, 2] - g[ok]) / sig[ok]
        n = len(z)
        if n < 10:
            continue
        rho_num.append((z.sum() ** 2 - (z**2).sum()) / (n * (n - 1)))
        z2.append(np.mean(z**2))
        n_used.append(n)
        bias.append(float(np.median(pts[ok, 2] - g[ok])))
        per_frame.append(rho_num[-1] / z2[-1])
        zs.append(z)
        errs.append(pts[ok, 2] - g[ok])
        sigs.append(sig[ok])
    rho = float(np.mean(rho_num) / np.mean(z2))
    n = float(np.mean(n_used))
    print(json.dumps({"replica": a.replica, "frames": len(n_used), "points": n, "rho": round(rho, 4),
                      "rho_frames_median": round(float(np.median(per_frame)), 4),
                      "n_eff": round(n / (1 + (n - 1) * rho), 1), "rms_z": round(float(np.sqrt(np.mean(z2))), 2),
                      "robust_z_scale": round(float(1.4826 * np.median(np.abs(np.concatenate(zs)))), 2),
                      "median_abs_err_m": round(float(np.median(np.abs(np.concatenate(errs)))), 4),
                      "median_sigma_m": round(float(np.median(np.concatenate(sigs))), 4),
                      "median_bias_m": round(float(np.median(bias)), 4)}), flush=True)


if __name__ == "__main__":
    main()
