"""``sigmaslam eval ablation``: the paper's Table IV (occupancy-to-point factors, depth sigma, depth fusion) and
the mono-inertial variant of Table II, as one command over several replicas, in one process per run (no
transport). Also ``python -m services.app.eval.ablation REPLICA ... [options]``.

Rows (each a full frontend + back end + loop closure + depth + mapping run over the same frames); what makes a
row is config alone (:func:`row_overrides`, applied after the user's ``--set``):

* ``baseline``: no dense terms; the map is built from stereo-network depth at the estimated poses
  (``o2p.enabled=false``, ``depth.use_mvs=false``).
* ``heuristic``: frame-to-map (and, with ``o2p.map_to_map``, map-to-map) factors on; the depth service publishes
  the stereo network's depth with a heuristic sigma, a disparity sigma of ``--heuristic-px`` pixels
  (sigma_d = d^2 sigma_u / (f b): ``depth.stereo_sigma=heuristic``, ``depth.heuristic_sigma_model=quadratic``,
  ``depth.heuristic_sigma_coeff=PX``), used by the factors and the map alike.
* ``learned``: as ``heuristic`` with the network's learned sigma (``depth.stereo_sigma`` left at ``network``).
* ``fused``: as ``learned`` with ``depth.use_mvs=true`` and ``mapping.depth_topic=depth/fused``: the map
  integrates the fused stereo + MVS depth, the frame-to-map points stay stereo (the back end reads
  ``depth/stereo``).
* ``mono``: the paper's Ours-Mono: ``rig.cameras=[cam0]``, ``depth.mono=true``, factors on; the depth
  service's MVS-only depth feeds both the map and the frame-to-map points.
* ``mono_baseline``: as ``mono`` without the factors (the map still from MVS depth): the row ``mono`` is judged
  against.

Each row runs the pipeline's own process nodes (frontend, back end with loop closure, depth, mapping) on the
in-process runner (services/app/inprocess.py: ``run_in_process(..., depth=True, mapping=True)``), deterministically
in stamp order, as a lockstep ``sigmaslam run`` would: the depth node takes a frame at most every 1 /
``depth.rate_hz`` of sensor time and waits for the frame's state; the mapping node integrates at the state's pose,
publishes the near-surface fields (and, with ``mapping.o2p_points`` > 0, map-to-map points) to the back end, and
moves its submaps onto the final trajectory after the stream (``mapping.follow_final``). Nothing is shared between
rows: stereo depth is computed again for each row. Two options of the hand-wired version are gone:
``--depth-every N`` (use ``--set depth.rate_hz=HZ``: the depth node paces itself by stamps, EuRoC cameras run at
20 Hz, so HZ = 20 / N) and the stereo cache across rows (each row now pays its own stereo network time, about
as long as the back end's share of a row on a CPU).

Per row: causal ATE (published states) and non-causal ATE (final bundle adjustment) [m] after SE(3)
alignment, mesh accuracy and completeness at 0.2 m and 0.05 m against the replica's scene mesh
(services/app/metrics/mesh.py) of the map as built (submaps at the causal keyframe poses, taken just before the
mapping follows the final trajectory), and accuracy and completeness of the final map (the mapping node's submaps
on the final bundle adjustment's trajectory), the back end's per-frame wall time (median, p99 of the runner's
times of its frame handler, without the loop closer's work, which ``loop.synchronous`` runs inside the frame's call
but the back-end service runs in its own thread: reported as its total and largest per-frame time), the o2p factor
counts, the depth frames published, the mapping's counts, the row's wall time. A row that fails is recorded as
``failed: why`` and the others still run.

Writes ``--out``/ablation.json, table.md and, per replica and row, ``<replica>/<row>.json`` (the result),
``<row>.log`` (that row's log) and ``<row>/trajectory_{causal,final}.txt`` (TUM). ``--resume`` skips rows whose
result json holds a finished (not failed) result of the same settings (--seconds, --heuristic-px, mesh,
overrides).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from shared import topics
from services.app.eval.ablation_table import MONO, ROWS, table_markdown

DEFAULT_REPLICAS = ("V1_02", "V2_01", "MH_04")

log = logging.getLogger("sigmaslam.ablation")
row_log = logging.getLogger("sigmaslam.ablation.row")  # failures: to the row's log file alone
row_log.propagate = False


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("replicas", nargs="*", default=list(DEFAULT_REPLICAS),
                   help="replica folders, or EuRoC sequence names (V1_02, V2_01, MH_04, ...) whose real-IMU replica "
                        "of --duration seconds is generated once and cached (services/app/synth/api.py); default: "
                        + " ".join(DEFAULT_REPLICAS))
    p.add_argument("--duration", type=float, default=25.0,
                   help="replica length for sequence names (0: whole sequence) [s]")
    p.add_argument("--rows", default=",".join(ROWS), help=f"comma-separated rows out of {','.join(ROWS)}")
    p.add_argument("--seconds", type=float, default=0.0, help="first S seconds of each replica (0: all) [s]")
    p.add_argument("--heuristic-px", type=float, default=1.0, help="disparity sigma of the heuristic row [px]")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override applied to every row (the row's own keys win); the depth rate is "
                        "depth.rate_hz (--depth-every N of earlier versions: depth.rate_hz=20/N)")
    p.add_argument("--no-mesh", action="store_true", help="skip the mesh evaluation")
    p.add_argument("--out", default="out/ablation", help="output folder (default out/ablation)")
    p.add_argument("--resume", action="store_true", help="skip rows whose result json holds a finished result of the same settings")


# ---------------------------------------------------------------------------------------------- inputs
def resolve_replica(name: str, duration_s: float) -> tuple[str, Path]:
    """(label, folder) of a replica given as a folder or a sequence name."""
    path = Path(name)
    if (path / "mav0").is_dir():
        return path.name, path
    if "/" in name or path.exists():
        raise ValueError(f"{name}: not a replica folder (no mav0/ inside)")
    from services.app.eval.suite import scene_for
    from services.app.synth.api import ensure_replica

    return name, ensure_replica(name, scene_for(name), imu="real", duration_s=duration_s, progress=False)


# under every row, before the user's --set: loop events handled in the back end's thread, so that a row's result
# depends on its input alone (with the loop thread, runs differ by a few mm of ATE with the machine's load)
EVAL_DEFAULTS = ("loop.synchronous=true",)


def row_overrides(row: str, heuristic_px: float = 1.0) -> list[str]:
    """The config keys that make a row what it is (applied after the user's ``--set``); ``heuristic_px``: the
    heuristic row's disparity sigma [px]."""
    if row == "baseline":
        return ["o2p.enabled=false", "depth.use_mvs=false"]
    if row in MONO:
        return ["rig.cameras=[cam0]", "depth.mono=true", "depth.use_mvs=true", f"o2p.enabled={str(row == 'mono').lower()}"]
    if row == "heuristic":
        return ["o2p.enabled=true", "depth.use_mvs=false", "depth.stereo_sigma=heuristic",
                "depth.heuristic_sigma_model=quadratic", f"depth.heuristic_sigma_coeff={heuristic_px:g}"]
    if row == "fused":
        return ["o2p.enabled=true", "depth.use_mvs=true", "mapping.depth_topic=depth/fused"]
    return ["o2p.enabled=true", "depth.use_mvs=false"]


_GT_POINTS: dict = {}


def _gt_points(path: Path) -> np.ndarray:
    from services.app.metrics.mesh import load_points

    if path not in _GT_POINTS:
        _GT_POINTS[path] = load_points(path, 0.02)
    return _GT_POINTS[path]


# ---------------------------------------------------------------------------------------------- one row
class _Progress:
    """A line now and then so that a user sees a long row is alive (a tap on the run's camera frames)."""

    def __init__(self, prefix: str, period_s: float = 30.0) -> None:
        self.prefix, self.period_s = prefix, period_s
        self.t0 = self.last = time.monotonic()
        self.frames, self.first_ns = 0, None

    def __call__(self, topic, msg) -> None:
        if topic != topics.FRAME:
            return
        self.frames += 1
        stamp = int(msg.header.stamp_ns)
        self.first_ns = stamp if self.first_ns is None else self.first_ns
        now = time.monotonic()
        if now - self.last >= self.period_s:
            self.last = now
            print(f"{self.prefix}: {self.frames} frames ({(stamp - self.first_ns) * 1e-9:.1f} s of data), "
                  f"{now - self.t0:.0f} s", flush=True)


def row_config(row: str, dataset: Path, overrides: list[str], heuristic_px: float = 1.0):
    """The system config of a row: the evaluation defaults, the user's ``--set``, then the row's own keys."""
    from services.app.system_config import load_system_config
    from shared.config import ConfigError, override

    if row not in ROWS:
        raise ValueError(f"unknown row {row!r} (rows: {', '.join(ROWS)})")
    try:
        cfg = load_system_config(None, [*EVAL_DEFAULTS, *overrides, *row_overrides(row, heuristic_px)])
    except ConfigError as exc:
        if row in MONO and "mono" in str(exc):
            raise ValueError("this build has no monocular depth (the config has no depth.mono)") from None
        raise
    if not cfg.rig.calibration:
        cfg = override(cfg, {"rig.calibration": str(dataset)})
    return cfg


def run_row(row: str, dataset: Path, overrides: list[str], seconds: float, heuristic_px: float,
            mesh: bool = True, progress: _Progress | None = None, out_dir: Path | None = None) -> dict:
    """One row over ``dataset``: the pipeline's nodes (frontend, back end, depth, mapping) on the in-process
    runner (services/app/inprocess.py) with the row's config; raises on configuration or component errors (the
    caller records them)."""
    from services.app.inprocess import run_in_process

    cfg = row_config(row, dataset, overrides, heuristic_px)
    run = run_in_process(str(dataset), cfg, depth=True, mapping=True, seconds=seconds,
                         taps=() if progress is None else (progress,))
    t_call = np.array([t for t, _ in run.runner.times.get(("backend", "on_features"), [])])
    if not len(t_call):
        raise RuntimeError(f"no frame reached the back end ({run.frames} camera frames)")
    t_loop = np.array(run.loop_s) if len(run.loop_s) == len(t_call) else np.zeros_like(t_call)
    t_be = t_call - t_loop  # the back end's own per-frame time, without the loop closer's work
    depth, mapping = run.nodes["depth"], run.nodes["mapping"]
    pipe, dc = depth.pipe, cfg.depth
    published = [s for s in run.states if s.status not in ("initialising", "reset")]
    res = {"row": row, "frames": run.frames, "states": len(published),
           "depth_frames": run.runner.emitted.get("depth/stereo", 0), "depth_rate_hz": dc.rate_hz,
           "submaps": len(mapping.mapper.submaps), "backend_median_ms": 1e3 * float(np.median(t_be)),
           "backend_p99_ms": 1e3 * float(np.percentile(t_be, 99)),
           "loop_closer_total_s": float(np.sum(t_loop)), "loop_closer_max_ms": 1e3 * float(np.max(t_loop)),
           "depth": {"method": pipe.method, "stereo_sigma": dc.stereo_sigma if pipe.stereo_net is not None else "-",
                     "stereo_weights": (dc.stereo_weights or "(shipped)") if pipe.stereo_net is not None else "-",
                     "mvs_weights": (dc.mvs_weights or "(shipped)") if pipe.mvs_net is not None else "-"},
           "mapping_counts": dict(mapping.counts)}
    t_odo = run.nodes["frontend"].timer("fast_path").durations_s
    if t_odo:  # the per-frame fast path (every frame's state); the back end's figures are its window's work
        res["odometry_median_ms"] = 1e3 * float(np.median(t_odo))
        res["odometry_p99_ms"] = 1e3 * float(np.percentile(t_odo, 99))
    if run.runner.rejected:
        res["rejected"] = {f"{n} {k}": v for (n, k), v in run.runner.rejected.items()}
    if depth.no_mvs:
        res["depth_frames_without_mvs"] = depth.no_mvs
    be = run.nodes["backend"]
    if cfg.o2p.enabled:
        res["o2p_counts"] = dict(be.o2p.counts)
    if be.loop_closure is not None:
        res["loop"] = {k: int(v) for k, v in be.loop_closure.counts.items()}
    stamps = [int(s.header.stamp_ns) for s in published]
    T_pub = [np.asarray(s.T_WS) for s in published]
    res.update(_evaluate(dataset, stamps, T_pub, run.final, mapping.mapper if mesh else None, run.mesh_causal, out_dir))
    return res


def _evaluate(dataset: Path, stamps, T_pub, final, mapper, mesh_causal, out_dir: Path | None) -> dict:
    """ATE of the causal and final trajectories; mesh metrics of the map as built (``mesh_causal``: world
    vertices at the causal poses) and of the mapping's final map (``mapper``, its submaps on the final trajectory)."""
    from shared.euroc import read_trajectory, series_from_matrices, write_tum
    from shared.euroc_reader import EurocDataset
    from shared.metrics.ate import compute_ate

    res: dict = {}
    trajs = {"causal": (np.array(stamps, np.int64), np.array(T_pub).reshape(-1, 4, 4))}
    if final is not None:
        trajs["noncausal"] = (np.asarray(final.stamps_ns, np.int64), np.asarray(final.T_WS))
        res["final_keyframes"] = int(final.keyframes)
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        for key, name in (("causal", "trajectory_causal.txt"), ("noncausal", "trajectory_final.txt")):
            if key in trajs and len(trajs[key][0]):
                write_tum(out_dir / name, series_from_matrices(*trajs[key]))
    gt_path = EurocDataset(dataset).groundtruth_path
    align = {}
    if gt_path is not None:
        gt = read_trajectory(gt_path)
        for key, (st, T) in trajs.items():
            try:
                ate = compute_ate(gt.stamps_ns, gt.p_WS, st, T[:, :3, 3], mode="se3")
            except ValueError as exc:
                res[f"error_ate_{key}"] = str(exc)
                continue
            res[f"ate_{key}_m"] = ate.rmse_m
            align[key] = ate.alignment
    scene = sorted(Path(dataset).glob("mav0/scene/*.ply"))
    if mapper is not None and mesh_causal is not None and scene:
        from services.app.metrics.mesh import evaluate_points

        t0 = time.perf_counter()
        v = mesh_causal
        if len(v) and "causal" in align:  # the estimate's W into the ground truth's frame (the causal alignment)
            ev = evaluate_points(align["causal"].apply(np.asarray(v, float)), _gt_points(scene[0]))
            res.update(accuracy_m=ev.accuracy_m, completeness=ev.completeness, completeness_5cm=ev.completeness_5cm,
                       mesh_points=ev.n_est, mesh_eval_s=round(time.perf_counter() - t0, 1))
        else:
            res["error_mesh"] = "no mesh vertices" if not len(v) else "no trajectory alignment"
        if len(v) and final is not None and "noncausal" in align:  # the map the mapping wrote at the end
            v, _ = mapper.world_mesh()  # (its submaps moved onto the final trajectory: mapping.follow_final)
            ev = evaluate_points(align["noncausal"].apply(np.asarray(v, float)), _gt_points(scene[0]))
            res.update(accuracy_final_m=ev.accuracy_m, completeness_final=ev.completeness)
    return res


# ---------------------------------------------------------------------------------------------- command
def _log_file(path: Path) -> logging.Handler:
    h = logging.FileHandler(path, mode="w")
    h.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    h.setLevel(logging.INFO)
    return h


def main(args: argparse.Namespace) -> int:
    rows = [r.strip() for r in args.rows.split(",") if r.strip()]
    bad = [r for r in rows if r not in ROWS]
    if bad or not rows:
        print(f"eval ablation: unknown rows {bad} (rows: {','.join(ROWS)})", file=sys.stderr)
        return 2
    if args.seconds < 0 or args.heuristic_px <= 0:
        print("eval ablation: --seconds must be >= 0, --heuristic-px > 0", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict[str, dict]] = {}
    rc, t_all = 0, time.monotonic()
    for name in args.replicas:
        try:
            label, dataset = resolve_replica(name, args.duration)
        except (ValueError, OSError) as exc:
            print(f"eval ablation: {exc}", file=sys.stderr)
            return 2
        rep_out = out / label
        rep_out.mkdir(parents=True, exist_ok=True)
        results[label] = {}
        for row in rows:
            path = rep_out / f"{row}.json"
            settings = {"seconds": args.seconds, "heuristic_px": args.heuristic_px, "mesh": not args.no_mesh,
                        "overrides": [*EVAL_DEFAULTS, *args.set, *row_overrides(row, args.heuristic_px)]}
            if args.resume and path.is_file():
                old = json.loads(path.read_text())
                same = all(old.get(k) == v for k, v in settings.items())
                if "error" not in old and same:
                    print(f"[eval ablation] {label} {row}: done before ({path}), skipped", flush=True)
                    results[label][row] = old
                    continue
                if not same:
                    print(f"[eval ablation] {label} {row}: {path} was run with other settings, running again", flush=True)
            prefix = f"[eval ablation] {label} {row}"
            print(f"{prefix}: running ({dataset})", flush=True)
            handler = _log_file(rep_out / f"{row}.log")
            row_log.addHandler(handler)
            root = logging.getLogger()
            root.addHandler(handler)
            level = root.level
            root.setLevel(min(level, logging.INFO) if level else logging.INFO)
            t0 = time.perf_counter()
            try:
                r = run_row(row, dataset, args.set, args.seconds, args.heuristic_px, not args.no_mesh,
                            _Progress(prefix), rep_out / row)
            except Exception as exc:  # noqa: BLE001 - a failed row is recorded; the others still run
                row_log.exception("row %s failed", row)  # the traceback goes to the row's log only
                r = {"row": row, "error": f"{type(exc).__name__}: {exc}"}
                rc = 1
            finally:
                root.removeHandler(handler)
                row_log.removeHandler(handler)
                handler.close()
                root.setLevel(level)
            r["wall_s"] = round(time.perf_counter() - t0, 1)
            r["replica"] = str(dataset)
            r.update(settings)
            path.write_text(json.dumps(r, indent=1, default=float))
            results[label][row] = r
            brief = {k: r[k] for k in ("error", "ate_causal_m", "ate_noncausal_m", "accuracy_m", "accuracy_final_m", "completeness",
                                       "completeness_5cm", "backend_median_ms", "backend_p99_ms") if k in r}
            if "o2p_counts" in r:
                brief["f2m/m2m"] = f"{r['o2p_counts'].get('frame_to_map', 0)}/{r['o2p_counts'].get('map_to_map', 0)}"
            print(f"{prefix}: {'failed' if 'error' in r else 'done'} in {r['wall_s']:.0f} s "
                  f"(total {time.monotonic() - t_all:.0f} s): {json.dumps(brief, default=float)}", flush=True)
    (out / "ablation.json").write_text(json.dumps({"replicas": results, "rows": rows, "seconds": args.seconds,
                                                   "set": args.set,
                                                   "heuristic_px": args.heuristic_px}, indent=1, default=float))
    table = table_markdown(results)
    (out / "table.md").write_text(table)
    print(table, flush=True)
    print(f"[eval ablation] wrote {out / 'table.md'} and {out / 'ablation.json'}", flush=True)
    return rc


if __name__ == "__main__":
    _parser = argparse.ArgumentParser(prog="python -m services.app.eval.ablation", description=__doc__.splitlines()[0])
    add_arguments(_parser)
    sys.exit(main(_parser.parse_args()))
