"""``sigmaslam eval relocalise MAP_DATASET DATASET --out DIR``: map one sequence, then localise another in that map.

Both runs are the pipeline's nodes in one process, in lockstep (services/app/inprocess.py, ``loop.synchronous``), so
the figures are reproducible. The first run writes its saved map (``DIR/a/map/``); the second starts with it
(``loop.prior_map``) and writes the extended map (``DIR/b/map/``). For the second run it reports

- the share of its frames whose state is in the map's frame (the rest were published in the temporary frame
  before the relocalisation), and the sensor time from its first state to the first one in the map's frame;
- its ATE in the map's frame with no alignment of its own: the first run's SE(3) alignment to the first sequence's
  ground truth applied to the second run's poses (both replicas share one world frame when rendered in the same
  scene); causal (the published states) and non-causal (the final bundle adjustment, anchored to the map);
- for comparison, the same poses with their own SE(3) alignment (how good the odometry is, whatever the frame).

Writes DIR/relocalise.json and prints a markdown table. Both datasets need ground truth.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from shared.map_folder import UNALIGNED_FRAME


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("map_dataset", help="EuRoC folder (replica) mapped first")
    p.add_argument("dataset", help="EuRoC folder (replica of the same scene) localised in the first one's map")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--max-frames-a", type=int, default=0, help="frames of the first run (0: all)")
    p.add_argument("--max-frames-b", type=int, default=0, help="frames of the second run (0: all)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override, both runs")


def _errors(gt, stamps: np.ndarray, p: np.ndarray) -> np.ndarray:
    from shared.metrics.ate import associate

    ia, ib = associate(gt.stamps_ns, stamps, 10_000_000)
    return np.linalg.norm(gt.p_WS[ia] - p[ib], axis=1)


def _rmse(e: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(e ** 2))) if len(e) else None


def evaluate(map_dataset: str, dataset: str, out: Path, max_a: int = 0, max_b: int = 0, sets=()) -> dict:
    from services.app.inprocess import run_in_process
    from services.app.system_config import load_system_config
    from shared.euroc import read_trajectory
    from shared.metrics.ate import compute_ate

    def run(ds: str, folder: Path, frames: int, extra: list[str]):
        cfg = load_system_config(None, ["loop.synchronous=true", f"loop.map_output={folder}", *extra, *sets])
        t0 = time.perf_counter()
        r = run_in_process(ds, cfg, max_frames=frames)
        print(f"[eval relocalise] {ds}: {r.frames} frames in {time.perf_counter() - t0:.0f} s", flush=True)
        if r.groundtruth_path is None:
            raise SystemExit(f"{ds}: no ground truth")
        return r

    ra = run(map_dataset, out / "a", max_a, [])
    gt_a = read_trajectory(ra.groundtruth_path)
    sa = [s for s in ra.states if s.status not in ("initialising", "reset")]
    res_a = compute_ate(gt_a.stamps_ns, gt_a.p_WS, np.array([s.header.stamp_ns for s in sa]),
                        np.array([s.T_WS[:3, 3] for s in sa]))
    al = res_a.alignment  # the only alignment to ground truth the second run gets
    rb = run(dataset, out / "b", max_b, [f"loop.prior_map={out / 'a'}"])
    gt_b = read_trajectory(rb.groundtruth_path)
    posed = [s for s in rb.states if s.status not in ("initialising", "reset")]
    in_map = [s for s in posed if s.header.frame_id != UNALIGNED_FRAME]
    first = int(rb.states[0].header.stamp_ns)
    st = np.array([s.header.stamp_ns for s in in_map], np.int64)
    p = np.array([s.T_WS[:3, 3] for s in in_map]).reshape(-1, 3)
    e_causal = _errors(gt_b, st, al.apply(p)) if len(st) else np.zeros(0)
    own = compute_ate(gt_b.stamps_ns, gt_b.p_WS, st, p).rmse_m if len(st) > 10 else None
    e_final = np.zeros(0)
    if rb.final is not None and rb.final.header.frame_id != UNALIGNED_FRAME:
        e_final = _errors(gt_b, np.asarray(rb.final.stamps_ns), al.apply(np.asarray(rb.final.T_WS)[:, :3, 3]))
    loop = rb.nodes["backend"].loop_closure
    rep = {"map_dataset": map_dataset, "dataset": dataset,
           "map_run": {"frames": ra.frames, "causal_ate_se3_m": res_a.rmse_m,
                       "keyframes": len(loop.runner.closer.prior) if loop.runner.closer.prior is not None else None},
           "frames": rb.frames, "states_in_map_frame": len(in_map), "states_before_relocalisation": len(posed) - len(in_map),
           "localised_fraction": len(in_map) / max(rb.frames, 1),
           "time_to_relocalise_s": (int(in_map[0].header.stamp_ns) - first) * 1e-9 if in_map else None,
           "ate_map_frame_causal_m": _rmse(e_causal), "ate_map_frame_causal_max_m": float(e_causal.max()) if len(e_causal) else None,
           "ate_map_frame_final_m": _rmse(e_final), "ate_own_alignment_causal_m": own,
           "loop_counts": dict(loop.counts)}
    out.mkdir(parents=True, exist_ok=True)
    (out / "relocalise.json").write_text(json.dumps(rep, indent=1))
    return rep


def table(rep: dict) -> str:
    f = lambda v, d=3: "-" if v is None else f"{v:.{d}f}"
    return "\n".join([
        "| map run: frames, causal ATE | localised run: frames | in the map's frame | time to relocalise [s] | "
        "ATE in the map's frame, causal / final [m] (first run's alignment only) | own SE(3) alignment, causal [m] |",
        "|---|---|---|---|---|---|",
        f"| {rep['map_run']['frames']}, {f(rep['map_run']['causal_ate_se3_m'])} m | {rep['frames']} | "
        f"{100 * rep['localised_fraction']:.1f} % | {f(rep['time_to_relocalise_s'], 1)} | "
        f"{f(rep['ate_map_frame_causal_m'])} / {f(rep['ate_map_frame_final_m'])} (max {f(rep['ate_map_frame_causal_max_m'])}) | "
        f"{f(rep['ate_own_alignment_causal_m'])} |"])


def main(args: argparse.Namespace) -> int:
    rep = evaluate(args.map_dataset, args.dataset, Path(args.out), args.max_frames_a, args.max_frames_b, args.set)
    print(table(rep), flush=True)
    return 0 if rep["time_to_relocalise_s"] is not None else 1
