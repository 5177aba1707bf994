"""``sigmaslam run DATASET --out DIR [CONFIG] [--set k=v]``: the pipeline on one dataset, as real processes.

The services are those of ``supervisor.services`` (enabled ones; the recorder only with ``--record``; frontend
and backend when it names no pipeline service) plus
the player of DATASET (lockstep by default, ``--realtime`` plays at sensor rate), started by the same
:class:`services.supervisor.Supervisor` as ``sigmaslam up``, on a router at a free local port and a
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
- ``DIR/ate.json`` and a printed line when the dataset has ground truth (SE(3) alignment, tools/eval/ate.py),
  causal and non-causal;
- ``DIR/config.yaml``: the resolved config every service got.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import threading
import time
import uuid
from pathlib import Path

import numpy as np

from services.cli import SUBCOMMANDS
from services.loop.run_outputs import loop_summary, wait_final, write_final
from services.supervisor import ServiceSpec, Supervisor, validate
from services.system_config import load_system_config
from shared import topics
from shared.config import to_yaml
from shared.euroc import series_from_matrices, PoseSeries, read_trajectory, write_euroc_csv, write_tum
from transport.node import Node
from transport.queues import Empty
from transport.session import free_local_port

log = logging.getLogger("sigmaslam.run")

# used when the config lists no pipeline service (besides player and recorder)
MAPPING_STOP_TIMEOUT_S = 60.0  # SIGKILL a mapping service still writing its map only after this long
DEFAULT_PIPELINE = (ServiceSpec(name="frontend", argv=["frontend"]), ServiceSpec(name="backend", argv=["backend"]))

# per-frame stages whose medians add up to the estimator's cost per camera frame
FRAME_STAGES = (("frontend", "track"), ("backend", "optimise"))


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", help="EuRoC ASL folder (real or replica)")
    p.add_argument("config", nargs="?", help="YAML system config (default: built-in defaults)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    p.add_argument("--realtime", action="store_true", help="play at sensor rate instead of lockstep")
    p.add_argument("--rate", type=float, default=0.0, metavar="R",
                   help="play at R times sensor rate instead of lockstep (overrides --realtime; 0: off)")
    p.add_argument("--record", action="store_true", help="also record every topic to DIR/recording.mcap")
    p.add_argument("--player-arg", action="append", default=[], metavar="ARG",
                   help="extra argument for the player (repeatable), e.g. --player-arg=--max-frames=200")
    p.add_argument("--settle-s", type=float, default=5.0, help="after the player ended, stop when no state came "
                   "for this long [s]")
    p.add_argument("--timeout-s", type=float, default=0.0, help="give up after this long (0: no limit) [s]")
    p.add_argument("--final-timeout-s", type=float, default=600.0, help="wait this long for the back end's final "
                   "bundle adjustment (estimator/trajectory_final) after the stream ended [s]")


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
        elif s.argv[0] == "mapping":  # the map goes into the run folder: DIR/mesh.ply, DIR/submaps/, DIR/map.npz
            # stopped right after the final trajectory, which it meshes and writes: give it time to finish
            s = dataclasses.replace(s, argv=["mapping", "--out", str(out)],
                                    stop_timeout_s=s.stop_timeout_s or MAPPING_STOP_TIMEOUT_S)
        services.append(dataclasses.replace(s, restart="never"))
    mode = ["--rate", f"{rate:g}"] if rate > 0 else (["--realtime"] if realtime else ["--lockstep"])
    wait = ["--wait-for", ",".join(s.name for s in services)] if services else []
    services.append(ServiceSpec(name="player", argv=["player", dataset, *mode, *wait, *player_args], restart="never"))
    return services


@dataclasses.dataclass
class _Collector:
    states: list = dataclasses.field(default_factory=list)
    stats: dict = dataclasses.field(default_factory=dict)  # service -> last ServiceStats
    window_p50: dict = dataclasses.field(default_factory=dict)  # (service, stage) -> [p50 per stats message]
    end: object | None = None
    last_state_time: float = 0.0


def _collect(node: Node, col: _Collector, sup_thread: threading.Thread, settle_s: float, timeout_s: float) -> str:
    states = node.subscriber(topics.STATE, policy="all", depth=1_000_000)
    stats = node.subscriber(topics.STATS, policy="all", depth=10_000)
    ends = node.subscriber(topics.STREAM_END)
    t0 = time.monotonic()
    while not node.stopped:
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


def _trajectory(states) -> PoseSeries:
    good = [s for s in states if s.status not in ("initialising", "reset")]  # no pose in these
    stamps = np.array([s.header.stamp_ns for s in good], np.int64)
    order = np.argsort(stamps, kind="stable")
    T = np.array([s.T_WS for s in good]).reshape(-1, 4, 4)[order]
    return series_from_matrices(stamps[order], T)


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
                                 "queues": queues}
    per_frame = [out["services"].get(svc, {}).get("stages", {}).get(st, {}).get("median_of_window_p50_ms")
                 for svc, st in FRAME_STAGES]
    out["frontend_backend_median_ms"] = float(sum(per_frame)) if all(v is not None for v in per_frame) else None
    status = [s.status for s in col.states]
    out["states"] = {k: status.count(k) for k in sorted(set(status))}
    out["frames_sent"] = int(col.end.frames_sent) if col.end is not None else None
    return out


def _ground_truth(dataset: Path) -> Path | None:
    root = dataset / "mav0" if (dataset / "mav0").is_dir() else dataset
    gt = root / "state_groundtruth_estimate0" / "data.csv"
    return gt if gt.is_file() else None


def evaluate(traj: PoseSeries, gt_path: Path) -> dict:
    from tools.eval.ate import compute_ate

    gt = read_trajectory(gt_path)
    res = compute_ate(gt.stamps_ns, gt.p_WS, traj.stamps_ns, traj.p_WS, mode="se3")
    return {"ate_rmse_m": res.rmse_m, "ate_mean_m": res.mean_m, "ate_median_m": res.median_m,
            "ate_max_m": res.max_m, "matched": res.matched, "alignment": "se3", "groundtruth": str(gt_path)}


def main(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    dataset = str(Path(args.dataset).resolve())
    port = free_local_port()
    run_id = uuid.uuid4().hex[:8]
    overrides = [f"transport.namespace=sigmaslam/run-{run_id}", f"transport.connect=[tcp/127.0.0.1:{port}]",
                 f"transport.router_listen=[tcp/127.0.0.1:{port}]", *args.set]
    cfg = load_system_config(args.config, overrides)
    if not cfg.rig.calibration:
        cfg.rig.calibration = dataset
    cfg.supervisor.services = pipeline_services(cfg, dataset, out.resolve(), args.realtime, args.record,
                                                args.player_arg, getattr(args, "rate", 0.0))
    cfg.supervisor.start_router = True
    validate(cfg.supervisor, SUBCOMMANDS)
    config_path = (out / "config.yaml").resolve()
    config_path.write_text(to_yaml(cfg))
    sup = Supervisor(cfg.supervisor, config_path, out.resolve())
    names = [s.name for s in cfg.supervisor.services]
    print(f"[sigmaslam run] {dataset}: services {names}, namespace {cfg.transport.namespace}, port {port}", flush=True)
    col = _Collector()
    t_start = time.monotonic()
    with Node("run", cfg.transport) as node:
        # the supervisor's loop runs beside the collector; it starts the router and the services
        sup_thread = threading.Thread(target=sup.run, name="supervisor", daemon=True)
        finals = node.subscriber(topics.TRAJECTORY_FINAL)  # non-causal trajectory (services/loop)
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
    traj = _trajectory(col.states)
    for name in ("trajectory_causal", "trajectory"):
        write_tum(out / f"{name}.txt", traj)
        write_euroc_csv(out / f"{name}.csv", traj)
    summary = stats_summary(col)
    summary.update({"end_reason": why, "wall_s": wall, "poses": len(traj.stamps_ns)})
    final_traj = write_final(out, final) if final is not None else None
    if final is not None:
        summary["loops"] = loop_summary(final)
        print(f"[sigmaslam run] final trajectory: {summary['loops']}", flush=True)
    (out / "stats.json").write_text(json.dumps(summary, indent=2))
    print(f"[sigmaslam run] {why}: {len(traj.stamps_ns)} poses in {wall:.1f} s; frontend+backend median "
          f"{summary['frontend_backend_median_ms']} ms per frame; states {summary['states']}", flush=True)
    gt = _ground_truth(Path(dataset))
    rc = 0 if why == "done" else 1
    if gt is not None and len(traj.stamps_ns) >= 3:
        try:
            ate = evaluate(traj, gt)
        except ValueError as exc:
            print(f"[sigmaslam run] ATE not computed: {exc}", flush=True)
            return 1
        (out / "ate.json").write_text(json.dumps(ate, indent=2))
        print(f"[sigmaslam run] causal ATE (SE(3)) RMSE {ate['ate_rmse_m']:.4f} m over {ate['matched']} poses", flush=True)
        if final_traj is not None and len(final_traj.stamps_ns) >= 3:
            ate["non_causal"] = evaluate(final_traj, gt)
            (out / "ate.json").write_text(json.dumps(ate, indent=2))
            print(f"[sigmaslam run] non-causal ATE (SE(3)) RMSE {ate['non_causal']['ate_rmse_m']:.4f} m over "
                  f"{ate['non_causal']['matched']} poses", flush=True)
    elif len(traj.stamps_ns) < 3:
        rc = 1
    return rc
