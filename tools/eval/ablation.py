"""``sigmaslam eval ablation``: the paper's Table IV (occupancy-to-point factors, depth sigma, depth fusion) and
the mono-inertial variant of Table II, as one command over several replicas, in one process per run (no
transport).

Rows (each a full frontend + back end + loop closure + depth + mapping run over the same frames):

* ``baseline``: no dense terms; the map is built from stereo-network depth at the estimated poses.
* ``heuristic``: frame-to-map and map-to-map factors on; stereo-network depth with a heuristic sigma (a
  disparity sigma of ``--heuristic-px`` pixels: sigma_d = d^2 sigma_u / (f b)) for the factors and the map.
* ``learned``: as ``heuristic`` with the network's learned sigma.
* ``fused``: as ``learned``, but the map (and its map-to-map points) integrates the fused stereo + MVS depth;
  the frame-to-map points stay stereo, as the back-end service reads ``depth/stereo``.
* ``mono``: the paper's Ours-Mono: ``rig.cameras=[cam0]``, ``depth.mono=true``, factors on; the depth
  pipeline's MVS-only depth feeds both the map and the frame-to-map points.
* ``mono_baseline``: as ``mono`` without the factors (the map still from MVS depth): the row ``mono`` is judged
  against.

The components are the services' own: ``FrontendNode``, the back end as ``BackendNode`` builds it (its shell,
wrapped in ``LoopClosingBackend`` when ``loop.enabled``: loop closure corrects the published poses, and at the
end the final bundle adjustment gives the non-causal trajectory), ``DepthPipeline``, ``SubmapMapper`` with
its field messages and map-to-map point pool. Depth runs on every ``--depth-every``-th camera frame (default:
camera rate / ``depth.rate_hz``, as the depth service); the mapping waits for nothing (a depth frame's pose
is the estimate just published for it). Stereo depth does not depend on the pose, so it is computed once
per replica and shared by the rows; MVS (fused, mono) runs per row.

Per row: causal ATE (published states) and non-causal ATE (final bundle adjustment) [m] after SE(3)
alignment, mesh accuracy and completeness at 0.2 m and 0.05 m against the replica's scene mesh
(services/app/metrics/mesh.py) of the map as built (submaps at the causal keyframe poses), and accuracy and completeness
of the final map (submaps moved onto the final bundle adjustment's trajectory, as the mapping service writes it
with ``mapping.follow_final``), the back end's per-frame wall time (median, p99; without the loop closer's work,
which ``loop.synchronous`` runs inside the frame's call but the back-end service runs in its own thread: reported
as its total and largest per-frame time), the o2p factor counts, the row's
wall time. A row that fails is recorded as ``failed: why`` and the others still run.

Writes ``--out``/ablation.json, table.md and, per replica and row, ``<replica>/<row>.json`` (the result),
``<row>.log`` (that row's log) and ``<row>/trajectory_{causal,final}.txt`` (TUM). ``--resume`` skips rows whose
result json holds a finished (not failed) result of the same settings (--seconds, --depth-every, --heuristic-px,
mesh, overrides).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from tools.eval.ablation_table import DENSE, MONO, ROWS, table_markdown

DEFAULT_REPLICAS = ("V1_02", "V2_01", "MH_04")
CAMERA_RATE_HZ = 20.0  # EuRoC camera rate, for the default --depth-every

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
    p.add_argument("--depth-every", type=int, default=0,
                   help="depth on every N-th camera frame (0: camera rate / depth.rate_hz, as the depth service)")
    p.add_argument("--heuristic-px", type=float, default=1.0, help="disparity sigma of the heuristic row [px]")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override applied to every row (the row's own keys win)")
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
    from tools.eval.suite import scene_for
    from services.app.synth.api import ensure_replica

    return name, ensure_replica(name, scene_for(name), imu="real", duration_s=duration_s, progress=False)


# under every row, before the user's --set: loop events handled in the back end's thread, so that a row's result
# depends on its input alone (with the loop thread, runs differ by a few mm of ATE with the machine's load)
EVAL_DEFAULTS = ("loop.synchronous=true",)


def row_overrides(row: str) -> list[str]:
    """The config keys that make a row what it is (applied after the user's ``--set``)."""
    if row == "baseline":
        return ["o2p.enabled=false", "depth.use_mvs=false"]
    if row in MONO:
        return ["rig.cameras=[cam0]", "depth.mono=true", "depth.use_mvs=true", f"o2p.enabled={str(row == 'mono').lower()}"]
    return ["o2p.enabled=true", f"depth.use_mvs={'true' if row == 'fused' else 'false'}"]


def _frames(dataset: Path, seconds: float):
    from shared.euroc_reader import EurocDataset

    t0 = None
    for msg in EurocDataset(dataset).messages():
        t = int(msg.header.stamp_ns)
        t0 = t if t0 is None else t0
        if seconds > 0 and t - t0 > seconds * 1e9:
            return
        yield msg


_GT_POINTS: dict = {}


def _gt_points(path: Path) -> np.ndarray:
    from services.app.metrics.mesh import load_points

    if path not in _GT_POINTS:
        _GT_POINTS[path] = load_points(path, 0.02)
    return _GT_POINTS[path]


def _depth_pipeline(cfg):
    """The depth service's pipeline: the left camera alone with ``depth.mono``, else the stereo pair."""
    from services.depth.pipeline import DepthPipeline
    from shared.rig import load_rig_config

    cams = {c.name: c for c in load_rig_config(cfg.rig)}
    dc = cfg.depth
    mono = bool(getattr(dc, "mono", False))
    missing = [n for n in (dc.left_camera, *(() if mono else (dc.right_camera,))) if n not in cams]
    if missing:
        raise ValueError(f"depth cameras {missing} not in the rig ({sorted(cams)})")
    if mono:
        return DepthPipeline(dc, cams[dc.left_camera], None)
    return DepthPipeline(dc, cams[dc.left_camera], cams[dc.right_camera])


# ---------------------------------------------------------------------------------------------- one row
class _Progress:
    """A line now and then so that a user sees a long row is alive."""

    def __init__(self, prefix: str, period_s: float = 30.0) -> None:
        self.prefix, self.period_s = prefix, period_s
        self.t0 = self.last = time.monotonic()

    def tick(self, frames: int, sensor_s: float) -> None:
        now = time.monotonic()
        if now - self.last >= self.period_s:
            self.last = now
            print(f"{self.prefix}: {frames} frames ({sensor_s:.1f} s of data), {now - self.t0:.0f} s", flush=True)


def run_row(row: str, dataset: Path, overrides: list[str], seconds: float, depth_every: int, heuristic_px: float,
            stereo_cache: dict, mesh: bool = True, progress: _Progress | None = None,
            out_dir: Path | None = None) -> dict:
    """One row over ``dataset``; raises on configuration or component errors (the caller records them)."""
    from services.backend.node import BackendNode
    from services.frontend.node import FrontendNode
    from services.frontend.keyframe_features import keyframe_features_message
    from services.mapping.export import field_message
    from shared.occupancy.o2p_points import SubmapPointPool
    from services.mapping.submaps import SubmapMapper
    from services.system_config import load_system_config
    from shared.config import ConfigError, override
    from shared.messages import ImuSample
    from shared.rig import load_rig_config

    if row not in ROWS:
        raise ValueError(f"unknown row {row!r} (rows: {', '.join(ROWS)})")
    mono = row in MONO
    try:
        cfg = load_system_config(None, [*EVAL_DEFAULTS, *overrides, *row_overrides(row)])
    except ConfigError as exc:
        if mono and "mono" in str(exc):
            raise ValueError("this build has no monocular depth (the config has no depth.mono)") from None
        raise
    if not cfg.rig.calibration:
        cfg = override(cfg, {"rig.calibration": str(dataset)})
    cams = load_rig_config(cfg.rig)
    dense = row in DENSE  # row_overrides: o2p.enabled exactly for these
    fe, node = FrontendNode(cfg.frontend, cams), BackendNode(cfg, cams)  # the back end as its root builds it
    shell, loop = node.shell, node.loop
    be = shell if loop is None else loop
    pipe = _depth_pipeline(cfg)
    dc = cfg.depth
    every = depth_every if depth_every > 0 else max(1, round(CAMERA_RATE_HZ / dc.rate_hz))
    mapper = SubmapMapper(cfg.mapping.sensor, cfg.mapping.submaps)
    # map-to-map points pooled per submap as the mapping service does with mapping.o2p_points (its default 0
    # switches the pool off there; the dense rows always pool, o2p.max_points_map then)
    pool = SubmapPointPool(cfg.mapping.o2p_points if cfg.mapping.o2p_points > 0 else cfg.o2p.max_points_map)
    t_be, t_loop, stamps, T_pub, n_frames, n_depth, no_depth = [], [], [], [], 0, 0, 0
    last_field_ns, t_first = 0, None
    try:
        for msg in _frames(dataset, seconds):
            if isinstance(msg, ImuSample):
                fe.gyro.add(int(msg.header.stamp_ns), msg.omega_S)
                shell.add_imu(msg)
                continue
            n_frames += 1
            stamp = int(msg.header.stamp_ns)
            t_first = stamp if t_first is None else t_first
            if progress is not None:
                progress.tick(n_frames, (stamp - t_first) * 1e-9)
            names = list(msg.camera_names)
            left = msg.images[names.index(dc.left_camera)]
            right = None if mono else msg.images[names.index(dc.right_camera)]
            pipe.remember_frame(stamp, left)
            ff = fe.process(msg)
            if ff is None:
                continue
            if loop is not None and ff.is_keyframe:  # descriptors before the frame, as the frontend sends them
                kff = keyframe_features_message(fe.tracker, stamp, ff.header.seq)
                if kff is not None:
                    loop.add_keyframe_features(kff)
            t0, busy0 = time.perf_counter(), (loop.runner.busy_s if loop is not None else 0.0)
            out = be.process(ff)
            # loop.synchronous: the loop closer's work happened inside process(); the back-end service does it
            # in its own thread, so the per-frame figure leaves it out and it is reported on its own
            t_loop.append(loop.runner.busy_s - busy0 if loop is not None else 0.0)
            t_be.append(time.perf_counter() - t0 - t_loop[-1])
            if out is None or out[0].status in ("initialising", "reset"):
                continue
            state, kfs = out
            if loop is not None:  # the published state, as the back end reads estimator/state for the final trajectory
                loop.record_state(state)
            fe.gyro_bias = np.asarray(state.gyro_bias, float)
            stamps.append(stamp)
            T_pub.append(np.array(state.T_WS))
            if kfs is not None:
                mapper.update_keyframes(kfs.ids, kfs.stamps_ns, kfs.T_WS)
                pipe.update_keyframes(kfs.stamps_ns, kfs.T_WS)
            lms = be.take_landmarks()  # estimator/landmarks: the MVS prior, as the depth service keeps the latest
            if lms is not None and pipe.mvs_net is not None:
                pipe.update_landmarks(lms.p_W, lms.last_seen_ns, lms.num_observations)
            if n_frames % every:
                continue
            T_WC = state.T_WS @ pipe.T_SC
            if mono:  # the pipeline's monocular mode: MVS depth for the map and the factor points alike
                res = pipe.process(stamp, left, None, state.T_WS)
                if res.fused is None:  # no pose or no MVS source views yet: the depth service publishes nothing
                    no_depth += 1
                    continue
                d_s, s_s = d_m, s_m = res.fused
            else:
                if stamp not in stereo_cache:
                    stereo_cache[stamp] = pipe.stereo(*pipe.rect.rectify(left, right))
                d_s, s_s = stereo_cache[stamp]
                if row == "heuristic":
                    s_s = (d_s**2 * heuristic_px / (pipe.f_px * pipe.baseline_m)).astype(np.float32)
                d_m, s_m = d_s, s_s
                if row == "fused":  # as DepthPipeline.process, with the stereo from the cache
                    mvs, _ = pipe.mvs(pipe.rect.rectify(left, right)[0], T_WC, pipe.mvs_prior(stamp, T_WC))
                    if mvs is not None:
                        from services.depth.uncertainty import fuse

                        d_m, s_m = fuse(d_s, s_s, *mvs)
            n_depth += 1
            if dense:  # as the back-end service feeds depth/stereo: the published pose at the depth's stamp
                est = shell.estimator
                shell.o2p.add_depth(stamp, d_s, s_s, pipe.K, pipe.T_SC, state.T_WS, est.stamps, est.values)
            rep = mapper.integrate(d_m, s_m, pipe.K, T_WC, pipe.T_SC, stamp)
            sm = mapper.submaps[rep.submap_id]
            pool.add(rep.submap_id, d_m, s_m, pipe.K, np.linalg.inv(sm.T_WM) @ T_WC)
            if dense and rep.new_submap and rep.submap_id > 0:  # the closed submap: its field, then its points
                old = mapper.submaps[rep.submap_id - 1]
                shell.o2p.add_field(field_message(old, cfg.mapping.sensor.l_min))
                got = pool.pop(old.id)
                if got is not None:
                    shell.o2p.add_submap_points(old.id, *got)
            if dense and stamp - last_field_ns > cfg.mapping.field_period_s * 1e9:  # the growing one, now and then
                last_field_ns = stamp
                shell.o2p.add_field(field_message(sm, cfg.mapping.sensor.l_min))
        final = None
        if loop is not None:
            try:
                final = loop.finish()
            except (RuntimeError, ValueError) as exc:
                log.warning("final trajectory not computed: %s", exc)
            loops = loop.counts
    finally:
        if loop is not None:
            loop.close()
    if not t_be:
        raise RuntimeError(f"no frame reached the back end ({n_frames} camera frames)")
    res = {"row": row, "frames": n_frames, "states": len(stamps), "depth_frames": n_depth, "depth_every": every,
           "submaps": len(mapper.submaps), "backend_median_ms": 1e3 * float(np.median(t_be)),
           "backend_p99_ms": 1e3 * float(np.percentile(t_be, 99)),
           "loop_closer_total_s": float(np.sum(t_loop)), "loop_closer_max_ms": 1e3 * float(np.max(t_loop)),
           "depth": {"method": pipe.method,
                     "stereo_weights": (dc.stereo_weights or "(shipped)") if pipe.stereo_net is not None else "-",
                     "mvs_weights": (dc.mvs_weights or "(shipped)") if pipe.mvs_net is not None else "-"}}
    if no_depth:
        res["depth_frames_without_mvs"] = no_depth
    if dense:
        res["o2p_counts"] = dict(shell.o2p.counts)
    if loop is not None:
        res["loop"] = {k: int(v) for k, v in loops.items()}
    res.update(_evaluate(dataset, stamps, T_pub, final, mapper if mesh else None, out_dir))
    return res


def _evaluate(dataset: Path, stamps, T_pub, final, mapper, out_dir: Path | None) -> dict:
    """ATE of the causal and final trajectories, mesh metrics of the mapper's world mesh."""
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
    if mapper is not None and scene:
        from services.app.metrics.mesh import evaluate_points

        t0 = time.perf_counter()
        mapper.remesh(None)
        v, _ = mapper.world_mesh()
        if len(v) and "causal" in align:  # the estimate's W into the ground truth's frame (the causal alignment)
            ev = evaluate_points(align["causal"].apply(np.asarray(v, float)), _gt_points(scene[0]))
            res.update(accuracy_m=ev.accuracy_m, completeness=ev.completeness, completeness_5cm=ev.completeness_5cm,
                       mesh_points=ev.n_est, mesh_eval_s=round(time.perf_counter() - t0, 1))
        else:
            res["error_mesh"] = "no mesh vertices" if not len(v) else "no trajectory alignment"
        if len(v) and final is not None and "noncausal" in align:  # the map the mapping service writes at the end
            mapper.follow_trajectory(final.stamps_ns, final.T_WS)  # (mapping.follow_final)
            v, _ = mapper.world_mesh()
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
    if args.seconds < 0 or args.depth_every < 0 or args.heuristic_px <= 0:
        print("eval ablation: --seconds and --depth-every must be >= 0, --heuristic-px > 0", file=sys.stderr)
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
        stereo_cache: dict = {}  # per replica: stereo depth does not depend on the row
        for row in rows:
            path = rep_out / f"{row}.json"
            settings = {"seconds": args.seconds, "depth_every_arg": args.depth_every, "heuristic_px": args.heuristic_px,
                        "mesh": not args.no_mesh, "overrides": [*EVAL_DEFAULTS, *args.set, *row_overrides(row)]}
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
                r = run_row(row, dataset, args.set, args.seconds, args.depth_every, args.heuristic_px,
                            stereo_cache, not args.no_mesh, _Progress(prefix), rep_out / row)
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
                                                   "depth_every": args.depth_every, "set": args.set,
                                                   "heuristic_px": args.heuristic_px}, indent=1, default=float))
    table = table_markdown(results)
    (out / "table.md").write_text(table)
    print(table, flush=True)
    print(f"[eval ablation] wrote {out / 'table.md'} and {out / 'ablation.json'}", flush=True)
    return rc
