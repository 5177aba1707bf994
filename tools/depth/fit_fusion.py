"""Fit the correlation of the stereo and MVS networks' errors that the fusion (eq. 14 generalised,
``services.depth.uncertainty.fuse``) assumes, on the validation split of the rendered set.

Eq. 14 weights the two depths by their inverse variances as if their errors were independent. Both networks see
the same images, so their errors are not: where the texture is poor both are wrong the same way, and the fused sigma
comes out too small (mean |error|/sigma 1.5-1.7 on the replica with independent errors). With a correlation rho of
the normalised errors the best linear combination has weights w1 = (s2^2 - rho s1 s2) / D, w2 = (s1^2 - rho s1 s2) / D,
D = s1^2 + s2^2 - 2 rho s1 s2 (clipped to [0, 1]), and the variance of that combination. This command runs both
networks on the validation frames and reports the correlation of their normalised errors (each clipped at 5 sigma,
so that a few gross errors do not decide it), to be set as ``depth.fusion_correlation``, and for information the fused
AbsRel and mean |error|/sigma for rho on a grid.

    python -m tools.depth.fit_fusion --data data/depth_train --frames 36

Never pass an evaluation set (the replica, Middlebury).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def collect(root: Path, frames: int, sources: int, prior_points: int, stereo_w: str, mvs_w: str, seed: int = 0):
    """Per valid pixel of the validation frames: (d_stereo, s_stereo, d_mvs, s_mvs, gt), calibrated sigmas."""
    from services.depth import weights
    from tools.depth.evaluate import _prior, _split_frames, mvs_net_depth, stereo_net_depth
    from tools.depth.make_dataset import BASELINE_M, K_RECT

    rng = np.random.default_rng(seed)
    st_net, st_meta = weights.load(weights.weights_path(stereo_w or "", weights.DEFAULT_STEREO))
    mv_net, mv_meta = weights.load(weights.weights_path(mvs_w or "", "mvs.pt"))
    cols = []
    for left, right, gt, T_WC, srcs, _ in _split_frames(root, "val", frames, sources):
        if not srcs:
            continue
        d1, s1 = stereo_net_depth(st_net, st_meta["gain"], left, right, float(K_RECT[0, 0]), BASELINE_M)
        d2, s2 = mvs_net_depth(mv_net, mv_meta["gain"], left, srcs, K_RECT, T_WC, _prior(rng, gt, prior_points))
        a = np.stack([np.ravel(x).astype(np.float64) for x in (d1, s1, d2, s2, gt)])
        cols.append(a[:, np.isfinite(a).all(axis=0) & (a[1] > 0) & (a[3] > 0) & (a[4] > 0)])
    if not cols:
        raise SystemExit(f"{root}/val: no frame with source views")
    return np.concatenate(cols, axis=1)


def main(argv: list[str] | None = None) -> int:
    from services.depth.uncertainty import fuse

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default="data/depth_train", help="rendered set; its 'val' split is used")
    p.add_argument("--frames", type=int, default=36)
    p.add_argument("--sources", type=int, default=4)
    p.add_argument("--prior-points", type=int, default=150)
    p.add_argument("--stereo-weights", default="")
    p.add_argument("--mvs-weights", default="")
    p.add_argument("--out", default="", help="also write the table as JSON here")
    a = p.parse_args(argv)
    d1, s1, d2, s2, gt = collect(Path(a.data), a.frames, a.sources, a.prior_points, a.stereo_weights, a.mvs_weights)
    z1, z2 = np.clip((d1 - gt) / s1, -5, 5), np.clip((d2 - gt) / s2, -5, 5)
    print(f"{d1.size} pixels; mean |error|/sigma stereo {np.mean(np.abs(d1 - gt) / s1):.3f}, "
          f"MVS {np.mean(np.abs(d2 - gt) / s2):.3f}")
    rows = []
    for rho in np.round(np.arange(0.0, 0.91, 0.05), 2):
        d, s = fuse(d1, s1, d2, s2, float(rho))
        rows.append({"rho": float(rho), "absrel": float(np.mean(np.abs(d - gt) / gt)),
                     "mean_err_over_sigma": float(np.mean(np.abs(d - gt) / s))})
        print(f"rho {rho:4.2f}: fused AbsRel {rows[-1]['absrel']:.4f}, mean |error|/sigma {rows[-1]['mean_err_over_sigma']:.3f}")
    rho = float(np.clip(np.corrcoef(z1, z2)[0, 1], 0.0, 0.9))
    print(f"depth.fusion_correlation: {rho:.2f} (the measured correlation, clipped to [0, 0.9])")
    if a.out:
        Path(a.out).write_text(json.dumps({"rows": rows, "rho": rho, "pixels": int(d1.size), "args": vars(a)}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
