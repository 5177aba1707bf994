"""``python -m tools eval stereo``: the stereo network against OpenCV SGBM on real photographs with ground truth.

    python -m tools eval stereo ../shared/data/real/middlebury_2001_2003 --out out/depth/stereo

Scenes are Middlebury-style folders (tools/depth/stereo_scene.py: the 2001/2003 and 2014 layouts); by default the
four classic scenes in ``$SIGMASLAM_SHARED/data/real/middlebury_2001_2003``. They are a test set: nothing in
this project trains or calibrates on them.

Methods, per scene and on average:

- ``net`` (one row per ``--weights``): the network's dense disparity and its sigma times the gain in the
  weights' JSON (fitted on the training data's validation split). An SGBM-guided network
  (services/depth/refine_net.py) gets the scene's stated range for its SGBM like ``sgbm``, and a second row
  ``net@96`` with the depth service's fixed 96 px search range;
- ``sgbm``: OpenCV SGBM (the depth service's parameters, left-right checked, its search range the scene's stated
  largest disparity rounded up to 16, as Middlebury gives every method) on the pixels it matches,
  sigma the heuristic constant disparity sigma ``depth.heuristic_sigma_coeff`` (1 px);
- ``sgbm_dense``: SGBM made dense the way sparse methods are scored on KITTI: each hole takes the smaller
  (farther) of the nearest matched disparities to its left and right on its row, so holes count with the error
  of that fill; sigma as ``sgbm``.

Metrics on the non-occluded mask (``nonocc``; EPE and bad-2 also on ``all``): end-point error [px], bad-1/2/3
[%] (error > 1/2/3 px), coverage [%], mean |error|/sigma (1 when calibrated, as sigma is a Laplacian scale)
and the fraction within 1/2/3 sigma (Laplacian expectation 63/86/95 %).

**Scaling.** A pair is fed at its own resolution when its largest disparity (``info.txt`` or the ground truth)
fits in ``--fit`` (0.9) of the network's range (96 px for the shipped network; all four classic scenes do, at
15-59 px); otherwise both images are shrunk by the factor that makes it fit, and the disparity and sigma are
enlarged back to the ground truth's pixels. Sizes are padded to multiples of 16 (edge pixels repeated) and the
padding cropped off. Errors are always in the ground truth's pixels. SGBM sees the same (scaled) images.

**Real EuRoC frames** (``--euroc DIR``, default the 60 real V1_01 frames when present): no ground truth, so the
check is agreement: where SGBM matches (left-right consistent) inside the rectified valid region, the mean
|u_net - u_sgbm| / sigma_net, the median |u_net - u_sgbm| [px] and the fraction within 1/2/3 sigma.

Writes ``metrics.json``, ``table.md`` and ``<scene>.png`` (left image, ground truth, disparity, |error|, sigma,
|error|/sigma of the first network) to ``--out``.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from services.depth.sgbm import SgbmParams, fill_background, sgbm_disparity
from tools.depth.stereo_scene import StereoScene, find_scenes, read_stereo_scene

DEFAULT_SCENES = "middlebury_2001_2003"
DEFAULT_EUROC = "euroc_V1_01_micro"
LAPLACE_WITHIN = (0.632, 0.865, 0.950)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenes", nargs="*", help="scene folders or folders of scenes (default: $SIGMASLAM_SHARED/data/real/"
                   f"{DEFAULT_SCENES})")
    p.add_argument("--weights", action="append", default=[],
                   help="stereo weights (.pt with .json), repeatable; default the shipped default (stereo_refine.pt)")
    p.add_argument("--euroc", default=None, help=f"real EuRoC folder for the agreement check (default $SIGMASLAM_SHARED/"
                   f"data/real/{DEFAULT_EUROC} when present; 'none' to skip)")
    p.add_argument("--euroc-frames", type=int, default=12, help="EuRoC frames checked (evenly spread)")
    p.add_argument("--fit", type=float, default=0.9, help="a pair is shrunk when its largest disparity exceeds this "
                   "fraction of the network's range")
    p.add_argument("--threads", type=int, default=1, help="torch threads (CPU times are process time: use 1)")
    p.add_argument("--precision", choices=("float32", "bfloat16"), default="float32",
                   help="the stereo network's arithmetic (depth.stereo_precision; MVS stays float32)")
    p.add_argument("--no-plots", action="store_true", help="skip the per-scene pictures")
    p.add_argument("--out", default="out/depth/stereo", help="output folder")


# ---------------------------------------------------------------------------------------------- algorithms
def disparity_metrics(est: np.ndarray, sigma: np.ndarray | None, gt: np.ndarray, mask: np.ndarray) -> dict:
    """Metrics over ``mask`` & known ground truth; accuracy on the pixels with an estimate (coverage says how many)."""
    m = mask & np.isfinite(gt)
    n = int(m.sum())
    has = m & np.isfinite(est)
    out: dict = {"n": n, "coverage": 100.0 * has.sum() / max(n, 1)}
    if not has.any():
        return out
    err = np.abs(est[has] - gt[has]).astype(np.float64)
    out |= {"epe": float(err.mean()), **{f"bad{k}": float(100.0 * np.mean(err > k)) for k in (1, 2, 3)}}
    if sigma is not None:
        s = sigma[has].astype(np.float64)
        ok = np.isfinite(s) & (s > 0)
        z = err[ok] / s[ok]
        out |= {"err_over_sigma": float(z.mean()), **{f"within{k}s": float(100.0 * np.mean(z < k)) for k in (1, 2, 3)}}
    return out


def _resize(a: np.ndarray, shape: tuple[int, int], interp) -> np.ndarray:
    import cv2

    return cv2.resize(a, (shape[1], shape[0]), interpolation=interp)


def scene_scale(scene: StereoScene, net_range: float, fit: float) -> float:
    """The factor (<= 1) the pair is shrunk by so that its largest disparity fits ``fit`` of the network's range."""
    top = scene.max_disparity if np.isfinite(scene.max_disparity) else float(np.nanmax(scene.disparity))
    return min(1.0, fit * net_range / max(top, 1e-6))


def run_methods(scene: StereoScene, nets: list[tuple[str, object, float]], fit: float, sigma_sgbm_px: float,
                device: str = "cpu", precision: str = "float32") -> dict[str, dict]:
    """{method: {'disp', 'sigma', 'cpu_s'}} at the ground truth's resolution and pixel units."""
    import cv2

    from services.depth.stereo_net import predict_disparity

    net_range = min((getattr(n, "max_disparity", 96) for _, n, _ in nets), default=96)
    s = scene_scale(scene, net_range, fit)
    shape = scene.left.shape
    left, right = scene.left, scene.right
    if s < 1.0:
        small = (max(16, round(shape[0] * s)), max(16, round(shape[1] * s)))
        left, right = (_resize(a, small, cv2.INTER_AREA) for a in (left, right))
    back = lambda a: a if s >= 1.0 else _resize(a, shape, cv2.INTER_LINEAR) / (left.shape[1] / shape[1])
    # the scene's stated range (info.txt / calib.txt ndisp, which Middlebury gives every method), not the GT
    top = scene.max_disparity if np.isfinite(scene.max_disparity) else float(np.nanmax(scene.disparity))
    n_disp = int(np.ceil(max(16.0, top * s + 1) / 16) * 16)
    out: dict[str, dict] = {}
    for label, net, gain in nets:
        runs = [(label, n_disp)]
        if hasattr(net, "refine"):  # SGBM-guided: also with the depth service's fixed search range
            runs.append((f"{label}@{net.max_disparity}", None))
        for name, search in runs:
            c0 = time.process_time()
            u, su = predict_disparity(net, left, right, device, search, precision)
            out[name] = {"disp": back(u), "sigma": back(su * gain), "cpu_s": time.process_time() - c0, "scale": s}
    c0 = time.process_time()
    sg = sgbm_disparity(left, right, SgbmParams(num_disparities=n_disp))
    cpu = time.process_time() - c0
    if s < 1.0:  # nearest keeps holes as holes
        sg = _resize(sg, shape, cv2.INTER_NEAREST) / (left.shape[1] / shape[1])
    const = np.full(shape, sigma_sgbm_px, np.float32)
    out["sgbm"] = {"disp": sg, "sigma": const, "cpu_s": cpu, "scale": s}
    out["sgbm_dense"] = {"disp": fill_background(sg), "sigma": const, "cpu_s": cpu, "scale": s}
    return out


def scene_metrics(scene: StereoScene, results: dict[str, dict]) -> dict[str, dict]:
    rows = {}
    for method, r in results.items():
        m = disparity_metrics(r["disp"], r["sigma"], scene.disparity, scene.masks["nonocc"])
        m_all = disparity_metrics(r["disp"], None, scene.disparity, scene.masks["all"])
        rows[method] = m | {"epe_all": m_all.get("epe"), "bad2_all": m_all.get("bad2"), "cpu_ms": 1e3 * r["cpu_s"],
                            "scale": r["scale"]}
    return rows


def euroc_agreement(dataset: Path, nets: list[tuple[str, object, float]], frames: int, device: str = "cpu",
                    precision: str = "float32") -> dict:
    """Per network: agreement with SGBM on real EuRoC frames rectified as the depth service does."""
    from services.depth.config import DepthConfig
    from services.depth.pipeline import pipeline_for_rig
    from services.depth.stereo_net import predict_disparity
    from shared.camera import load_rig
    from shared.euroc_reader import EurocDataset

    cfg = DepthConfig(method="sgbm")  # the service's rectification and valid region, no network loaded
    pipe = pipeline_for_rig(cfg, load_rig(dataset))
    rect, valid = pipe.rect, pipe.valid
    ds = EurocDataset(dataset)
    names = ds.camera_names
    picks = np.unique(np.linspace(0, len(ds.frame_stamps_ns) - 1, frames).round().astype(int))
    z = {label: [] for label, _, _ in nets}
    diff = {label: [] for label, _, _ in nets}
    sgbm_cov = []
    for i in picks:
        imgs = ds.load_frame(int(ds.frame_stamps_ns[i]))
        left, right = rect.rectify(imgs[names.index(cfg.left_camera)], imgs[names.index(cfg.right_camera)])
        sg = sgbm_disparity(left, right, SgbmParams(num_disparities=cfg.sgbm_num_disparities,
                                                    block_size=cfg.sgbm_block_size))
        ok = np.isfinite(sg) & valid
        sgbm_cov.append(ok.sum() / max(1, valid.sum()))
        for label, net, gain in nets:
            u, su = predict_disparity(net, left, right, device, precision=precision)
            d = np.abs(u[ok] - sg[ok])
            diff[label].append(d)
            z[label].append(d / (su[ok] * gain))
    out = {"dataset": str(dataset), "frames": len(picks), "sgbm_coverage": float(100 * np.mean(sgbm_cov))}
    for label in z:
        zz, dd = np.concatenate(z[label]), np.concatenate(diff[label])
        out[label] = {"diff_over_sigma": float(zz.mean()), "median_diff_px": float(np.median(dd)),
                      **{f"within{k}s": float(100 * np.mean(zz < k)) for k in (1, 2, 3)}}
    return out


# ---------------------------------------------------------------------------------------------- report
COLUMNS = [("epe", "EPE [px]", 2), ("bad1", "bad-1 [%]", 1), ("bad2", "bad-2 [%]", 1), ("bad3", "bad-3 [%]", 1),
           ("coverage", "coverage [%]", 0), ("epe_all", "EPE all [px]", 2), ("bad2_all", "bad-2 all [%]", 1),
           ("err_over_sigma", "mean abs(err)/sigma", 2), ("within1s", "<1 sigma [%]", 0), ("within2s", "<2 sigma [%]", 0),
           ("within3s", "<3 sigma [%]", 0), ("cpu_ms", "CPU [ms]", 0)]


def mean_rows(per_scene: dict[str, dict[str, dict]]) -> dict[str, dict]:
    methods = next(iter(per_scene.values())).keys()
    return {m: {k: float(np.mean([s[m][k] for s in per_scene.values() if s[m].get(k) is not None]))
                for k, _, _ in COLUMNS if any(s[m].get(k) is not None for s in per_scene.values())}
            for m in methods}


def table(rows: dict[str, dict]) -> list[str]:
    fmt = lambda v, d: "-" if v is None else f"{v:.{d}f}"
    lines = ["| method | " + " | ".join(h for _, h, _ in COLUMNS) + " |", "|---" * (len(COLUMNS) + 1) + "|"]
    for m, r in rows.items():
        lines.append(f"| {m} | " + " | ".join(fmt(r.get(k), d) for k, _, d in COLUMNS) + " |")
    return lines


def markdown(report: dict) -> str:
    out = ["# Stereo on real photographs (`python -m tools eval stereo`)", "",
           f"Non-occluded pixels unless marked 'all'; errors in the ground truth's pixels. Laplacian expectation within "
           f"1/2/3 sigma: 63/86/95 %. SGBM sigma: constant {report['sgbm_sigma_px']:g} px. Scale: "
           + ", ".join(f"{n} x{s['scale']:.2f}" for n, s in report["scales"].items()) + ".", "",
           "## Mean over scenes", "", *table(report["mean"]), ""]
    for name, rows in report["scenes"].items():
        out += [f"## {name}", "", *table(rows), ""]
    eu = report.get("euroc")
    if eu:
        out += ["## Real EuRoC frames: agreement with SGBM where it matches", "",
                f"{eu['frames']} frames of {eu['dataset']}; SGBM matches {eu['sgbm_coverage']:.0f} % of the valid region.", "",
                "| network | mean abs(net - sgbm)/sigma | median abs(net - sgbm) [px] | <1 sigma [%] | <2 sigma [%] | <3 sigma [%] |",
                "|---|---|---|---|---|---|"]
        for label, r in eu.items():
            if isinstance(r, dict):
                out.append(f"| {label} | {r['diff_over_sigma']:.2f} | {r['median_diff_px']:.2f} | {r['within1s']:.0f} | "
                           f"{r['within2s']:.0f} | {r['within3s']:.0f} |")
    return "\n".join(out) + "\n"


def plot_scene(scene: StereoScene, r: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gt, mask = scene.disparity, scene.masks["nonocc"] & np.isfinite(scene.disparity)
    err = np.where(mask, np.abs(r["disp"] - gt), np.nan)
    vmax = float(np.nanmax(gt))
    panels = [("left", scene.left, "gray", None), ("ground truth [px]", gt, "viridis", vmax),
              ("network disparity [px]", r["disp"], "viridis", vmax), ("abs(error) [px], non-occluded", err, "magma", 4.0),
              ("sigma [px]", r["sigma"], "magma", 4.0), ("abs(error)/sigma", err / r["sigma"], "coolwarm", 4.0)]
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5))
    for ax, (title, img, cmap, vm) in zip(axes.ravel(), panels):
        im = ax.imshow(img, cmap=cmap, vmin=0, vmax=vm)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
        if vm is not None:
            fig.colorbar(im, ax=ax, fraction=0.04)
    fig.suptitle(f"{scene.name}: network EPE {np.nanmean(err):.2f} px")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------- command
def _default(arg, name: str) -> Path | None:
    from shared.paths import shared_dir

    if arg is not None:
        return None if arg == "none" else Path(arg)
    p = shared_dir() / "data" / "real" / name
    return p if p.is_dir() else None


def load_nets(paths: list[str]) -> list[tuple[str, object, float]]:
    from services.depth import weights

    paths = paths or [str(weights.WEIGHTS_DIR / weights.DEFAULT_STEREO)]
    nets = []
    for p in paths:
        net, meta = weights.load(p)
        if meta["arch"] == "mvs":
            raise weights.WeightsError(f"{p}: an MVS network; eval stereo needs stereo weights")
        label = "net" if len(paths) == 1 else f"net:{Path(p).stem}"
        nets.append((label, net, float(meta["gain"])))
    return nets


def main(args: argparse.Namespace) -> int:
    import torch

    from services.depth.config import DepthConfig
    from services.depth.weights import DEFAULT_STEREO, WeightsError
    from tools.depth.stereo_scene import StereoSceneError

    torch.set_num_threads(max(1, args.threads))
    scene_args = args.scenes or ([p] if (p := _default(None, DEFAULT_SCENES)) else [])
    if not scene_args:
        print(f"eval stereo: no scenes given and no $SIGMASLAM_SHARED/data/real/{DEFAULT_SCENES}")
        return 2
    try:
        dirs = find_scenes(scene_args)
        nets = load_nets(args.weights)
    except (StereoSceneError, WeightsError) as exc:
        print(f"eval stereo: {exc}")
        return 2
    sigma_sgbm = DepthConfig().heuristic_sigma_coeff
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {"scenes": {}, "scales": {}, "sgbm_sigma_px": sigma_sgbm, "precision": args.precision,
                    "weights": [str(p) for p in args.weights] or [f"services/depth/weights/{DEFAULT_STEREO}"]}
    for i, d in enumerate(dirs):
        try:
            scene = read_stereo_scene(d)
        except StereoSceneError as exc:
            print(f"eval stereo: skipping {d}: {exc}")
            continue
        results = run_methods(scene, nets, args.fit, sigma_sgbm, precision=args.precision)
        rows = scene_metrics(scene, results)
        report["scenes"][scene.name] = rows
        report["scales"][scene.name] = {"scale": results["sgbm"]["scale"], "max_disparity": scene.max_disparity}
        first = nets[0][0]
        print(f"[{i + 1}/{len(dirs)}] {scene.name}: " + ", ".join(
            f"{m} EPE {r.get('epe', float('nan')):.2f} bad-2 {r.get('bad2', float('nan')):.1f}%" for m, r in rows.items()),
              flush=True)
        if not args.no_plots:
            plot_scene(scene, results[first], out / f"{scene.name}.png")
    if not report["scenes"]:
        print("eval stereo: no readable scene")
        return 2
    report["mean"] = mean_rows(report["scenes"])
    euroc = _default(args.euroc, DEFAULT_EUROC)
    if euroc is not None:
        report["euroc"] = euroc_agreement(euroc, nets, args.euroc_frames, precision=args.precision)
    (out / "metrics.json").write_text(json.dumps(report, indent=1))
    md = markdown(report)
    (out / "table.md").write_text(md)
    print(md)
    print(f"eval stereo: wrote {out / 'table.md'}, {out / 'metrics.json'}")
    return 0
