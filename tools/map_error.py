"""Where the map's error comes from, at ground-truth poses on a replica (issue 56, item 1).

``python -m tools.map_error --replica DIR --out DIR [--frames N] [--set depth.KEY=VALUE ...]``

1. **Depth, frame by frame.** The depth service's pipeline (services/depth/pipeline.py) runs on the replica's stereo
   frames at ground-truth poses (MVS keyframes at ground-truth poses too); the ground-truth depth of the same
   rectified camera is ray-cast from the replica's scene mesh. Per pixel ``e = d_net - d_gt``, reported by
   ground-truth depth range, by decile of the predicted sigma, near depth edges (pixels within ``--edge-px`` of a
   ground-truth discontinuity: flying pixels between foreground and background) against surfaces: pixel share,
   mean |e|, median e (bias), a robust spread (1.4826 MAD), the share beyond 3 sigma, mean |e| / sigma.
2. **What survives integration.** The same frames integrated into the mapper (services/mapping/submaps.py) in
   variants that each remove one error source with the ground truth's help (an oracle: what the map would gain if
   that source were gone), and variants that take the ground truth's depth with the network's noise: mesh accuracy
   and completeness of each (services/app/metrics/mesh.py), with the share of the accuracy that comes from mesh
   vertices more than 5 / 10 / 20 cm off, and an error-coloured top view per variant.

Every frame's depth, sigma and ground-truth depth are cached in ``OUT/frames/`` (float16), so variants rerun
without the networks (``--reuse``). The depth is the service's, with its filters as configured: ``--set
depth.flying_radius_px=0`` keeps the flying pixels, whose removal the variant ``net-flying`` then measures. Writes ``OUT/map_error.json`` and ``OUT/map_error.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

RANGES_M = (0.0, 1.0, 2.0, 3.0, 4.0, 6.0, np.inf)
EUROC_BASELINE_M = 0.11  # frames cached before the baseline was stored: the EuRoC rig's


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--replica", required=True, metavar="DIR", help="replica folder (sigmaslam synth)")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--frames", type=int, default=0, help="depth frames (0 = all)")
    p.add_argument("--stride", type=int, default=2, help="every n-th camera frame (20 Hz -> 10 Hz)")
    p.add_argument("--keyframe-every", type=int, default=3, help="every n-th used frame becomes an MVS keyframe")
    p.add_argument("--source", choices=("stereo", "fused"), default="stereo", help="the depth the variants integrate")
    p.add_argument("--edge-px", type=int, default=2, help="pixels this close to a ground-truth depth edge are 'edge'")
    p.add_argument("--variants", default="", help="comma-separated subset of the map variants (default: all)")
    p.add_argument("--reuse", action="store_true", help="use the frames cached in OUT/frames/ (no networks)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="depth.*, mapping.sensor.* or mapping.submaps.* override (the mapping keys reach every variant)")


# ----------------------------------------------------------------------------- ground truth in the depth camera
class GroundTruthDepth:
    """Depth along the optical axis [m] of a pinhole camera (K, size) ray-cast from a triangle mesh."""

    def __init__(self, mesh_path: Path, K: np.ndarray, size: tuple[int, int]) -> None:
        import open3d as o3d

        from services.app.synth.scene import read_ply

        v, f = read_ply(mesh_path)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
        w, h = size
        u, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        self.rays_C = np.stack([(u - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
        self.shape = (h, w)

    def depth(self, T_WC: np.ndarray) -> np.ndarray:
        import open3d as o3d

        d_W = self.rays_C @ T_WC[:3, :3].T
        rays = np.concatenate([np.broadcast_to(T_WC[:3, 3], d_W.shape), d_W], 1).astype(np.float32)
        t = self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()  # along z = 1 rays: the depth
        return np.where(np.isfinite(t), t, np.nan).astype(np.float32).reshape(self.shape)


def depth_edges(d_gt: np.ndarray, radius_px: int, rel_jump: float = 0.05) -> np.ndarray:
    """Pixels within ``radius_px`` of a ground-truth depth discontinuity (neighbours differing by more than
    ``rel_jump`` of the nearer depth)."""
    import cv2

    d = np.nan_to_num(d_gt, nan=0.0)
    jump = np.zeros(d.shape, bool)
    for a, b, sl_a, sl_b in ((d[:, 1:], d[:, :-1], np.s_[:, 1:], np.s_[:, :-1]),
                             (d[1:, :], d[:-1, :], np.s_[1:, :], np.s_[:-1, :])):
        j = np.abs(a - b) > rel_jump * np.maximum(np.minimum(a, b), 1e-3)
        jump[sl_a] |= j
        jump[sl_b] |= j
    k = 2 * radius_px + 1
    return cv2.dilate(jump.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)


# ----------------------------------------------------------------------------- frames
def compute_frames(args: argparse.Namespace, out: Path) -> list[Path]:
    """Run the depth pipeline at ground-truth poses and cache depth, sigma and ground truth per frame."""
    import cv2

    from services.depth.pipeline import DepthPipeline
    from shared.camera import load_rig
    from tools.bench_mapping import replica_frames
    from tools.mapping_ablation import _images, system_config

    folder = Path(args.replica)
    mav = folder / "mav0"
    rig = {c.name: c for c in load_rig(mav)}
    pipe = DepthPipeline(system_config(args.set).depth, rig["cam0"], rig["cam1"])
    gt = GroundTruthDepth(mav / "scene" / "mesh.ply", pipe.K, (pipe.cfg.width, pipe.cfg.height))
    left, right = _images(mav, "cam0"), _images(mav, "cam1")
    frames_dir = out / "frames"
    frames_dir.mkdir(parents=True, exist_ok=True)
    paths, kf_stamps, kf_T, t0 = [], [], [], time.monotonic()
    for i, (stamp, _, _, T_WC_gt) in enumerate(replica_frames(folder, args.frames, args.stride)):
        if stamp not in left or stamp not in right:
            continue
        T_WS = T_WC_gt @ np.linalg.inv(rig["cam0"].T_SC)
        raw_l = cv2.imread(str(left[stamp]), cv2.IMREAD_GRAYSCALE)
        raw_r = cv2.imread(str(right[stamp]), cv2.IMREAD_GRAYSCALE)
        pipe.remember_frame(stamp, raw_l)
        res = pipe.process(stamp, raw_l, raw_r, T_WS)
        T_WC = T_WS @ pipe.T_SC
        arrays = {"d_gt": gt.depth(T_WC), "T_WC": T_WC, "K": pipe.K, "T_SC": pipe.T_SC, "stamp": np.int64(stamp),
                  "baseline_m": np.float64(pipe.baseline_m),
                  "surface_max_relative_sigma": np.float64(res.surface_max_relative_sigma)}
        for name, ds in (("stereo", res.stereo), ("fused", res.fused)):
            if ds is not None:
                arrays[f"d_{name}"], arrays[f"s_{name}"] = ds
        path = frames_dir / f"{stamp}.npz"
        np.savez(path, **{k: (v.astype(np.float16) if k[:2] in ("d_", "s_") and k != "d_gt" else v)
                          for k, v in arrays.items()})
        paths.append(path)
        if i % args.keyframe_every == 0:
            kf_stamps.append(stamp)
            kf_T.append(T_WS)
            pipe.update_keyframes(np.array(kf_stamps), np.array(kf_T))
        if len(paths) % 25 == 0:
            print(f"[map_error] {len(paths)} frames ({time.monotonic() - t0:.0f} s)", flush=True)
    return paths


def load_frame(path: Path, source: str) -> dict:
    with np.load(path) as z:
        f = {k: z[k] for k in z.files}
    f["d"] = f[f"d_{source}"].astype(np.float32)
    f["s"] = f[f"s_{source}"].astype(np.float32)
    f["d_gt"] = f["d_gt"].astype(np.float32)
    return f


# ----------------------------------------------------------------------------- frame statistics
def _stats(e: np.ndarray, s: np.ndarray, n_all: int) -> dict:
    if len(e) == 0:
        return {"share": 0.0, "n": 0}
    med = float(np.median(e))
    return {"share": len(e) / max(n_all, 1), "n": int(len(e)), "mean_abs_m": float(np.mean(np.abs(e))),
            "median_m": med, "spread_m": float(1.4826 * np.median(np.abs(e - med))),
            "beyond_3_sigma": float(np.mean(np.abs(e) > 3 * s)), "mean_abs_over_sigma": float(np.mean(np.abs(e) / s)),
            "beyond_10cm": float(np.mean(np.abs(e) > 0.1))}


def frame_statistics(paths: list[Path], source: str, edge_px: int, max_depth_m: float) -> dict:
    """Pixel errors of every cached frame by range, sigma decile and edge/surface."""
    E, S, D, EDGE = [], [], [], []
    for p in paths:
        f = load_frame(p, source)
        ok = np.isfinite(f["d"]) & np.isfinite(f["s"]) & np.isfinite(f["d_gt"]) & (f["d"] <= max_depth_m)
        edge = depth_edges(f["d_gt"], edge_px)
        E.append((f["d"] - f["d_gt"])[ok])
        S.append(f["s"][ok])
        D.append(f["d_gt"][ok])
        EDGE.append(edge[ok])
    e, s, d, edge = (np.concatenate(a) for a in (E, S, D, EDGE))
    n = len(e)
    out = {"pixels": n, "all": _stats(e, s, n),
           "by_range_m": {f"{lo:g}-{hi:g}": _stats(e[(d >= lo) & (d < hi)], s[(d >= lo) & (d < hi)], n)
                          for lo, hi in zip(RANGES_M[:-1], RANGES_M[1:])},
           "edge": _stats(e[edge], s[edge], n), "surface": _stats(e[~edge], s[~edge], n)}
    q = np.quantile(s, np.linspace(0, 1, 11))
    out["by_sigma_decile"] = {}
    for k in range(10):
        sel = (s >= q[k]) & (s <= q[k + 1] if k == 9 else s < q[k + 1])
        out["by_sigma_decile"][f"{k + 1}: {q[k]:.3f}-{q[k + 1]:.3f} m"] = _stats(e[sel], s[sel], n)
    # the total error mass: where the sum of |e| lives
    tot = float(np.abs(e).sum())
    out["abs_error_mass"] = {"edge": float(np.abs(e[edge]).sum()) / tot,
                             **{f"range {lo:g}-{hi:g} m": float(np.abs(e[(d >= lo) & (d < hi)]).sum()) / tot
                                for lo, hi in zip(RANGES_M[:-1], RANGES_M[1:])},
                             "beyond 3 sigma": float(np.abs(e[np.abs(e) > 3 * s]).sum()) / tot}
    return out


# ----------------------------------------------------------------------------- map variants
def _variant_frame(name: str, f: dict, edge_px: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray | None]:
    """(depth, sigma) a map variant integrates for one cached frame (sigma None: the heuristic model's)."""
    d, s, g = f["d"], f["s"], f["d_gt"]
    nan = np.float32(np.nan)
    with np.errstate(invalid="ignore"):
        if name == "gt-heuristic":
            return g, None
        if name == "gt-net-sigma":
            return np.where(np.isfinite(d), g, nan), s
        if name == "gt-net-noise":  # the ground truth with Gaussian noise of the predicted sigma
            return np.where(np.isfinite(d), g + rng.standard_normal(g.shape).astype(np.float32) * s, nan), s
        if name == "net":
            return d, s
        if name == "net-no-edges":
            edge = depth_edges(g, edge_px)
            return np.where(edge, nan, d), s
        if name == "net-inliers":  # pixels off by more than 3 of their own sigma removed
            bad = ~(np.abs(d - g) <= 3 * s)
            return np.where(bad, nan, d), s
        if name == "net-within-3m":
            return np.where(d <= 3.0, d, nan), s
        if name == "net-edge-filter":  # realisable: edges of the predicted depth, not of the ground truth
            return np.where(depth_edges(d, 1), nan, d), s
        if name == "net-flying":  # realisable: the depth service's own filter (depth.flying_*), with its defaults
            from services.depth.config import DepthConfig
            from services.depth.flying import flying_pixels

            c = DepthConfig()
            fly = flying_pixels(d, float(f["K"][0, 0]) * float(f.get("baseline_m", EUROC_BASELINE_M)),
                                c.flying_radius_px, c.flying_rel_jump, c.flying_min_gradient, c.flying_margin)
            return np.where(fly, nan, d), s
    raise KeyError(name)


VARIANTS = ("gt-heuristic", "gt-net-sigma", "gt-net-noise", "net", "net-no-edges", "net-inliers", "net-within-3m",
            "net-edge-filter", "net-flying")


def run_variant(name: str, paths: list[Path], source: str, edge_px: int, replica: Path, out: Path,
                overrides: tuple[str, ...] = ()) -> dict:
    from services.app.metrics.mesh import evaluate_mesh_files, load_ground_truth
    from services.mapping.io import write_ply
    from services.mapping.submaps import SubmapMapper
    from tools.mapping_ablation import system_config

    mapping = system_config(list(overrides)).mapping
    heuristic = dataclasses.replace(mapping.sensor, sigma_model="quadratic", k_sigma=0.005)
    mapper = SubmapMapper(heuristic if name == "gt-heuristic" else mapping.sensor, mapping.submaps)
    rng = np.random.default_rng(0)
    for p in paths:
        f = load_frame(p, source)
        d, s = _variant_frame(name, f, edge_px, rng)
        mapper.integrate(d, s, f["K"], f["T_WC"], f["T_SC"], int(f["stamp"]), float(f.get("surface_max_relative_sigma", 0.0)))
    mapper.remesh()
    v, tri = mapper.world_mesh()
    d_out = out / "variants" / name
    write_ply(d_out / "mesh.ply", v, tri)
    gt_mesh = replica / "mav0" / "scene" / "mesh.ply"
    res = evaluate_mesh_files(d_out / "mesh.ply", gt_mesh, out_dir=d_out)
    # the share of the accuracy (mean distance) from vertices far off, after the evaluation's ICP
    gt = load_ground_truth(gt_mesh)
    T = res.T_gt_est
    dist = gt.distances(np.asarray(v) @ T[:3, :3].T + T[:3, 3]) if len(v) else np.zeros(0)
    tail = {f"> {c} cm": float(dist[dist > c / 100].sum() / max(dist.sum(), 1e-12)) for c in (5, 10, 20)}
    return {"accuracy_m": res.accuracy_m, "completeness": res.completeness, "completeness_5cm": res.completeness_5cm,
            "vertex_error_mean_m": float(dist.mean()) if len(dist) else None, "vertex_error_share": tail,
            "vertices": int(len(v))}


# ----------------------------------------------------------------------------- report
def report(summary: dict) -> str:
    fs = summary["frames"]
    f = lambda x, d=3: "-" if x is None else f"{x:.{d}f}"  # noqa: E731
    row = lambda name, st: (f"| {name} | {100 * st['share']:.1f} % | {f(st.get('mean_abs_m'))} | "  # noqa: E731
                            f"{f(st.get('median_m'))} | {f(st.get('spread_m'))} | "
                            f"{100 * st.get('beyond_3_sigma', 0):.1f} % | {f(st.get('mean_abs_over_sigma'), 2)} |")
    head = ["| pixels | share | mean abs(e) [m] | median e (bias) [m] | spread (1.48 MAD) [m] | beyond 3 sigma | "
            "mean abs(e)/sigma |", "|---|---|---|---|---|---|---|"]
    lines = [f"# Map error decomposition: {summary['replica']} ({summary['source']} depth, {summary['n_frames']} frames)",
             "", "## Depth, per pixel, at ground-truth poses", "", *head, row("all", fs["all"]),
             row("near depth edges", fs["edge"]), row("surfaces", fs["surface"])]
    lines += [row(f"ground truth {k} m", v) for k, v in fs["by_range_m"].items()]
    lines += [row(f"sigma decile {k}", v) for k, v in fs["by_sigma_decile"].items()]
    lines += ["", "Share of the summed abs(e): " + ", ".join(f"{k} {100 * v:.0f} %"
                                                            for k, v in fs["abs_error_mass"].items()), ""]
    lines += ["## The map, by variant (mesh accuracy against the scene mesh)", "",
              "| variant | accuracy [m] | completeness @ 0.2 m / 5 cm | share of the mean from vertices > 5 / 10 / 20 cm |",
              "|---|---|---|---|"]
    for name, r in summary["variants"].items():
        t = r["vertex_error_share"]
        lines.append(f"| {name} | {r['accuracy_m']:.4f} | {100 * r['completeness']:.1f} % / "
                     f"{100 * r['completeness_5cm']:.1f} % | {100 * t['> 5 cm']:.0f} / {100 * t['> 10 cm']:.0f} / "
                     f"{100 * t['> 20 cm']:.0f} % |")
    return "\n".join(lines) + "\n"


def main(args: argparse.Namespace) -> int:
    from services.mapping.config import SensorModelConfig

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    paths = sorted((out / "frames").glob("*.npz")) if args.reuse else compute_frames(args, out)
    if not paths:
        print(f"[map_error] no frames ({out / 'frames'} is empty: run without --reuse)")
        return 1
    summary = {"replica": str(args.replica), "source": args.source, "n_frames": len(paths), "depth_set": args.set,
               "frames": frame_statistics(paths, args.source, args.edge_px, SensorModelConfig().max_depth_m),
               "variants": {}}
    names = [v for v in args.variants.split(",") if v] or list(VARIANTS)
    for name in names:
        t0 = time.monotonic()
        summary["variants"][name] = run_variant(name, paths, args.source, args.edge_px, Path(args.replica), out,
                                                 tuple(args.set))
        r = summary["variants"][name]
        print(f"[map_error] {name:16s} accuracy {r['accuracy_m']:.4f} m completeness {100 * r['completeness']:.1f} % "
              f"({time.monotonic() - t0:.0f} s)", flush=True)
    (out / "map_error.json").write_text(json.dumps(summary, indent=1))
    text = report(summary)
    (out / "map_error.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(p)
    raise SystemExit(main(p.parse_args()))
