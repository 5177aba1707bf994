"""``python -m tools eval depth``: depth and uncertainty of every method on held-out frames with ground truth.

Methods: SGBM with the quadratic and the linear heuristic sigma; the stereo network with its learned
sigma and, for the same depths, with the quadratic heuristic sigma; the MVS network; the fusion of both
networks (eq. 14). The heuristic models get the same treatment as the networks: one gain each, fitted
on the validation split of the rendered training set (sec. V-A). Per method: AbsRel, RMSE, delta<1.25,
mean Mahalanobis, NLL, fraction within 1/2/3 sigma (next to the Laplacian and Gaussian expectations), coverage; a
table (markdown + JSON), a calibration plot (PNG) and the CPU time per frame (median over frames).

Frames come from a synthetic replica (``--replica DIR``: EuRoC folder with ``mav0/scene/mesh.ply``;
ground truth ray-cast in the rectified left camera at the ground-truth pose; MVS sources are earlier
frames chosen by baseline) or from a split of the rendered set (``--split test``).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

METHODS = ("sgbm_quadratic", "sgbm_linear", "stereo_net", "stereo_net_quadratic", "mvs_net", "fused")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--replica", help="replica folder (EuRoC layout with mav0/scene/mesh.ply)")
    p.add_argument("--data", default="data/depth_train", help="rendered set (val split: heuristic gains; --split)")
    p.add_argument("--split", default="test", help="split of --data to evaluate when no --replica is given")
    p.add_argument("--frames", type=int, default=30, help="frames evaluated")
    p.add_argument("--stride", type=int, default=10, help="replica: every n-th frame (after --skip)")
    p.add_argument("--skip", type=int, default=40, help="replica: frames skipped at the start (MVS needs history)")
    p.add_argument("--sources", type=int, default=4, help="MVS source views")
    p.add_argument("--prior-points", type=int, default=150, help="sparse prior depths (landmark-like, 2%% noise)")
    p.add_argument("--border-margin-px", type=int, default=None, help="replica: depth dropped on the black rectification "
                   "border and this far around it, as the pipeline does (default depth.border_margin_px; -1: keep all)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (CPU times are process time: use 1)")
    p.add_argument("--precision", choices=("float32", "bfloat16"), default="float32",
                   help="the stereo network's arithmetic (depth.stereo_precision; MVS stays float32)")
    p.add_argument("--stereo-weights", default="", help="default: services/depth/weights/stereo_refine.pt (weights.DEFAULT_STEREO)")
    p.add_argument("--mvs-weights", default="", help="default: services/depth/weights/mvs.pt")
    p.add_argument("--fusion-correlation", type=float, default=None,
                   help="rho of the fusion (default: depth.fusion_correlation of the depth config)")
    p.add_argument("--out", default="out/depth/eval", help="output folder")


def _replica_frames(path: Path, n: int, stride: int, skip: int, rect, sources: int, rng):
    """Yields (left, right, gt, T_WC, [(src_img, T_WC_src)], stamp) from a replica."""
    import open3d as o3d

    from services.depth.views import select_sources
    from shared.euroc import read_euroc_csv
    from shared.euroc_reader import EurocDataset
    from services.app.synth.trajectory import Trajectory

    ds = EurocDataset(path)
    traj = Trajectory(read_euroc_csv(ds.groundtruth_path), knot_spacing_s=0.05)
    mesh = o3d.io.read_triangle_mesh(str(ds.root / "scene" / "mesh.ply"))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    w, h = rect.size
    v, u = np.mgrid[0:h, 0:w]
    rays = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1) @ np.linalg.inv(rect.K).T  # z = 1
    stamps = ds.frame_stamps_ns[(ds.frame_stamps_ns >= traj.t0_ns) & (ds.frame_stamps_ns <= traj.t_end_ns)]
    T_WC_all = traj.pose(stamps) @ rect.T_SN0
    names = ds.camera_names
    for k in range(n):
        i = skip + k * stride
        if i >= len(stamps):
            return
        imgs = ds.load_frame(stamps[i])
        left, right = rect.rectify(imgs[names.index("cam0")], imgs[names.index("cam1")])
        T = T_WC_all[i]
        dirs = rays @ T[:3, :3].T
        hit = scene.cast_rays(o3d.core.Tensor(np.hstack([np.tile(T[:3, 3], (len(dirs), 1)), dirs]).astype(np.float32)))
        gt = hit["t_hit"].numpy().reshape(h, w)  # rays have z = 1: t is the depth
        gt[~np.isfinite(gt)] = np.nan
        lo = max(0, i - 40)
        idx = select_sources(T, T_WC_all[lo:i], sources, 0.03, 1.0, 35.0)
        srcs = []
        for j in idx:
            im = ds.load_frame(stamps[lo + j])
            srcs.append((rect.rectify(im[names.index("cam0")], im[names.index("cam0")])[0], T_WC_all[lo + j]))
        yield left, right, gt.astype(np.float32), T, srcs, int(stamps[i])


def _split_frames(root: Path, split: str, n: int, sources: int):
    from services.depth.views import select_sources

    files = sorted((root / split).glob("scene_*.npz"))
    per = max(1, int(np.ceil(n / max(1, len(files)))))
    count = 0
    for f in files:
        with np.load(f) as z:
            s = dict(z)  # decompress once
        T = s["T_WC"]
        for i in np.linspace(0, len(T) - 1, per).astype(int):
            if count >= n:
                return
            others = np.array([j for j in range(len(T)) if j != i])
            order = others[np.argsort(np.abs(others - i))[::-1]]
            idx = order[select_sources(T[i], T[order], sources, 0.03, 1.0, 40.0)]
            yield s["left"][i], s["right"][i], s["depth"][i], T[i], [(s["left"][j], T[j]) for j in idx], count
            count += 1


def _prior(rng, gt: np.ndarray, n: int) -> np.ndarray:
    from tools.depth.train import prior_points

    return prior_points(rng, np.where(np.isfinite(gt), gt, np.nan), n)


def _valid_pixels(rect, cams, margin_px: int | None) -> np.ndarray | None:
    """Pixels where DepthPipeline keeps depth (services/depth/coverage.py), None with a negative margin."""
    from services.depth.config import DepthConfig
    from services.depth.coverage import stereo_valid

    margin = DepthConfig().border_margin_px if margin_px is None else margin_px
    if margin < 0:
        return None
    return stereo_valid(rect, [(c.camera.height, c.camera.width) for c in cams[:2]], margin)


def heuristic_gains(root: Path, f_px: float, baseline_m: float, stereo_net, n_frames: int = 12) -> dict[str, float]:
    """Gains of the heuristic sigma models on the validation split (same calibration as the networks)."""
    from services.depth.sgbm import sgbm_depth
    from services.depth.uncertainty import calibration_gain, heuristic_sigma

    acc: dict[str, list] = {"sgbm_quadratic": [], "sgbm_linear": [], "stereo_net_quadratic": []}
    for left, right, gt, *_ in _split_frames(root, "val", n_frames, 1):
        for name, model, coeff in (("sgbm_quadratic", "quadratic", 1.0), ("sgbm_linear", "linear", 0.01)):
            d, s = sgbm_depth(left, right, f_px, baseline_m, model, coeff)
            acc[name].append((d, s, gt))
        if stereo_net is not None:
            d, _ = stereo_net_depth(stereo_net, 1.0, left, right, f_px, baseline_m)
            acc["stereo_net_quadratic"].append((d, heuristic_sigma(d, "quadratic", 1.0 / (f_px * baseline_m)), gt))
    return {k: calibration_gain(*(np.stack(x) for x in zip(*v))) for k, v in acc.items() if v}


def stereo_net_depth(net, gain: float, left: np.ndarray, right: np.ndarray, f_px: float, baseline_m: float,
                     precision: str = "float32") -> tuple[np.ndarray, np.ndarray]:
    """Depth and sigma [m] of a stereo network on one rectified pair (eq. 11), sigma times ``gain`` (the weights')."""
    import torch

    from services.depth import weights
    from services.depth.uncertainty import disparity_to_depth

    tt = lambda a: torch.from_numpy(np.asarray(a)).float()[None, None]
    with weights.inference("cpu", precision):
        u, su = (x.float() for x in net(tt(left), tt(right)))
    return disparity_to_depth(u[0].numpy(), su[0].numpy() * gain, f_px, baseline_m)


def mvs_net_depth(net, gain: float, ref: np.ndarray, srcs: list, K: np.ndarray, T_WC: np.ndarray,
                  prior: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth and sigma [m] of the MVS network (eq. 13), sigma times ``gain``: reference image, its T_WC, sources
    [(image, T_WC)], the intrinsics and a sparse prior depth (0 where none)."""
    import torch

    from services.depth import weights
    from services.depth.uncertainty import logdepth_to_depth

    tt = lambda a: torch.from_numpy(np.asarray(a)).float()[None]
    with weights.inference("cpu"):
        ld, sl = net(tt(ref)[:, None], tt(np.stack([x[0] for x in srcs]))[:, :, None], tt(K),
                     tt(np.stack([np.linalg.inv(x[1]) @ T_WC for x in srcs])), tt(prior))
    return logdepth_to_depth(ld[0].numpy(), sl[0].numpy() * gain)


def main(args: argparse.Namespace) -> int:
    import torch

    from services.depth import weights
    from services.depth.config import DepthConfig
    from services.depth.sgbm import sgbm_depth
    from services.depth.uncertainty import EXPECTED_WITHIN, depth_metrics, fuse, heuristic_sigma
    from shared.camera import camera_from_sensor_yaml, read_sensor_yaml_file, stereo_rectification
    from tools.depth.make_dataset import BASELINE_M, K_RECT

    torch.set_num_threads(args.threads)
    rho = DepthConfig().fusion_correlation if args.fusion_correlation is None else args.fusion_correlation
    rng = np.random.default_rng(0)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    st_net, st_meta = weights.load(weights.weights_path(args.stereo_weights or "", weights.DEFAULT_STEREO))
    mv_net, mv_meta = weights.load(weights.weights_path(args.mvs_weights or "", "mvs.pt"))
    if args.replica:
        root = Path(args.replica) / "mav0" if (Path(args.replica) / "mav0").is_dir() else Path(args.replica)
        cams = [camera_from_sensor_yaml(read_sensor_yaml_file(root / c / "sensor.yaml"), c) for c in ("cam0", "cam1")]
        rect = stereo_rectification(cams[0], cams[1], (512, 384))
        K, baseline = rect.K, rect.baseline_m
        frames = _replica_frames(Path(args.replica), args.frames, args.stride, args.skip, rect, args.sources, rng)
        valid = _valid_pixels(rect, cams, args.border_margin_px)
        source = f"replica {args.replica}"
    else:
        K, baseline = K_RECT, BASELINE_M
        valid = None  # rendered pinhole pairs: every pixel has content
        frames = _split_frames(Path(args.data), args.split, args.frames, args.sources)
        source = f"{args.data}/{args.split}"
    f_px = float(K[0, 0])
    if not any((Path(args.data) / "val").glob("scene_*.npz")):
        raise SystemExit(f"eval depth: no validation scenes in {args.data}/val (the heuristic sigmas are calibrated "
                         "on them); render the set first: python -m tools.depth.make_dataset --out data/depth_train "
                         "--train 40 --val 12 --test 3 (docs/depth.md)")
    hg = heuristic_gains(Path(args.data), f_px, baseline, st_net)
    q_coeff = 1.0 / (f_px * baseline)
    acc = {m: [] for m in METHODS}
    times: dict[str, list] = {"sgbm": [], "stereo_net": [], "mvs_net": [], "fusion": []}
    n_src = []
    for left, right, gt, T_WC, srcs, _ in frames:
        t = time.process_time()
        d, s = sgbm_depth(left, right, f_px, baseline, "quadratic", 1.0)
        times["sgbm"].append(time.process_time() - t)
        acc["sgbm_quadratic"].append((d, s * hg["sgbm_quadratic"], gt))
        acc["sgbm_linear"].append((d, heuristic_sigma(d, "linear", 0.01 * hg["sgbm_linear"]), gt))
        t = time.process_time()
        d_st, s_st = stereo_net_depth(st_net, st_meta["gain"], left, right, f_px, baseline, args.precision)
        times["stereo_net"].append(time.process_time() - t)
        acc["stereo_net"].append((d_st, s_st, gt))
        acc["stereo_net_quadratic"].append((d_st, heuristic_sigma(d_st, "quadratic", q_coeff * hg["stereo_net_quadratic"]), gt))
        if not srcs:
            continue
        n_src.append(len(srcs))
        prior = _prior(rng, gt, args.prior_points)
        t = time.process_time()
        d_mv, s_mv = mvs_net_depth(mv_net, mv_meta["gain"], left, srcs, K, T_WC, prior)
        times["mvs_net"].append(time.process_time() - t)
        acc["mvs_net"].append((d_mv, s_mv, gt))
        t = time.process_time()
        acc["fused"].append((*fuse(d_st, s_st, d_mv, s_mv, rho), gt))
        times["fusion"].append(time.process_time() - t)
    rows = {}
    for m, v in acc.items():
        if not v:
            continue
        d, s, g = (np.stack(x) for x in zip(*v))
        if valid is not None:  # every method keeps depth where the pipeline does; coverage counts the rest as missing
            d = np.where(valid, d, np.nan)
        met = depth_metrics(d, s, g)
        met["coverage"] = float(np.mean(np.isfinite(d) & np.isfinite(g)) / max(np.mean(np.isfinite(g)), 1e-9))
        rows[m] = met
    timing = {k: float(np.median(v) * 1000) for k, v in times.items() if v}
    result = {"source": source, "frames": len(acc["stereo_net"]), "mvs_frames": len(acc["mvs_net"]),
              "mean_sources": float(np.mean(n_src)) if n_src else 0.0, "heuristic_gains": hg,
              "network_gains": {"stereo": st_meta["gain"], "mvs": mv_meta["gain"]}, "fusion_correlation": rho, "metrics": rows,
              "median_ms": timing, "threads": args.threads, "expected_within_laplace": EXPECTED_WITHIN["laplace"],
              "expected_within_gauss": EXPECTED_WITHIN["gauss"]}
    (out / "metrics.json").write_text(json.dumps(result, indent=1))
    lines = [f"Depth evaluation on {source}: {result['frames']} frames ({result['mvs_frames']} with MVS, "
             f"{result['mean_sources']:.1f} sources on average; fusion correlation {rho:g})", "",
             "| method | AbsRel | RMSE [m] | d<1.25 | mean Mahalanobis | NLL (Laplace) | NLL (Gauss) | <1s | <2s | <3s "
             "| coverage |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for m, r in rows.items():
        lines.append(f"| {m} | {r['absrel']:.4f} | {r['rmse']:.4f} | {r['delta1']:.3f} | {r['mahalanobis']:.3f} | "
                     f"{r['nll_laplace']:.3f} | {r['nll_gauss']:.3f} | {r['within_1s']:.3f} | {r['within_2s']:.3f} | {r['within_3s']:.3f} | "
                     f"{r['coverage']:.3f} |")
    e = EXPECTED_WITHIN["laplace"]
    g = EXPECTED_WITHIN["gauss"]
    lines += [f"| (Laplace expectation, sigma = scale b) | | | | 1.000 | | | {e[0]:.3f} | {e[1]:.3f} | {e[2]:.3f} | |",
              f"| (Gaussian expectation, sigma = std) | | | | 0.798 | | | {g[0]:.3f} | {g[1]:.3f} | {g[2]:.3f} | |", "",
              "CPU time (process time, not wall time: the machine is shared) per 512x384 frame, median [ms] (" +
              f"{args.threads} threads): " +
              ", ".join(f"{k} {v:.1f}" for k, v in timing.items())]
    (out / "table.md").write_text("\n".join(lines) + "\n")
    _plot(acc, out / "calibration.png", valid)
    print("\n".join(lines))
    return 0


def _plot(acc, path: Path, valid: np.ndarray | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = np.linspace(0, 4, 81)
    fig, ax = plt.subplots(figsize=(6, 4.5))
    ax.plot(k, 1 - np.exp(-k), "k--", label="Laplace expectation")
    from scipy.special import erf

    ax.plot(k, erf(k / np.sqrt(2)), "k:", label="Gaussian expectation")
    for m, v in acc.items():
        if not v:
            continue
        d, s, g = (np.stack(x) for x in zip(*v))
        if valid is not None:
            d = np.where(valid, d, np.nan)
        d, s, g = d.ravel(), s.ravel(), g.ravel()
        ok = np.isfinite(d) & np.isfinite(s) & np.isfinite(g) & (s > 0)
        z = np.sort(np.abs(d[ok] - g[ok]) / s[ok])
        ax.plot(k, np.searchsorted(z, k) / max(len(z), 1), label=m)
    ax.set_xlabel("k (|d - d_gt| < k sigma)")
    ax.set_ylabel("fraction of pixels")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
