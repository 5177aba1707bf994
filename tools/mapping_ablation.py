"""``python -m tools bench mapping-ablation --replica DIR``: the paper's Table IV style ablation of what the map
gets as depth and sigma, all at ground-truth poses on a replica:

- ``gt``: ground-truth depth (cam0, undistorted) with the heuristic quadratic sigma;
- ``stereo-heuristic``: stereo depth with the heuristic sigma (supereight2's model);
- ``stereo-learned``: stereo depth with its learned sigma;
- ``fused``: stereo + MVS fused by inverse variance (eq. 14) with the fused sigma.

The depth comes from :class:`services.depth.pipeline.DepthPipeline` (networks when their weights are
present, else SGBM, in which case only the heuristic variants are meaningful). Each variant is
meshed and evaluated against the replica's scene mesh (services/app/metrics/mesh.py): the mesh as the mapping service
writes it (faces the map is unsure of left out: ``mapping.submaps.mesh_max_sigma_m``) and, in the same run, every
face ("(all faces)").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from services.mapping.io import write_ply
from services.mapping.submaps import SubmapMapper

VARIANTS = ("gt", "stereo-heuristic", "stereo-learned", "fused")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--replica", required=True, metavar="DIR", help="replica folder (sigmaslam synth)")
    p.add_argument("--frames", type=int, default=0, help="depth frames to use (0 = all)")
    p.add_argument("--stride", type=int, default=2, help="every n-th camera frame (20 Hz -> 10 Hz)")
    p.add_argument("--keyframe-every", type=int, default=3, help="every n-th used frame becomes an MVS keyframe")
    p.add_argument("--sigma-k", type=float, default=0.005, help="heuristic sigma = k * depth^2 [1/m]")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="depth.*, mapping.sensor.* or mapping.submaps.* override, e.g. depth.stereo_weights=stereo.pt "
                        "or mapping.submaps.mesh_max_sigma_m=0 (every face)")
    p.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated subset of " + ", ".join(VARIANTS))
    p.add_argument("--out", required=True, metavar="DIR", help="per-variant mesh.ply and the summary ablation.json")


def _images(mav: Path, cam: str) -> dict[int, Path]:
    rows = [ln.split(",") for ln in (mav / cam / "data.csv").read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    return {int(r[0]): mav / cam / "data" / r[1].strip() for r in rows}


READ_KEYS = ("depth.", "mapping.sensor.", "mapping.submaps.")


def system_config(overrides: list[str]):
    """The system config with ``depth.*``, ``mapping.sensor.*`` and ``mapping.submaps.*`` overrides, as
    ``sigmaslam run`` applies them (ConfigError for other keys: nothing else here reads them)."""
    from services.app.system_config import load_system_config
    from shared.config import ConfigError

    other = [o for o in overrides if not o.strip().startswith(READ_KEYS)]
    if other:
        raise ConfigError(f"only {', '.join(k + '*' for k in READ_KEYS)} keys can be set here, got {other}")
    return load_system_config(None, overrides)


def main(args: argparse.Namespace) -> int:
    import cv2

    from services.depth.pipeline import DepthPipeline
    from shared.camera import load_rig
    from tools.bench_mapping import replica_frames
    from services.app.metrics.mesh import evaluate_mesh_files

    folder, out = Path(args.replica), Path(args.out)
    variants = [v for v in args.variants.split(",") if v]
    unknown = set(variants) - set(VARIANTS)
    if unknown:
        print(f"unknown variants {sorted(unknown)}; known: {', '.join(VARIANTS)}")
        return 2
    mav = folder / "mav0"
    rig = {c.name: c for c in load_rig(mav)}
    cfg = system_config(args.set)
    pipe = DepthPipeline(cfg.depth, rig["cam0"], rig["cam1"])
    left, right = _images(mav, "cam0"), _images(mav, "cam1")
    sensor, submaps = cfg.mapping.sensor, cfg.mapping.submaps
    heuristic = dataclasses.replace(sensor, sigma_model="quadratic", k_sigma=args.sigma_k)
    mappers = {v: SubmapMapper(heuristic if v in ("gt", "stereo-heuristic") else sensor, submaps) for v in variants}
    kf_stamps: list[int] = []
    kf_T: list[np.ndarray] = []
    for i, (stamp, d_gt, K_gt, T_WC_gt) in enumerate(replica_frames(folder, args.frames, args.stride)):
        T_WS = T_WC_gt @ np.linalg.inv(rig["cam0"].T_SC)
        if "gt" in mappers:
            mappers["gt"].integrate(d_gt, None, K_gt, T_WC_gt, rig["cam0"].T_SC, stamp)
        if len(mappers) == ("gt" in mappers):
            continue
        if stamp not in left or stamp not in right:
            continue
        raw_l = cv2.imread(str(left[stamp]), cv2.IMREAD_GRAYSCALE)
        raw_r = cv2.imread(str(right[stamp]), cv2.IMREAD_GRAYSCALE)
        pipe.remember_frame(stamp, raw_l)
        res = pipe.process(stamp, raw_l, raw_r, T_WS)
        T_WC = T_WS @ pipe.T_SC
        for name, (d, s) in (("stereo-heuristic", res.stereo), ("stereo-learned", res.stereo), ("fused", res.fused)):
            if name in mappers:
                mappers[name].integrate(d, s, pipe.K, T_WC, pipe.T_SC, stamp, res.surface_max_relative_sigma)
        if i % args.keyframe_every == 0:
            kf_stamps.append(stamp)
            kf_T.append(T_WS)
            pipe.update_keyframes(np.array(kf_stamps), np.array(kf_T))
    summary = {"depth_method": pipe.method, "depth_set": list(args.set), "variants": {},
               "uncertain_fraction": pipe.uncertain_px / max(1, pipe.uncertain_px + pipe.confident_px)}
    gt_mesh = mav / "scene" / "mesh.ply"
    for name, mapper in mappers.items():
        mapper.remesh()
        # the mesh as configured and, where the confident mesh leaves faces out, the whole mesh (same depth)
        for label, limit in ((name, submaps.mesh_max_sigma_m), (f"{name} (all faces)", 0.0)):
            if label != name and submaps.mesh_max_sigma_m <= 0:
                continue
            mapper.cfg = dataclasses.replace(submaps, mesh_max_sigma_m=limit)
            v, f = mapper.world_mesh()
            d = out / (name if label == name else f"{name}-all-faces")
            write_ply(d / "mesh.ply", v, f)
            res = evaluate_mesh_files(d / "mesh.ply", gt_mesh, out_dir=d)
            summary["variants"][label] = {"accuracy_m": res.accuracy_m, "completeness": res.completeness,
                                          "completeness_5cm": res.completeness_5cm, "submaps": len(mapper.submaps),
                                          "map_MB": mapper.nbytes() / 2**20, "mesh_max_sigma_m": limit}
            print(f"{label:17s} accuracy {res.accuracy_m:.4f} m  completeness {100 * res.completeness:.1f} % @ 0.2 m, "
                  f"{100 * res.completeness_5cm:.1f} % @ 0.05 m  ({len(mapper.submaps)} submaps, "
                  f"{mapper.nbytes() / 2**20:.1f} MiB)", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / "ablation.json").write_text(json.dumps(summary, indent=1))
    return 0
