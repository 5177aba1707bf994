"""Where does fused depth hurt the map? Diagnostic of the mapping ablation's ``fused`` variant.

Two stages, so that map variants can be tried without re-running the networks:

    python -m tools.depth.fused_map_diag dump REPLICA --frames 80 --out DIR     # networks, GT depth -> DIR/frames.npz
    python -m tools.depth.fused_map_diag maps DIR --variants stereo,fused,...     # occupancy maps of variants
    python -m tools.depth.fused_map_diag stats DIR                              # per-pixel error tails

``dump`` feeds :class:`services.depth.pipeline.DepthPipeline` exactly as ``python -m tools bench mapping-ablation``
does (GT poses, every ``--keyframe-every``-th used frame a keyframe) and stores per frame the stereo, MVS
and fused depth and sigma, the number of MVS source views, the pose, and the ground-truth depth ray-cast
from the replica's scene mesh in the rectified left camera.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def dump(a) -> int:
    import cv2
    import open3d as o3d

    from services.depth.config import DepthConfig
    from services.depth.pipeline import DepthPipeline
    from shared.occupancy.uncertain_pixels import surface_depth
    from shared.camera import load_rig
    from tools.bench_mapping import replica_frames
    from tools.mapping_ablation import _images
    from tests.raycast_depth import DepthRenderer

    folder, out = Path(a.replica), Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    mav = folder / "mav0"
    rig = {c.name: c for c in load_rig(mav)}
    cfg = DepthConfig(**json.loads(a.depth_cfg)) if a.depth_cfg else DepthConfig()
    pipe = DepthPipeline(cfg, rig["cam0"], rig["cam1"])
    renderer = DepthRenderer(o3d.io.read_triangle_mesh(str(mav / "scene" / "mesh.ply")))
    left, right = _images(mav, "cam0"), _images(mav, "cam1")
    rec: dict[str, list] = {k: [] for k in ("stamp", "T_WC", "gt", "st_d", "st_s", "mv_d", "mv_s", "fu_d", "fu_s", "n_src")}
    kf_stamps, kf_T = [], []
    for i, (stamp, _d, _K, T_WC_gt) in enumerate(replica_frames(folder, a.frames, a.stride)):
        if stamp not in left or stamp not in right:
            continue
        T_WS = T_WC_gt @ np.linalg.inv(rig["cam0"].T_SC)
        raw_l = cv2.imread(str(left[stamp]), cv2.IMREAD_GRAYSCALE)
        raw_r = cv2.imread(str(right[stamp]), cv2.IMREAD_GRAYSCALE)
        pipe.remember_frame(stamp, raw_l)
        res = pipe.process(stamp, raw_l, raw_r, T_WS)
        T_WC = T_WS @ pipe.T_SC
        nan = np.full_like(res.stereo[0], np.nan)
        mv = res.mvs if res.mvs is not None else (nan, nan)
        k = res.surface_max_relative_sigma  # pixels too uncertain for a surface: NaN here, as the map takes none
        st, mv, fu = ((surface_depth(d, s, k), s) for d, s in (res.stereo, mv, res.fused))
        for k, v in (("stamp", stamp), ("T_WC", T_WC), ("gt", renderer.render(pipe.K, cfg.width, cfg.height, T_WC)),
                     ("st_d", st[0]), ("st_s", st[1]), ("mv_d", mv[0]), ("mv_s", mv[1]),
                     ("fu_d", fu[0]), ("fu_s", fu[1]), ("n_src", res.n_sources)):
            rec[k].append(v)
        if i % a.keyframe_every == 0:
            kf_stamps.append(stamp)
            kf_T.append(T_WS)
            pipe.update_keyframes(np.array(kf_stamps), np.array(kf_T))
        print(f"frame {i} n_src {res.n_sources}", flush=True)
    np.savez(out / "frames.npz", K=pipe.K, T_SC=pipe.T_SC, **{k: np.stack(v) for k, v in rec.items()})
    return 0


def _swap(bad: np.ndarray, into: tuple[np.ndarray, np.ndarray], taken: tuple) -> tuple[np.ndarray, np.ndarray]:
    """(depth, sigma) ``into`` with the ``bad`` pixels taken from ``taken`` (arrays or scalars)."""
    return np.where(bad, taken[0], into[0]), np.where(bad, taken[1], into[1])


def _variant(name: str, z) -> tuple[np.ndarray, np.ndarray]:
    """(depth, sigma) stacks of a named variant built from the dumped frames."""
    from services.depth.uncertainty import fuse

    st_d, st_s, mv_d, mv_s, fu_d, fu_s, gt = (z[k] for k in ("st_d", "st_s", "mv_d", "mv_s", "fu_d", "fu_s", "gt"))
    if "*" in name and "-" not in name:  # 'stereo*x', 'fused*x[*y]': stereo (MVS) sigma scaled by x (y), refused
        base, *xs = name.split("*")
        x, y = float(xs[0]), float(xs[1]) if len(xs) > 1 else 1.0
        if base == "stereo":
            return st_d, st_s * x
        if base == "fused":
            return fuse(st_d, st_s * x, mv_d, mv_s * y)
    if name == "stereo":
        return st_d, st_s
    if name == "fused":
        return fu_d, fu_s
    if name == "mvs":
        return mv_d, mv_s
    if name == "fused-refuse":  # eq. 14 recomputed from the dumped inputs (sanity check of the dump)
        return fuse(st_d, st_s, mv_d, mv_s)
    with np.errstate(invalid="ignore"):
        if name == "fused-disagree-stereo":  # the disagreement pixels of the brief replaced by stereo
            return _swap((st_s > 0.4) & (mv_d - st_d > 0.8), (fu_d, fu_s), (st_d, st_s))
        if name == "fused-oracle-stereo":  # fused pixels more than 3 sigma behind GT replaced by stereo
            return _swap((fu_d - gt) > 3 * fu_s, (fu_d, fu_s), (st_d, st_s))
        if name == "fused-oracle-drop":  # fused pixels more than 3 sigma off GT dropped
            return _swap(np.abs(fu_d - gt) > 3 * fu_s, (fu_d, fu_s), (np.nan, np.nan))
        if name == "stereo-oracle-drop":
            return _swap(np.abs(st_d - gt) > 3 * st_s, (st_d, st_s), (np.nan, np.nan))
        if name == "fused-stereo-sigma":  # fused depth with the stereo sigma: is it the sigma or the depth?
            return fu_d, st_s
        if name == "stereo-fused-sigma":
            return st_d, fu_s
        if name == "gt-fused-sigma":
            return gt, fu_s
        if name == "gt-stereo-sigma":
            return gt, st_s
        if "-rectmask-" in name:  # outside the rectified images' coverage (eroded by n px) dropped
            base, n = name.split("-rectmask-")
            return _swap(~_coverage(z, int(n)), _variant(base, z), (np.nan, np.nan))
        if "-relsigma-" in name:  # pixels whose sigma exceeds k times their depth dropped
            base, k = name.split("-relsigma-")
            d, s = _variant(base, z)
            return _swap(s > float(k) * d, (d, s), (np.nan, np.nan))
        if "-maxsigma-" in name:  # pixels whose sigma exceeds s [m] dropped
            base, m = name.split("-maxsigma-")
            d, s = _variant(base, z)
            return _swap(s > float(m), (d, s), (np.nan, np.nan))
        if name.startswith("fused-minsrc-"):  # frames with fewer MVS source views than n keep stereo alone
            n = int(name.rsplit("-", 1)[1])
            few = (z["n_src"] < n)[:, None, None]
            return _swap(np.broadcast_to(few, st_d.shape), (fu_d, fu_s), (st_d, st_s))
        if name.startswith("fused-gate-"):  # stereo alone where the two disagree by more than k combined sigmas
            k = float(name.rsplit("-", 1)[1])
            bad = np.abs(mv_d - st_d) > k * np.sqrt(st_s ** 2 + mv_s ** 2)
            return _swap(bad, (fu_d, fu_s), (st_d, st_s))
        if name.startswith("fused-rho-"):  # refused with this correlation of the two networks' errors
            return fuse(st_d, st_s, mv_d, mv_s, float(name.rsplit("-", 1)[1]))
        if name.startswith("fused-border"):  # MVS ignored within n px of the image border
            n = int(name.rsplit("-", 1)[1])
            m = np.ones(st_d.shape[1:], bool)
            m[n:-n, n:-n] = False
            return _swap(m, (fu_d, fu_s), (st_d, st_s))
    raise ValueError(f"unknown variant {name}")


def _coverage(z, margin_px: int) -> np.ndarray:
    """(H,W) bool: where the depth pipeline keeps depth (services/depth/coverage.py) for the dumped replica."""
    from services.depth.coverage import stereo_valid
    from shared.camera import load_rig, stereo_rectification

    rig = {c.name: c for c in load_rig(Path(z["replica"].item()) / "mav0")}
    h, w = z["gt"].shape[1:]
    rect = stereo_rectification(rig["cam0"], rig["cam1"], (w, h))
    return stereo_valid(rect, [(rig[c].camera.height, rig[c].camera.width) for c in ("cam0", "cam1")], margin_px)


def maps(a) -> int:
    from services.mapping.config import SensorModelConfig, SubmapConfig
    from services.mapping.io import write_ply
    from services.mapping.submaps import SubmapMapper
    from services.app.metrics.mesh import evaluate_mesh_files

    d = Path(a.dir)
    z = dict(np.load(d / "frames.npz"))
    z["replica"] = np.array(str(a.replica))
    gt_mesh = Path(a.replica) / "mav0" / "scene" / "mesh.ply"
    for name in a.variants.split(","):
        dep, sig = _variant(name, z)
        m = SubmapMapper(SensorModelConfig(), SubmapConfig())
        for k in range(len(dep)):
            m.integrate(dep[k], sig[k], z["K"], z["T_WC"][k], z["T_SC"], int(z["stamp"][k]))
        m.remesh()
        v, f = m.world_mesh()
        o = d / "maps" / name
        write_ply(o / "mesh.ply", v, f)
        r = evaluate_mesh_files(o / "mesh.ply", gt_mesh, out_dir=o)
        print(f"{name:24s} accuracy {r.accuracy_m:.4f} m (median {r.accuracy_median_m:.4f})  completeness "
              f"{100 * r.completeness:.1f} % @ 0.2 m, {100 * r.completeness_5cm:.1f} % @ 0.05 m", flush=True)
    return 0


def stats(a) -> int:
    z = dict(np.load(Path(a.dir) / "frames.npz"))
    gt = z["gt"]
    n, h, w = gt.shape
    print(f"{n} frames, n_src per frame: {z['n_src'].tolist()}")
    v, u = np.mgrid[0:h, 0:w]
    border = np.minimum(np.minimum(u, w - 1 - u), np.minimum(v, h - 1 - v))
    for key in ("st", "mv", "fu"):
        d, s = z[f"{key}_d"], z[f"{key}_s"]
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(d) & np.isfinite(gt)
            e = d - gt
            behind = ok & (e > 0.3)
            front = ok & (e < -0.3)
        print(f"{key}: valid {ok.sum()}  AbsRel {np.nanmean(np.abs(e[ok]) / gt[ok]):.4f}  "
              f">0.3 m behind {100 * behind.sum() / ok.sum():.2f} %  >0.3 m in front {100 * front.sum() / ok.sum():.2f} %  "
              f"|e|>3s {100 * np.mean(np.abs(e[ok]) > 3 * s[ok]):.2f} %")
        if behind.any():
            bb = np.broadcast_to(border, gt.shape)[behind]
            print(f"   behind: border dist px quartiles {np.percentile(bb, [10, 25, 50, 75, 90]).round(0).tolist()}  "
                  f"depth med {np.median(d[behind]):.2f} gt med {np.median(gt[behind]):.2f} sigma med {np.median(s[behind]):.3f}"
                  f"  sigma<0.5 {100 * np.mean(s[behind] < 0.5):.0f} %")
            per_frame = behind.reshape(n, -1).sum(1)
            print(f"   behind per frame: {per_frame.tolist()}")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("dump")
    p.add_argument("replica")
    p.add_argument("--frames", type=int, default=80)
    p.add_argument("--stride", type=int, default=2)
    p.add_argument("--keyframe-every", type=int, default=3)
    p.add_argument("--depth-cfg", default="", help="JSON of DepthConfig overrides")
    p.add_argument("--out", required=True)
    p = sub.add_parser("maps")
    p.add_argument("dir")
    p.add_argument("--replica", required=True)
    p.add_argument("--variants", default="stereo,fused,mvs")
    p = sub.add_parser("stats")
    p.add_argument("dir")
    a = ap.parse_args(argv)
    return {"dump": dump, "maps": maps, "stats": stats}[a.cmd](a)


if __name__ == "__main__":
    raise SystemExit(main())
