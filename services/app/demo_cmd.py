"""``sigmaslam demo``: the README's main job, the whole pipeline on the bundled synthetic sequence.

1. Generates (once; cached under ``data/replicas/``) the default replica: 25 s of EuRoC V1_02 rendered in the
   'vicon-a' scene with the real IMU, exact ground-truth trajectory and scene mesh.
2. Runs ``sigmaslam run`` on it with ``configs/demo.yaml``: router, player at sensor rate (``--lockstep``: the
   player waits for each frame's state), frontend, per-frame fast path, back end (with loop closure and final
   bundle adjustment), depth, mapping and the web viewer, each its own process over Zenoh.
3. Evaluates what came out against the ground truth and prints one summary: causal and non-causal ATE,
   mesh accuracy and completeness, the occupancy map's false free and free recall (voxels and 2D grid) and a planned
   path on the grid checked against the scene (``sigmaslam eval occupancy``, services/app/planner.py), frames without a state, pose latency, queue drops, per-frame estimator
   time, the viewer's address, and the wall time of each
   phase (set-up when ``make demo`` passes ``--setup-s``, replica, run, evaluation; also ``DIR/phases.json``).

``--serve-s S`` keeps the viewer up for S seconds after the run, showing the final map and trajectories.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from shared.paths import REPO_ROOT

DEMO_CONFIG = REPO_ROOT / "configs" / "demo.yaml"
# the queues whose drops are camera frames the estimator never answered (frontend input, fast-path input)
ESTIMATOR_QUEUES = ("frontend:sensors/frame",)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="out/demo", metavar="DIR", help="run folder (default: out/demo)")
    p.add_argument("--config", default=str(DEMO_CONFIG), help="system config of the run (default: configs/demo.yaml)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    p.add_argument("--max-frames", type=int, default=0, help="play only this many camera frames (0: all)")
    p.add_argument("--lockstep", action="store_true", help="the player waits for each frame's state instead of playing "
                   "at sensor rate (reproducible figures; the default is live, as on a robot)")
    p.add_argument("--realtime", action="store_true", help=argparse.SUPPRESS)  # the default since stop 26
    p.add_argument("--serve-s", type=float, default=0.0,
                   help="after the run, keep the viewer up this long with the final map [s] (0: stop with the run)")
    p.add_argument("--setup-s", type=float, default=None,
                   help="seconds the set-up before this command took, to print among the phases (`make demo` passes it)")


def _run_pipeline(dataset: Path, args: argparse.Namespace) -> int:
    """The pipeline on the replica, as ``sigmaslam run`` runs it (which finds its ground truth, overlays it in the
    viewer and prints the viewer's address); returns its exit status."""
    from services.app.run_outputs import find_ground_truth
    from services.app.run_pipeline import run_pipeline

    return run_pipeline(dataset, args.out, args.config, args.set, rate=0.0 if args.lockstep else 1.0,
                        max_frames=args.max_frames, gt=find_ground_truth(dataset)).rc


def _say(msg: str) -> None:
    print(f"[sigmaslam demo] {msg}", flush=True)


def _mesh_figures(out: Path, dataset: Path) -> dict | None:
    from shared.metrics.ate import run_alignment
    from services.app.metrics.mesh import evaluate_mesh_files

    est = out / "mesh.ply"
    gt = dataset / "mav0" / "scene" / "mesh.ply"
    if not est.is_file() or not gt.is_file():
        print(f"[sigmaslam demo] no mesh evaluation ({est if not est.is_file() else gt} missing)", flush=True)
        return None
    T0 = None
    # the run's world frame into the ground truth's, by the SE(3) alignment of the trajectory that placed the map:
    # the final one when the mapping moved its submaps onto it (mapping.follow_final), else the causal one
    try:
        counts = json.loads((out / "mapping.json").read_text()).get("counts", {})
    except (OSError, ValueError):
        counts = {}
    final = bool(counts.get("final_trajectories", 0)) and (out / "trajectory_final.txt").is_file()
    try:
        T0 = run_alignment(out / ("trajectory_final.txt" if final else "trajectory_causal.txt"),
                           dataset / "mav0" / "state_groundtruth_estimate0" / "data.csv")
    except (ValueError, OSError) as exc:
        print(f"[sigmaslam demo] mesh evaluated without trajectory alignment ({exc})", flush=True)
    # ground truth sampled at the 1 cm evaluation resolution (the protocol downsamples to 1 cm anyway); prepared
    # once per scene and cached
    t0 = time.monotonic()
    res = evaluate_mesh_files(est, gt, gt_sample_spacing_m=0.01, out_dir=out / "mesh_eval", T_gt_est_init=T0,
                              progress=lambda m: _say(f"mesh evaluation {time.monotonic() - t0:5.1f} s: {m}"))
    return res.summary() | {"map_placed_by": "final" if final else "causal"}


def _occupancy_figures(out: Path, dataset: Path) -> dict | None:
    """The occupancy map's safety figures (``sigmaslam eval occupancy``) and the planner on the run's grid
    (services/app/planner.py), each None when it cannot be computed."""
    from services.app.eval.occupancy_cmd import evaluate_run
    from services.app.planner import plan_run

    figures: dict = {"eval": None, "plan": None}
    try:
        figures["eval"] = evaluate_run(out, dataset)
        (out / "occupancy_eval.json").write_text(json.dumps(figures["eval"], indent=1))
    except (OSError, ValueError) as exc:
        _say(f"no occupancy evaluation: {exc}")
    try:
        figures["plan"] = plan_run(out, dataset)
    except (OSError, ValueError) as exc:
        _say(f"no planner run: {exc}")
    return figures


def occupancy_lines(figures: dict | None) -> list[str]:
    from services.app.eval.occupancy_cmd import summary_lines as eval_lines

    if not figures:
        return []
    lines = eval_lines(figures["eval"]) if figures.get("eval") else []
    p = figures.get("plan")
    if p is not None:
        if p["found"]:
            check = ("" if p["clearance_m"] is None else
                     f", clearance to the scene {p['clearance_m']:.3f} m: "
                     + ("collision-free" if p["collision_free"] else "COLLIDES"))
            far = p.get("farthest_straight_m", p["straight_m"])
            note = ("" if p["straight_m"] >= far - 1e-6 else
                    f" (the poses farthest apart, {far:.2f} m, are not connected through free cells)")
            lines.append(f"planner (A*, radius {p['radius_m']} m)          path {p['length_m']:.2f} m between two "
                         f"trajectory poses {p['straight_m']:.2f} m apart{check}{note}")
        else:
            lines.append(f"planner (A*, radius {p['radius_m']} m)          no path: {p['reason']}")
    return lines


def phase_line(phases: dict[str, float]) -> str:
    """One line of the demo's phases and their wall times, e.g. ``set-up 52 s, replica 0 s (cached), ...``."""
    parts = [f"{name} {sec:.0f} s" for name, sec in phases.items()]
    return ", ".join(parts) + f"; total {sum(phases.values()) / 60:.1f} min"


def summary_lines(out: Path, mesh: dict | None, viewer_url: str, phases: dict[str, float] | None = None,
                  occupancy: dict | None = None) -> list[str]:
    """The closing summary of a demo run folder (ate.json, stats.json) and its mesh evaluation."""
    lines = ["", "sigmaslam demo: results", "-----------------------"]
    ate_path, stats_path = out / "ate.json", out / "stats.json"
    ate = json.loads(ate_path.read_text()) if ate_path.is_file() else {}
    stats = json.loads(stats_path.read_text()) if stats_path.is_file() else {}
    if ate:
        lines.append(f"causal ATE (SE(3) aligned) RMSE     {ate['ate_rmse_m']:.4f} m over {ate['matched']} poses")
        nc = ate.get("non_causal")
        if nc:
            lines.append(f"non-causal ATE (final BA) RMSE      {nc['ate_rmse_m']:.4f} m over {nc['matched']} poses")
    else:
        lines.append("ATE: not available (no trajectory or no ground truth)")
    if mesh:
        placed = {"final": "  (map placed by the final trajectory)", "causal": "  (map at the causal poses)"}
        lines.append(f"mesh accuracy (mean dist. to GT)    {mesh['accuracy_m']:.4f} m{placed.get(mesh.get('map_placed_by'), '')}")
        lines.append(f"mesh completeness (GT within 0.2 m) {100 * mesh['completeness']:.1f} %  "
                     f"(within 5 cm: {100 * mesh['completeness_5cm']:.1f} %)")
    lines += occupancy_lines(occupancy)
    if stats.get("frames_sent") is not None:
        lines.append(f"frames without a state              {stats.get('frames_without_state')} of {stats['frames_sent']}")
    lat = stats.get("state_latency_ms") or {}
    if lat.get("n"):
        lines.append(f"pose latency (sensor -> state)      p50 {lat['median']:.0f} ms, p99 {lat['p99']:.0f} ms "
                     f"over {lat['n']} states (from {stats.get('state_latency_from', 'arrival times')})")
    drops = stats.get("drops") or {}
    if drops:
        lost = {k: v for k, v in drops.items() if k in ESTIMATOR_QUEUES}
        lines.append("frames lost by the estimator        " + (", ".join(f"{k} {v}" for k, v in lost.items()) or "none"))
        other = {k: v for k, v in drops.items() if k not in ESTIMATOR_QUEUES}
        if other:
            lines.append("other queue drops (by design)       " + ", ".join(f"{k} {v}" for k, v in other.items())
                         + "  (latest-only inputs, depth paced at depth.rate_hz, non-keyframes the back end skips)")
    if stats.get("depth_uncertain_fraction") is not None:
        lines.append(f"depth pixels only freeing space     {100 * stats['depth_uncertain_fraction']:.1f} % "
                     f"(sigma > depth.max_relative_sigma x depth: too uncertain for a surface)")
    fb = stats.get("frontend_backend_median_ms")
    if fb is not None:
        lines.append(f"frontend + fast path median / frame {fb:.1f} ms (budget 33 ms)")
    if stats.get("loops"):
        lines.append(f"loop closure                        {stats['loops']}")
    lines.append(f"outputs                             {out}/ (trajectories, stats.json, mesh.ply, mesh_eval/)")
    lines.append(f"viewer                              {viewer_url}")
    if phases:
        lines.append(f"time                                {phase_line(phases)}")
    return lines


def main(args: argparse.Namespace) -> int:
    from services.app.system_config import load_system_config
    from services.app.synth.api import ensure_default_replica, replica_exists

    phases: dict[str, float] = {}
    if args.setup_s is not None:
        phases["set-up"] = args.setup_s
    cached = replica_exists()
    _say("default replica: 25 s of EuRoC V1_02 in scene vicon-a, real IMU "
         + ("(cached under data/replicas/)" if cached else "(rendering it once, about 1-2 min; then cached under data/replicas/)"))
    t = time.monotonic()
    dataset = ensure_default_replica(progress=True)
    phases["replica (cached)" if cached else "replica render"] = time.monotonic() - t
    gt = dataset / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    cfg = load_system_config(args.config, args.set)
    url = f"http://{cfg.viewer.host}:{cfg.viewer.port}"
    out = Path(args.out)
    t = time.monotonic()
    rc = _run_pipeline(dataset, args)
    phases["run"] = time.monotonic() - t
    t = time.monotonic()
    _say("evaluating the mesh against the scene (paper sec. V: 1 cm grid, point-to-plane ICP)")
    mesh = _mesh_figures(out, dataset)
    _say("evaluating the occupancy map against the scene (false free, free recall) and planning on its grid")
    occupancy = _occupancy_figures(out, dataset)
    phases["evaluation"] = time.monotonic() - t
    if mesh is not None:
        (out / "mesh_eval.json").write_text(json.dumps(mesh, indent=1))
    if args.serve_s > 0:
        from services.app.demo_serve import serve_run

        _say(f"serving the final map at {url} for {args.serve_s:.0f} s (Ctrl-C stops)")
        serve_run(out, args.config, [f"viewer.ground_truth={gt}", *args.set], args.serve_s)
        url += " (served the final map)"
    else:
        url += " (live during the run; `sigmaslam demo --serve-s 600` keeps it up with the final map)"
    (out / "phases.json").write_text(json.dumps({k: round(v, 2) for k, v in phases.items()}, indent=1))
    for line in summary_lines(out, mesh, url, phases, occupancy):
        print(line, flush=True)
    return rc
