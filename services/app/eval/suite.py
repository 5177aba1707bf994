"""``sigmaslam eval suite``: the paper's tables (I: ATE, II: mesh, V: timing; plus the Hilti score) on replicas.

For each sequence (default: every EuRoC sequence whose files are found, shared/paths.py: the eight of the shared
folder, real IMU where it was recorded, simulated for MH_01/MH_02; scene ``vicon-<variant>`` /
``machinehall-<variant>``, ``--variant a|b``) the replica is generated once (cached, services/app/synth/api.py;
``--duration S`` for a short one), the pipeline runs on it (services/app/run_pipeline.py, as ``sigmaslam run``, with
frontend, backend, depth, mapping, or the services of ``--config`` with ``--services config``; final bundle
adjustment on; stages logged and processes sampled) once per playback rate of ``--rates``
(0: lockstep, so that a loaded machine does not change accuracy; R: R x sensor rate, live; ``--rates 0,1`` gives
both), and the outputs are evaluated:

- ATE RMSE after SE(3) alignment of the causal (trajectory_causal.txt) and non-causal (trajectory_final.txt)
  trajectories (shared/metrics/ate.py), the RMSE of their first 10 s and of the 10 s where the ground truth turns
  fastest (services/app/metrics/segments.py), the means over the sequences against the paper's, Hilti score on control points from the ground truth (services/app/metrics/hilti.py);
- mesh accuracy / completeness of DIR/mesh.ply against the replica's mav0/scene/mesh.ply (services/app/metrics/mesh.py),
  with its error image;
- per-item compute times of every stage (mean +- sigma, pooled over the sequences);
- live runs: pose latency, frames without a state, keyframes skipped, and the share of the wall time the frontend's
  and back end's main threads ran and waited for a core (:func:`live_figures`).

Writes ``--out``/report.md (tables with the paper's numbers beside ours), summary.png, suite.json and per
sequence ``<seq>/trajectory.png``, ``<seq>/mesh/error_top.png`` and the run folder. ``--skip-run`` rebuilds the
report from existing run folders.

One run per sequence is a noisy measure: small perturbations (another machine, another start frame) move a
sequence's causal ATE by tens of percent. ``--starts 0,0.5,1`` runs each sequence once per start offset (the
player's ``start_s``: the sensors switched on that long after the first frame) into ``<seq>/start_<S>s/`` and
reports, per sequence, the median over the runs (Table I and the means) and their spread.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

from services.app.eval.suite_report import pooled_timing, write_report

SITE_OF_PREFIX = {"V": "vicon", "MH": "machinehall"}


def available_sequences() -> list[str]:
    """The known EuRoC sequences whose files are found (shared folder or bundled), in EuRoC order."""
    from shared.paths import EUROC_SEQUENCES, has_sequence

    return [s for s in sorted(EUROC_SEQUENCES) if has_sequence(s)]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sequences", default="all",
                   help="comma-separated EuRoC sequences (default 'all': every one whose files are found)")
    p.add_argument("--variant", default="a", choices=("a", "b"), help="scene variant of the replicas")
    p.add_argument("--profile", default="", help="harder replicas (services/app/synth/profiles.py: 'hard' = motion "
                   "blur, auto-exposure jumps, 1 ms camera-IMU offset)")
    p.add_argument("--duration", type=float, default=0.0, help="replica length (0: whole sequence) [s]")
    p.add_argument("--seconds", type=float, default=0.0,
                   help="play only the first S seconds of each replica (0: all); unlike --duration, the cached "
                        "replica is reused [s]")
    p.add_argument("--out", default="out/suite", help="output folder (default out/suite)")
    p.add_argument("--rates", default="0",
                   help="comma-separated playback rate factors, one run each (0: lockstep; 1: live at sensor rate)")
    p.add_argument("--rate", type=float, help=argparse.SUPPRESS)  # the former single-rate flag: --rates R
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    p.add_argument("--services", default="frontend,backend,depth,mapping",
                   help="pipeline services (comma-separated; 'config': those of --config)")
    p.add_argument("--config", help="YAML system config of the runs (default: built-in defaults), e.g. configs/demo.yaml")
    p.add_argument("--hilti-points", type=int, default=12, help="control points per sequence for the Hilti score")
    p.add_argument("--skip-run", action="store_true", help="use the run folders already under --out")
    p.add_argument("--keep-maps", action="store_true",
                   help="keep each pipeline run's dense map (RUN/submaps/, RUN/map/dense.npz: hundreds of MB for a "
                        "whole sequence); by default they are deleted once the run is scored (mesh.ply and the "
                        "trajectories stay)")
    p.add_argument("--in-process", action="store_true",
                   help="the estimator alone in one process (frontend, back end, loop closure, final BA; no depth, "
                        "mapping, transport), reproducible: Table I in minutes (--rates is ignored)")
    p.add_argument("--timeout-s", type=float, default=1800.0, help="give up a run after this long [s]")
    p.add_argument("--starts", default="0",
                   help="comma-separated start offsets, one run each per sequence and rate (player.start_s); with "
                        "more than one, a sequence's figures are the median over its runs and the report shows "
                        "their spread (default 0: one run from the first frame) [s]")


def scene_for(sequence: str, variant: str = "a") -> str:
    for prefix, site in SITE_OF_PREFIX.items():
        if sequence.startswith(prefix):
            return f"{site}-{variant}"
    raise ValueError(f"no replica scene for sequence {sequence!r} (known sites: V*, MH*)")


def mode_name(rate: float) -> str:
    return "lockstep" if rate <= 0 else f"live {rate:g}x"


def _aligned(res, est_p: np.ndarray, est_stamps: np.ndarray) -> np.ndarray:
    keep = np.isin(est_stamps, res.stamps_ns)
    return res.alignment.apply(est_p[keep])


def evaluate_sequence(seq: str, replica: Path, run_dir: Path, out: Path, hilti_points: int) -> dict:
    """ATE, Hilti score, mesh metrics and the trajectory figure of one finished run."""
    from services.app.eval.hilti_cmd import dataset_control_points
    from shared.euroc import read_trajectory
    from shared.metrics.ate import compute_ate
    from services.app.metrics.segments import segment_errors
    from services.app.metrics.hilti import hilti_score
    from services.app.metrics.mesh import evaluate_mesh_files
    from services.app.eval.suite_plots import trajectory_figure

    row: dict = {"replica": str(replica)}
    gt = read_trajectory(replica / "mav0" / "state_groundtruth_estimate0" / "data.csv")
    cs, cp = dataset_control_points(replica, hilti_points)
    row["hilti_points"] = hilti_points
    runs = {}
    for label, name, key in (("causal", "trajectory_causal.txt", "causal"), ("non-causal", "trajectory_final.txt",
                                                                            "noncausal")):
        path = run_dir / name
        if not path.is_file():
            continue
        est = read_trajectory(path)
        try:
            res = compute_ate(gt.stamps_ns, gt.p_WS, est.stamps_ns, est.p_WS, mode="se3")
        except ValueError as exc:
            row[f"error_{key}"] = str(exc)
            continue
        row[f"ate_{key}_m"] = res.rmse_m
        seg = segment_errors(res, gt.stamps_ns, gt.q_WS_wxyz, 10.0)
        row[f"first10_{key}_m"], row[f"fastest10_{key}_m"] = seg["first_rmse_m"], seg["fastest_rmse_m"]
        row["fastest10_start_s"], row["fastest10_deg_s"] = seg["fastest_start_s"], seg["fastest_deg_s"]
        row["poses"] = res.matched if key == "causal" else row.get("poses")
        row[f"hilti_{key}"] = hilti_score(cs, cp, est.stamps_ns, est.p_WS).score
        runs[label] = (res, _aligned(res, est.p_WS, est.stamps_ns))
    if runs:
        trajectory_figure(out / "trajectory.png", seq, gt.p_WS, runs)
    mesh = run_dir / "mesh.ply"
    if not mesh.is_file() and (run_dir / "map" / "dense.npz").is_file():
        mesh = mesh_from_checkpoint(run_dir)
        row["mesh_source"] = "map/dense.npz checkpoint (the mapper stopped before writing mesh.ply)"
    gt_mesh = replica / "mav0" / "scene" / "mesh.ply"
    if mesh.is_file() and gt_mesh.is_file():
        try:
            T0 = runs["causal"][0].alignment.matrix() if "causal" in runs else None  # run frame -> GT frame
            m = evaluate_mesh_files(mesh, gt_mesh, out_dir=out / "mesh", T_gt_est_init=T0)
            row.update(accuracy_m=m.accuracy_m, completeness=m.completeness, mesh_points=m.n_est)
        except (ValueError, RuntimeError) as exc:
            row["error_mesh"] = str(exc)
    return row


DENSE_MAP_FILES = ("submaps", "map/dense.npz", "mesh_from_checkpoint.ply")  # under a run folder


def drop_dense_map(run_dir: Path) -> int:
    """Delete a scored run's dense map (:data:`DENSE_MAP_FILES`); the trajectories, stats, the sparse map and
    mesh.ply stay. Returns the bytes freed."""
    freed = 0
    for name in DENSE_MAP_FILES:
        path = run_dir / name
        files = [f for f in path.rglob("*") if f.is_file()] if path.is_dir() else [path] if path.is_file() else []
        freed += sum(f.stat().st_size for f in files)
        shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)
    return freed


def mesh_from_checkpoint(run_dir: Path) -> Path:
    """World mesh of the mapper's last checkpoint (DIR/map/dense.npz) as DIR/mesh_from_checkpoint.ply."""
    from services.mapping.io import load_map, write_ply

    mapper = load_map(run_dir / "map" / "dense.npz")
    mapper.remesh(None)
    v, f = mapper.world_mesh()
    return write_ply(run_dir / "mesh_from_checkpoint.ply", v, f)


def run_estimator_in_process(replica: Path, run_dir: Path, config: str | None, sets: list[str],
                             seconds: float = 0.0) -> dict:
    """The estimator alone (frontend, fast path, back end with loop closure and final BA; no depth, mapping or
    occupancy terms) on the in-process runner, loop events handled synchronously: a reproducible run of a few
    minutes per sequence. Writes trajectory_causal.txt and trajectory_final.txt into ``run_dir``."""
    from services.app.eval.loop_eval import evaluate_loop
    from services.app.run_pipeline import frames_within
    from shared.euroc import write_tum

    run_dir.mkdir(parents=True, exist_ok=True)
    frames = frames_within(replica, seconds) if seconds > 0 else 0
    res, trajs = evaluate_loop(str(replica), ["loop.synchronous=true", "loop.final_ba=true", *sets], frames,
                               config=config)
    write_tum(run_dir / "trajectory_causal.txt", trajs["causal"])
    if "final" in trajs:
        write_tum(run_dir / "trajectory_final.txt", trajs["final"])
    (run_dir / "eval_loop.json").write_text(json.dumps(res, indent=1, default=str))
    return res


def parse_rates(args: argparse.Namespace) -> list[float]:
    if args.rate is not None:
        return [args.rate]
    rates = [float(x) for x in args.rates.split(",") if x.strip()]
    if not rates:
        raise ValueError("--rates: give at least one rate (0: lockstep)")
    return rates


def parse_starts(text: str) -> list[float]:
    """The distinct start offsets of ``--starts`` [s], in the order given."""
    starts = list(dict.fromkeys(float(x) for x in text.split(",") if x.strip()))
    if not starts or any(not (s >= 0) for s in starts):
        raise ValueError(f"--starts: give one or more offsets >= 0 s, got {text!r}")
    return starts


def _number(v) -> bool:
    """An int or float figure (NaN included), not a bool."""
    return isinstance(v, (int, float)) and not isinstance(v, bool)


# the figures whose per-run values a row of several runs keeps beside their median
SPREAD_KEYS = ("ate_causal_m", "ate_noncausal_m", "first10_causal_m", "fastest10_causal_m")


def median_row(runs: dict[float, dict]) -> dict:
    """One row for several runs of a sequence (start offset -> its row): every numeric field is the median over
    the runs that have it (each field on its own: the median ATE and the median first 10 s may come from different
    runs; a count's median rounded to a whole number), other fields are the first run's; 'runs' keeps the
    :data:`SPREAD_KEYS` of each run, keyed by its start [s], and 'runs_failed' counts the runs without a causal ATE."""
    row: dict = {}
    for key in dict.fromkeys(k for r in runs.values() for k in r):
        values = [r[key] for r in runs.values() if key in r]
        if not all(_number(v) for v in values):
            row[key] = values[0]
        else:  # counts stay whole numbers
            med = float(np.median(values))
            row[key] = int(round(med)) if all(isinstance(v, int) for v in values) else med
    row["runs"] = {f"{s:g}": {k: r.get(k) for k in SPREAD_KEYS} for s, r in runs.items()}
    row["runs_failed"] = sum("ate_causal_m" not in r for r in runs.values())
    return row


# a live run's real-time figures in its row (median over starts like the others): key -> (source, field)
LIVE_KEYS = {"latency_p50_ms": ("latency", "median"), "latency_p99_ms": ("latency", "p99"),
             "frames_without_state": ("stats", "frames_without_state"),
             "keyframes_skipped": ("backend", "keyframes_skipped"),
             "frontend_run_pct": ("frontend", "main_thread_run_pct"),
             "frontend_wait_pct": ("frontend", "main_thread_wait_pct"),
             "backend_run_pct": ("backend_process", "main_thread_run_pct"),
             "backend_wait_pct": ("backend_process", "main_thread_wait_pct")}


def live_figures(run_stats: dict, processes: dict) -> dict:
    """What a live run did in real time, from its stats.json (``run_stats``) and the process sampler's summary
    (``processes``, services/app/metrics/processes.py): sensor -> pose latency p50 / p99 [ms], frames without a state,
    keyframes the back end skipped to catch up, and the share of the wall time the frontend's and the back end's
    main threads ran and waited for a core [%]. A figure the run did not report is left out."""
    sources = {"latency": run_stats.get("state_latency_ms") or {}, "stats": run_stats,
               "backend": run_stats.get("services", {}).get("backend", {}).get("counters", {}),
               "frontend": processes.get("frontend", {}), "backend_process": processes.get("backend", {})}
    out = {}
    for key, (src, field) in LIVE_KEYS.items():
        v = sources[src].get(field)
        if _number(v) and v == v:  # not None, not NaN
            out[key] = v
    return out


def run_pipeline_measured(args: argparse.Namespace, replica: Path, run_out: Path, rate: float, sets: list[str]):
    """The pipeline (the services of ``--services``, final bundle adjustment on) on ``replica`` into ``run_out``/run,
    its stages logged to ``run_out``/stage_log and its processes sampled (``rate`` <= 0: lockstep)."""
    from services.app.run_pipeline import frames_within, run_pipeline, services_overrides

    overrides = [*services_overrides(args.services), "loop.final_ba=true", *sets]
    return run_pipeline(replica, run_out / "run", args.config, overrides,
                        rate=max(rate, 0.0), max_frames=frames_within(replica, args.seconds),
                        timeout_s=args.timeout_s, final_timeout_s=120.0, stage_log=run_out / "stage_log",
                        sample_processes=True)


def run_and_score(args: argparse.Namespace, label: str, replica: Path, run_out: Path, rate: float,
                  sets: list[str]) -> tuple[dict, bool]:
    """One run of the pipeline (or of the estimator in process) on ``replica`` into ``run_out``/run, scored:
    (its row, whether it ran and scored without an error)."""
    ok = True
    if args.skip_run:
        pass
    elif args.in_process:
        run_estimator_in_process(replica, run_out / "run", args.config, sets, args.seconds)
    else:
        res = run_pipeline_measured(args, replica, run_out, rate, sets)
        ok = res.rc == 0
    try:
        row = evaluate_sequence(label, replica, run_out / "run", run_out, args.hilti_points)
    except (ValueError, OSError) as exc:
        row, ok = {"error_run": str(exc)}, False
    if not (args.in_process or args.skip_run):
        row.update(live_figures(res.stats, res.sampler.summary()))
    if not (args.in_process or args.skip_run or args.keep_maps):
        freed = drop_dense_map(run_out / "run")
        print(f"[eval suite] {label}: dense map deleted after scoring ({freed / 1e6:.0f} MB; --keep-maps keeps it)",
              flush=True)
    print(f"[eval suite] {label}: {json.dumps({k: v for k, v in row.items() if k != 'replica'})}", flush=True)
    return row, ok


def main(args: argparse.Namespace) -> int:
    from services.app.synth.api import ensure_replica
    from shared.paths import has_real_imu

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    try:
        seqs = available_sequences() if args.sequences.strip() == "all" else \
            [s.strip() for s in args.sequences.split(",") if s.strip()]
        scenes = {s: scene_for(s, args.variant) for s in seqs}
        rates = [0.0] if args.in_process else parse_rates(args)
        starts = parse_starts(args.starts)
    except ValueError as exc:
        print(f"eval suite: {exc}", file=sys.stderr)
        return 2
    if not seqs or args.duration < 0:
        print("eval suite: give at least one sequence and --duration >= 0", file=sys.stderr)
        return 2
    rows, stage_dirs, rc = {}, [], 0
    for seq in seqs:
        imu = "real" if has_real_imu(seq) else "sim"
        # a bar on a terminal: rendering a whole sequence takes minutes (logs get the 'generating replica' line)
        replica = ensure_replica(seq, scenes[seq], imu=imu, duration_s=args.duration, progress=sys.stderr.isatty(),
                                 profile=args.profile)
        print(f"[eval suite] {seq}: replica {replica} ({imu} IMU)", flush=True)
        for rate in rates:
            key = seq if len(rates) == 1 else f"{seq} {mode_name(rate)}"
            seq_out = out / seq if len(rates) == 1 else out / seq / mode_name(rate).replace(" ", "_")
            runs = {}
            for start in starts:
                run_out = seq_out if len(starts) == 1 else seq_out / f"start_{start:g}s"
                label = key if len(starts) == 1 else f"{key} (start {start:g} s)"
                sets = [*args.set, f"player.start_s={start:g}"] if start > 0 else list(args.set)
                runs[start], ok = run_and_score(args, label, replica, run_out, rate, sets)
                rc = rc if ok else 1
                runs[start]["dir"] = str(run_out.relative_to(out))
                stage_dirs.append(run_out / "stage_log")
            rows[key] = runs[starts[0]] if len(starts) == 1 else median_row(runs)
            rows[key].update(sequence=seq, imu=imu, mode=mode_name(rate), scene=scenes[seq])
            if len(starts) > 1:
                spread = {s: r["ate_causal_m"] for s, r in rows[key]["runs"].items()}
                print(f"[eval suite] {key}: median over starts {json.dumps(spread)}: causal "
                      f"{rows[key].get('ate_causal_m')}, non-causal {rows[key].get('ate_noncausal_m')}", flush=True)
    timing = pooled_timing([d for d in stage_dirs if d.is_dir()])
    (out / "suite.json").write_text(json.dumps({"rows": rows, "timing": timing, "duration_s": args.duration,
                                                "rates": rates, "variant": args.variant}, indent=2))
    path = write_report(out, rows, timing, args, rates, starts)
    print(path.read_text().split("![summary]")[0], flush=True)
    print(f"[eval suite] wrote {path}", flush=True)
    return rc
