"""``sigmaslam run DATASET --out DIR [CONFIG] [--set k=v]``: the pipeline on one dataset, as real processes.

The services are those of ``supervisor.services`` (enabled ones; the recorder only with ``--record``; frontend
and backend when it names no pipeline service) plus
the player of DATASET (lockstep by default, ``--realtime`` plays at sensor rate), started by the same
:class:`services.app.supervisor.Supervisor` as ``sigmaslam up``, on a router at a free local port and a
namespace of their own (so runs never cross ``sigmaslam up`` or each other). ``rig.calibration`` defaults
to DATASET. This process listens to estimator/state, stats/* and sensors/end; once the player has ended
and the last state is in (or no state came for ``--settle-s``), it stops the services and writes

- ``DIR/trajectory_causal.txt`` (TUM) and ``DIR/trajectory_causal.csv`` (EuRoC): each pose as published at its
  frame time, never revised; ``DIR/trajectory.txt`` / ``.csv`` are the same until a non-causal trajectory exists;
- ``DIR/stats.json``: per service and stage the whole-run count and overruns, the last window's p50/p99, and the
  median of the per-window medians over the run; queue drops; frontend+backend median per frame;
- ``DIR/trajectory_final.txt`` / ``.csv``: the non-causal trajectory (final bundle adjustment with loops, from
  ``estimator/trajectory_final``; ``loop.final_ba``), which then also becomes ``DIR/trajectory.txt``; loop counts
  in stats.json;
- ``DIR/ate.json`` and a printed line when there is ground truth (SE(3) alignment, shared/metrics/ate.py), causal
  and non-causal, over the poses that have a ground-truth pose within 10 ms (a ground truth that starts late or
  ends early only shortens the span; ate.json says how many poses and which span). The ground truth is
  ``--gt PATH`` (EuRoC CSV or TUM ``.txt``), else the first of :data:`GT_CANDIDATES` found in DATASET; it is also
  the viewer's overlay unless ``viewer.ground_truth`` is set;
- ``DIR/config.yaml``: the resolved config every service got;
- ``DIR/map/``: the saved map (docs/maps.md): ``sparse.npz`` from the back end (``loop.map_output``), ``dense.npz``
  from the mapping service.

``--map SAVED`` localises in a saved map (a run folder or its map/ folder): the back end relocalises against it and
publishes in its frame from then on; the states before (``header.frame_id`` ``odom``) are left out of the
trajectory files and counted in stats.json's ``localisation``; the mapping starts from the saved submaps; the map
written to ``DIR/map/`` is the saved one extended by this run (not with ``--localise-only``: no sparse map written).

``--serve-s S`` then shows the run's final map and trajectories in the web viewer for S seconds.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import logging
import threading
import time
import uuid
from pathlib import Path

import numpy as np

from services.app.cli import SUBCOMMANDS
from services.app.run_outputs import (frame_comment, loop_summary, wait_final, write_final,
                                     write_refined_extrinsics)
from services.app.supervisor import ServiceSpec, Supervisor, validate
from services.system_config import load_system_config
from shared import topics
from shared.config import override, to_yaml
from shared.map_folder import UNALIGNED_FRAME, sparse_path
from shared.euroc import series_from_matrices, PoseSeries, read_trajectory, write_euroc_csv, write_tum
from transport.node import Node
from services.app.metrics.latency import ArrivalLog, first_arrivals, matched_latencies, summary
from transport.queues import Empty
from transport.session import free_local_port

log = logging.getLogger("sigmaslam.run")

# used when the config lists no pipeline service (besides player and recorder)
MAPPING_STOP_TIMEOUT_S = 60.0  # SIGKILL a mapping service still writing its map only after this long
# subcommand -> the name its node's heartbeat carries, where the two differ
HEARTBEAT_NAMES = {"record": "recorder"}

DEFAULT_PIPELINE = (ServiceSpec(name="frontend", argv=["frontend"]), ServiceSpec(name="backend", argv=["backend"]))

# per-frame stages whose medians add up to the estimator's cost per camera frame: the frontend process's tracking
# and fast path (the back end's window optimisation runs beside them, at keyframes: reported on its own)
FRAME_STAGES = (("frontend", "track"),)

# where a dataset folder (the one holding mav0/, or mav0 itself) keeps its ground truth, in the order looked for:
# the ASL layout's own file, then a TUM or CSV file at the folder's top (what trimmed or converted folders carry)
GT_CANDIDATES = ("mav0/state_groundtruth_estimate0/data.csv", "groundtruth_tum.txt", "groundtruth.txt",
                 "groundtruth.csv")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", help="EuRoC ASL folder (real or replica; the folder holding mav0/, or mav0), or a ROS "
                   "bag (ROS 2 folder/.mcap/.db3, ROS 1 .bag: converted to DIR/dataset first, with --calib)")
    p.add_argument("config", nargs="?", help="YAML system config (default: built-in defaults); before or after "
                   "the options")
    p.add_argument("--gt", metavar="PATH", help="ground truth for the ATE: EuRoC CSV (state_groundtruth_estimate0 "
                   "or 8-column pose CSV, .xz ok) or TUM .txt (default: the first of "
                   f"{', '.join(GT_CANDIDATES)} in DATASET; none: no ATE)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    p.add_argument("--realtime", action="store_true", help="play at sensor rate instead of lockstep")
    p.add_argument("--rate", type=float, default=0.0, metavar="R",
                   help="play at R times sensor rate instead of lockstep (overrides --realtime; 0: off)")
    p.add_argument("--map", metavar="SAVED", default=None, help="localise in this saved map (a run's output folder "
                   "or its map/ folder): poses in its frame once relocalised; DIR/map/ then holds it extended")
    p.add_argument("--localise-only", action="store_true", help="with --map: do not extend the saved map (no "
                   "DIR/map/sparse.npz is written)")
    p.add_argument("--record", action="store_true", help="also record every topic to DIR/recording.mcap")
    p.add_argument("--ros2-bag", metavar="BAG", default=None, help="also write the results as a ROS 2 bag (MCAP "
                   "storage, standard messages: services/app/ros2_export.py) to the new folder BAG; implies --record")
    p.add_argument("--player-arg", action="append", default=[], metavar="ARG",
                   help="extra argument for the player (repeatable), e.g. --player-arg=--max-frames=200")
    p.add_argument("--settle-s", type=float, default=5.0, help="after the player ended, stop when no state came "
                   "for this long [s]")
    p.add_argument("--timeout-s", type=float, default=0.0, help="give up after this long (0: no limit) [s]")
    p.add_argument("--final-timeout-s", type=float, default=600.0, help="wait this long for the back end's final "
                   "bundle adjustment (estimator/trajectory_final) after the stream ended [s]")
    p.add_argument("--serve-s", type=float, default=0.0, help="after the run, show its final map and trajectories "
                   "in the web viewer (viewer.host:viewer.port) this long [s] (0: no)")
    from services.app.bag_input import add_bag_arguments

    add_bag_arguments(p)
    _intermixed(p)


def _intermixed(p: argparse.ArgumentParser) -> None:
    """Let CONFIG come after the options (``run DATASET --out DIR CONFIG``): argparse of Python 3.11 binds every
    positional at the first one (CONFIG to nothing) and then refuses a later CONFIG; intermixed parsing first
    takes the options, then the positionals. The subcommand parser is called through ``parse_known_args``."""
    plain = functools.partial(type(p).parse_known_args, p)

    def parse_known_args(args=None, namespace=None):
        p.parse_known_args = plain  # intermixed parsing calls parse_known_args itself
        try:
            return p.parse_known_intermixed_args(args, namespace)
        finally:
            p.parse_known_args = parse_known_args

    p.parse_known_args = parse_known_args


def pipeline_services(cfg, dataset: str, out: Path, realtime: bool, record: bool,
                      player_args: list[str], rate: float = 0.0) -> list[ServiceSpec]:
    """The configured services with the player of ``dataset`` (replacing a configured one) appended."""
    services = []
    configured = [s for s in cfg.supervisor.services if s.argv and s.argv[0] not in ("player", "record")]
    for s in (cfg.supervisor.services if configured else [*DEFAULT_PIPELINE, *cfg.supervisor.services]):
        if not s.enabled or s.name == "player" or (s.argv and s.argv[0] == "player"):
            continue
        if s.argv[0] == "record":
            if not record:
                continue
            s = dataclasses.replace(s, argv=["record", "--out", str(out / "recording.mcap")])
        elif s.argv[0] == "mapping":  # the map goes into the run folder: DIR/mesh.ply, DIR/submaps/, DIR/map/dense.npz
            # stopped right after the final trajectory, which it meshes and writes: give it time to finish
            s = dataclasses.replace(s, argv=["mapping", "--out", str(out)],
                                    stop_timeout_s=s.stop_timeout_s or MAPPING_STOP_TIMEOUT_S)
        services.append(dataclasses.replace(s, restart="never"))
    if record and not any(s.argv and s.argv[0] == "record" for s in services):  # asked for, but not configured
        services.append(ServiceSpec(name="recorder", argv=["record", "--out", str(out / "recording.mcap")],
                                    restart="never"))
    mode = ["--rate", f"{rate:g}"] if rate > 0 else (["--realtime"] if realtime else ["--lockstep"])
    # the player waits for each service's heartbeat, which carries its node's name, not the service's
    wait = ["--wait-for", ",".join(HEARTBEAT_NAMES.get(s.argv[0], s.argv[0]) for s in services)] if services else []
    services.append(ServiceSpec(name="player", argv=["player", dataset, *mode, *wait, *player_args], restart="never"))
    return services


@dataclasses.dataclass
class _Collector:
    states: list = dataclasses.field(default_factory=list)
    stats: dict = dataclasses.field(default_factory=dict)  # service -> last ServiceStats
    window_p50: dict = dataclasses.field(default_factory=dict)  # (service, stage) -> [p50 per stats message]
    end: object | None = None
    last_state_time: float = 0.0
    arrivals: ArrivalLog = dataclasses.field(default_factory=ArrivalLog)  # frame and state arrival times
    extrinsics: np.ndarray | None = None  # (C,4,4) the newest refined T_SC (backend.refine_extrinsics), else None
    time_offset_s: float | None = None  # the newest camera-IMU time offset estimate (backend.estimate_time_offset)

    def on_window(self, msg) -> None:
        if len(msg.T_SC):
            self.extrinsics = np.array(msg.T_SC, float)
        if msg.status not in ("initialising", "reset"):
            self.time_offset_s = float(msg.time_offset_s)


PROGRESS_EVERY_S = 10.0  # wall time between two progress lines of a run [s]


def progress_line(col: _Collector, elapsed_s: float) -> str:
    """What a run has received so far: states by status and how far into the sequence the last one is."""
    if not col.states:
        return f"{elapsed_s:.0f} s: no state yet (services starting, or the back end initialising)"
    status = [s.status for s in col.states]
    counts = ", ".join(f"{k} {status.count(k)}" for k in sorted(set(status)))
    span_s = (col.states[-1].header.stamp_ns - col.states[0].header.stamp_ns) * 1e-9
    return f"{elapsed_s:.0f} s: {len(col.states)} states ({counts}), {span_s:.1f} s into the sequence"


def _collect(node: Node, col: _Collector, sup_thread: threading.Thread, settle_s: float, timeout_s: float) -> str:
    states = node.subscriber(topics.STATE, policy="all", depth=1_000_000)
    # arrival times for the pose latency (sensor publication -> estimator/state), in the Zenoh threads
    node.subscriber(topics.FRAME, policy="latest", depth=1, handler=col.arrivals.handler("frame"))
    node.subscriber(topics.STATE, policy="latest", depth=1, handler=col.arrivals.handler("state"))
    stats = node.subscriber(topics.STATS, policy="all", depth=10_000)
    ends = node.subscriber(topics.STREAM_END)
    node.subscriber(topics.WINDOW, policy="latest", depth=1, handler=col.on_window)
    t0 = next_report = time.monotonic()
    while not node.stopped:
        if time.monotonic() >= next_report:  # a line now and then, so a long run is never silent
            if next_report > t0:
                print(f"[sigmaslam run] {progress_line(col, time.monotonic() - t0)}", flush=True)
            next_report += PROGRESS_EVERY_S
        for s in stats.drain():
            col.stats[s.service] = s
            for name, p50, n in zip(s.stage_names, s.stage_p50_ms, s.stage_count):
                if n > 0 and np.isfinite(p50):
                    col.window_p50.setdefault((s.service, name), []).append(float(p50))
        for e in ends.drain():
            if e.source == "player" and col.end is None:
                col.end = e
                col.last_state_time = max(col.last_state_time, time.monotonic())
                print(f"[sigmaslam run] player ended after {e.frames_sent} frames", flush=True)
        try:
            st = states.get(timeout=0.05)
            col.states.append(st)
            col.last_state_time = time.monotonic()
            for st in states.drain():
                col.states.append(st)
        except Empty:
            pass
        now = time.monotonic()
        if col.end is not None:
            last = col.states[-1].header.stamp_ns if col.states else -1
            if last >= col.end.header.stamp_ns > 0 or now - col.last_state_time > settle_s:
                node.wait(1.5)  # one more stats period
                for s in stats.drain():
                    col.stats[s.service] = s
                return "done"
        if not sup_thread.is_alive():
            return "services exited"
        if timeout_s > 0 and now - t0 > timeout_s:
            return "timeout"
    return "stopped"


def _trajectory(states) -> tuple[PoseSeries, str]:
    """The causal trajectory to write and its frame. No pose in 'initialising' and 'reset'. A run localising in a
    saved map publishes in its own frame (:data:`UNALIGNED_FRAME`) until it relocalises and in the map's ('W') from
    then on: the trajectory is its states in the map's frame, or, when it never relocalised, all its states in its
    own frame, so that no run loses its trajectory."""
    posed = [s for s in states if s.status not in ("initialising", "reset")]
    good, frame = [s for s in posed if s.header.frame_id != UNALIGNED_FRAME], "W"
    if not good and posed:
        good, frame = posed, UNALIGNED_FRAME
    stamps = np.array([s.header.stamp_ns for s in good], np.int64)
    order = np.argsort(stamps, kind="stable")
    T = np.array([s.T_WS for s in good]).reshape(-1, 4, 4)[order]
    return series_from_matrices(stamps[order], T), frame


def stats_summary(col: _Collector) -> dict:
    out: dict = {"services": {}}
    for name, s in col.stats.items():
        stages = {}
        for k, st in enumerate(s.stage_names):
            w = col.window_p50.get((name, st), [])
            stages[st] = {"count": int(s.stage_count[k]), "overruns": int(s.stage_overruns[k]),
                          "budget_ms": float(s.stage_budget_ms[k]), "last_window_p50_ms": float(s.stage_p50_ms[k]),
                          "last_window_p99_ms": float(s.stage_p99_ms[k]),
                          "median_of_window_p50_ms": float(np.median(w)) if w else float("nan")}
        queues = {q: {"received": int(s.queue_received[k]), "dropped": int(s.queue_dropped[k])}
                  for k, q in enumerate(s.queue_names)}
        out["services"][name] = {"uptime_s": float(s.uptime_s), "rss_mb": float(s.rss_mb), "stages": stages,
                                 "queues": queues,
                                 "counters": {c: int(v) for c, v in zip(s.counter_names, s.counter_values)}}
    per_frame = [out["services"].get(svc, {}).get("stages", {}).get(st, {}).get("median_of_window_p50_ms")
                 for svc, st in FRAME_STAGES]
    out["frontend_backend_median_ms"] = float(sum(per_frame)) if all(v is not None for v in per_frame) else None
    status = [s.status for s in col.states]
    out["states"] = {k: status.count(k) for k in sorted(set(status))}
    out["frames_sent"] = int(col.end.frames_sent) if col.end is not None else None
    published = first_arrivals(*col.arrivals.get("frame"))
    lat = matched_latencies(published, *col.arrivals.get("state"))
    out["state_latency_ms"] = summary(lat["latency_ms"])  # sensor publication -> estimator/state, per frame
    answered = {int(s.header.stamp_ns) for s in col.states}  # any status: the estimator answered the frame
    out["frames_without_state"] = (None if out["frames_sent"] is None
                                   else max(0, out["frames_sent"] - len(answered)))
    out["drops"] = {f"{svc}:{q}": v["dropped"] for svc, d in out["services"].items()
                    for q, v in d["queues"].items() if v["dropped"]}
    px = out["services"].get("depth", {}).get("counters", {})
    n_px = px.get("confident_pixels", 0) + px.get("uncertain_pixels", 0)
    out["depth_uncertain_fraction"] = px.get("uncertain_pixels", 0) / n_px if n_px else None
    out["localisation"] = localisation_summary(col.states)
    return out



def localisation_summary(states) -> dict | None:
    """How a run localising in a saved map got there: states before and after its relocalisation, and the sensor
    time from the first state to the first one in the map's frame (None for a run without a saved map)."""
    posed = [s for s in states if s.status not in ("initialising", "reset")]
    before = sum(s.header.frame_id == UNALIGNED_FRAME for s in posed)
    if not before:
        return None
    in_map = [s for s in posed if s.header.frame_id != UNALIGNED_FRAME]
    first = int(states[0].header.stamp_ns)
    return {"states_before_relocalisation": before, "states_in_map_frame": len(in_map),
            "time_to_relocalise_s": (int(in_map[0].header.stamp_ns) - first) * 1e-9 if in_map else None}


def find_ground_truth(dataset: Path) -> Path | None:
    """The first of :data:`GT_CANDIDATES` in ``dataset`` (the folder holding mav0/, or mav0 itself), or None."""
    root = dataset / "mav0" if (dataset / "mav0").is_dir() else dataset  # the reader's root (mav0 or its content)
    base = root.parent if root.name == "mav0" else root
    paths = [root / "state_groundtruth_estimate0" / "data.csv", *(base / c for c in GT_CANDIDATES[1:])]
    return next((q for q in paths if q.is_file()), None)


def evaluate(traj: PoseSeries, gt_path: Path) -> dict:
    """SE(3)-aligned ATE of ``traj`` over its poses that have a ground-truth pose within 10 ms (the overlap)."""
    from shared.metrics.ate import compute_ate

    gt = read_trajectory(gt_path)
    res = compute_ate(gt.stamps_ns, gt.p_WS, traj.stamps_ns, traj.p_WS, mode="se3")
    return {"ate_rmse_m": res.rmse_m, "ate_mean_m": res.mean_m, "ate_median_m": res.median_m,
            "ate_max_m": res.max_m, "matched": res.matched, "poses": len(traj.stamps_ns),
            "matched_span_ns": [int(res.stamps_ns[0]), int(res.stamps_ns[-1])],
            "groundtruth_span_ns": [int(gt.stamps_ns[0]), int(gt.stamps_ns[-1])],
            "alignment": "se3", "groundtruth": str(gt_path)}


def _ate_line(kind: str, ate: dict) -> str:
    t0, t1 = ate["matched_span_ns"]
    return (f"[sigmaslam run] {kind} ATE (SE(3)) RMSE {ate['ate_rmse_m']:.4f} m over {ate['matched']} of "
            f"{ate['poses']} poses ({(t1 - t0) * 1e-9:.1f} s with ground truth)")


def _bag_dataset(args: argparse.Namespace, out: Path) -> str:
    """A ROS bag converted to OUT/dataset (an EuRoC folder; reused when it is already there)."""
    from services.app.bag_input import bag_to_euroc

    dst = out / "dataset"
    if (dst / "mav0").is_dir():
        print(f"[sigmaslam run] {args.dataset}: using the conversion already in {dst}", flush=True)
    else:
        counts = bag_to_euroc(args.dataset, dst, getattr(args, "calib", None), getattr(args, "imu_calib", None),
                              getattr(args, "cam", None), getattr(args, "imu", None),
                              getattr(args, "sync_tolerance_ms", 2.0))
        print(f"[sigmaslam run] converted {args.dataset} -> {dst}: " + ", ".join(f"{k} {v}" for k, v in counts.items()),
              flush=True)
    return str(dst.resolve())


def main(args: argparse.Namespace) -> int:
    from shared.euroc_reader import DatasetError
    from shared.ros_bag import is_ros_bag

    out = Path(args.out)
    dataset = str(Path(args.dataset).resolve())
    if is_ros_bag(dataset):
        out.mkdir(parents=True, exist_ok=True)
        try:
            dataset = _bag_dataset(args, out)
        except (DatasetError, OSError) as exc:
            print(f"sigmaslam run: {exc}", flush=True)
            return 2
    gt_arg = getattr(args, "gt", None)
    if gt_arg and gt_arg != "none" and not Path(gt_arg).is_file():
        print(f"sigmaslam run: --gt {gt_arg}: file not found", flush=True)
        return 2
    gt = (None if gt_arg == "none" else Path(gt_arg).resolve()) if gt_arg else find_ground_truth(Path(dataset))
    out.mkdir(parents=True, exist_ok=True)
    port = free_local_port()
    run_id = uuid.uuid4().hex[:8]
    overrides = [f"transport.namespace=sigmaslam/run-{run_id}", f"transport.connect=[tcp/127.0.0.1:{port}]",
                 f"transport.router_listen=[tcp/127.0.0.1:{port}]", *args.set]
    saved = getattr(args, "map", None)
    if saved:
        if not sparse_path(saved).is_file():
            print(f"sigmaslam run: --map {saved}: no saved map there ({sparse_path(saved)} not found)", flush=True)
            return 2
        saved = str(Path(saved).resolve())
        overrides += [f"loop.prior_map={saved}", f"mapping.prior_map={saved}"]
    if getattr(args, "localise_only", False):
        if not saved:
            print("sigmaslam run: --localise-only needs --map", flush=True)
            return 2
        overrides.append("loop.localise_only=true")
    cfg = load_system_config(args.config, overrides)
    if getattr(args, "ros2_bag", None):
        args.record = True
    changes: dict = {"supervisor.services": pipeline_services(cfg, dataset, out.resolve(), args.realtime, args.record,
                                                              args.player_arg, getattr(args, "rate", 0.0)),
                     "supervisor.start_router": True}
    if not cfg.rig.calibration:
        changes["rig.calibration"] = dataset
    if not cfg.loop.map_output:  # the run's sparse map goes beside the mapping's dense one, in DIR/map/
        changes["loop.map_output"] = str(out.resolve())
    if not (args.realtime or getattr(args, "rate", 0.0) > 0):  # lockstep: reproducible, the fast path waits for windows
        changes["backend.fast_path_waits_for_window"] = True
    if gt is not None and not cfg.viewer.ground_truth:
        changes["viewer.ground_truth"] = str(gt)  # the viewer overlays it (green)
    cfg = override(cfg, changes)  # a changed copy: the loaded config is frozen
    validate(cfg.supervisor, SUBCOMMANDS)
    config_path = (out / "config.yaml").resolve()
    config_path.write_text(to_yaml(cfg))
    sup = Supervisor(cfg.supervisor, config_path, out.resolve())
    names = [s.name for s in cfg.supervisor.services]
    print(f"[sigmaslam run] {dataset}: services {names}, namespace {cfg.transport.namespace}, port {port}", flush=True)
    url = f"http://{cfg.viewer.host}:{cfg.viewer.port}"
    if any(s.argv and s.argv[0] == "viewer" for s in cfg.supervisor.services):
        print(f"[sigmaslam run] viewer at {url} while the pipeline runs", flush=True)
    col = _Collector()
    t_start = time.monotonic()
    with Node("run", cfg.transport) as node:
        # the supervisor's loop runs beside the collector; it starts the router and the services
        sup_thread = threading.Thread(target=sup.run, name="supervisor", daemon=True)
        finals = node.subscriber(topics.TRAJECTORY_FINAL)  # non-causal trajectory (services/backend/loop)
        final = None
        sup_thread.start()
        try:
            why = _collect(node, col, sup_thread, args.settle_s, args.timeout_s)
            if why == "done" and cfg.loop.enabled and cfg.loop.final_ba:
                print("[sigmaslam run] waiting for the final bundle adjustment", flush=True)
                final = wait_final(finals, args.final_timeout_s, lambda: node.stopped)
        finally:
            sup.request_stop()
            sup_thread.join(timeout=cfg.supervisor.longest_stop_s() + cfg.supervisor.shutdown_timeout_s + 5)
    wall = time.monotonic() - t_start
    traj, frame = _trajectory(col.states)
    comment = frame_comment(frame, bool(saved))
    for name in ("trajectory_causal", "trajectory"):
        write_tum(out / f"{name}.txt", traj, comment)
        write_euroc_csv(out / f"{name}.csv", traj, comment)
    summary = stats_summary(col)
    summary.update({"end_reason": why, "wall_s": wall, "poses": len(traj.stamps_ns), "trajectory_frame": frame})
    final_traj = write_final(out, final, bool(saved)) if final is not None else None
    if final is not None:
        summary["final_trajectory_frame"] = final.header.frame_id
    if col.extrinsics is not None:
        summary["extrinsics_refined"] = write_refined_extrinsics(out, cfg.rig, col.extrinsics)
    if cfg.backend.estimate_time_offset and col.time_offset_s is not None:
        summary["time_offset_ms"] = 1e3 * col.time_offset_s
        print(f"[sigmaslam run] camera-IMU time offset estimated online: {1e3 * col.time_offset_s:+.2f} ms (an image "
              f"stamped t was taken at IMU time t + offset; Kalibr's timeshift_cam_imu)", flush=True)
    if final is not None:
        summary["loops"] = loop_summary(final)
        print(f"[sigmaslam run] final trajectory: {summary['loops']}", flush=True)
    (out / "stats.json").write_text(json.dumps(summary, indent=2))
    if (loc := summary["localisation"]) is not None:
        t = loc["time_to_relocalise_s"]
        if t is not None:
            print(f"[sigmaslam run] saved map: relocalised {t:.1f} s into the run; {loc['states_in_map_frame']} "
                  f"states in the map's frame (the trajectory files), {loc['states_before_relocalisation']} before "
                  "(in the run's own frame 'odom', not written)", flush=True)
        else:
            print(f"[sigmaslam run] saved map: this run never relocalised in it, so it did not join the map; its "
                  f"trajectory files hold its {loc['states_before_relocalisation']} states in its own frame "
                  f"'{UNALIGNED_FRAME}' (its first pose's), not the map's", flush=True)
    lat = summary["state_latency_ms"]
    lat_text = f"pose latency p50 {lat['median']:.0f} ms, p99 {lat['p99']:.0f} ms" if lat.get("n") else "no latency"
    fb = summary["frontend_backend_median_ms"]
    fb_text = "n/a" if fb is None else f"{fb:.1f}"
    print(f"[sigmaslam run] {why}: {len(traj.stamps_ns)} poses in {wall:.1f} s "
          f"({summary['frames_without_state']} of {summary['frames_sent']} frames without a state); "
          f"frontend + fast path median {fb_text} ms per frame; {lat_text}; "
          f"states {summary['states']}", flush=True)
    rc = 0 if why == "done" else 1
    if len(traj.stamps_ns) < 3:
        rc = 1
    elif gt is not None:
        try:
            _write_ate(out, traj, final_traj, gt)
        except ValueError as exc:
            print(f"[sigmaslam run] ATE not computed ({gt}): {exc}", flush=True)
            rc = 1
    elif gt_arg != "none":
        print("[sigmaslam run] no ground truth (none of " + ", ".join(GT_CANDIDATES) + " in the dataset, no --gt): "
              "no ATE", flush=True)
    if getattr(args, "ros2_bag", None):
        from services.app.ros2_export import recording_to_ros2

        try:
            counts = recording_to_ros2(out / "recording.mcap", args.ros2_bag)
            print(f"[sigmaslam run] ROS 2 bag {args.ros2_bag}: " + ", ".join(f"{k} {v}" for k, v in counts.items()),
                  flush=True)
        except (OSError, ValueError) as exc:
            print(f"[sigmaslam run] ROS 2 bag not written: {exc}", flush=True)
            rc = 1
    if getattr(args, "serve_s", 0.0) > 0:
        from services.app.demo_serve import serve_run

        print(f"[sigmaslam run] serving the final map at {url} for {args.serve_s:.0f} s (Ctrl-C stops)", flush=True)
        serve_run(out, args.config, [*([f"viewer.ground_truth={gt}"] if gt else []), *args.set], args.serve_s)
    return rc


def _write_ate(out: Path, traj: PoseSeries, final_traj: PoseSeries | None, gt: Path) -> None:
    """DIR/ate.json (causal, and non-causal when there is a final trajectory) and their printed lines."""
    ate = evaluate(traj, gt)
    (out / "ate.json").write_text(json.dumps(ate, indent=2))
    print(_ate_line("causal", ate), flush=True)
    if final_traj is not None and len(final_traj.stamps_ns) >= 3:
        ate["non_causal"] = evaluate(final_traj, gt)
        (out / "ate.json").write_text(json.dumps(ate, indent=2))
        print(_ate_line("non-causal", ate["non_causal"]), flush=True)
