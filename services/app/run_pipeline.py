"""The pipeline on one dataset as real processes, typed: :func:`run_pipeline` -> :class:`RunResult`.

``sigmaslam run`` (services/app/run_cmd.py), ``sigmaslam demo``, ``sigmaslam eval suite`` and the pipeline bench call
it. The services are those of ``supervisor.services`` (enabled ones; the recorder only with ``record``; the registry's
default pipeline, frontend and back end, when it names no pipeline process) plus the player of the dataset (lockstep
unless ``rate`` > 0), started by the same :class:`services.app.supervisor.Supervisor` as ``sigmaslam up``, on a router
at a free local port and a namespace of their own, so runs never cross ``sigmaslam up`` or each other. What the run
reads is :class:`services.app.run_collector.RunCollectorNode`; what it writes, services/app/run_outputs.py.
"""

from __future__ import annotations

import dataclasses
import json
import os
import threading
import time
import uuid
from pathlib import Path
from typing import Sequence

import numpy as np

from services.app import processes
from services.app.cli import command_names
from services.app.config import ServiceSpec
from services.app.run_collector import Collection, RunCollectorNode, collect, subscribe, wait_final
from services.app.run_outputs import (causal_trajectory, frame_comment, loop_summary, stats_summary, write_ate,
                                      write_final, write_occupancy_voxels, write_refined_extrinsics)
from services.app.supervisor import Supervisor, validate
from services.app.system_config import load_system_config
from shared.config import override, to_yaml
from shared.euroc import write_euroc_csv, write_tum
from shared.map_folder import UNALIGNED_FRAME
from transport.node import Node
from transport.session import free_local_port


@dataclasses.dataclass(frozen=True)
class RunResult:
    """What a run gave: its exit status (0: the stream was played to its end, poses came and the ATE was computed
    where there is ground truth), how it ended, and what it wrote to ``out``."""

    rc: int
    out: Path
    end_reason: str  # 'done', 'services exited', 'timeout', 'stopped'
    wall_s: float
    stats: dict  # stats.json
    ate: dict | None  # ate.json (None: no ground truth or too few poses)
    sampler: object | None = None  # the processes' CPU, memory and scheduling over the run (sample_processes=True):
    # services.app.metrics.processes.ProcessSampler (summary(), series())
    stage_dir: Path | None = None  # the services' per-item stage logs (stage_log)


def frames_within(dataset: Path, seconds: float) -> int:
    """Camera frames in the first ``seconds`` of the EuRoC folder ``dataset`` (0: all)."""
    root = Path(dataset) / "mav0" if (Path(dataset) / "mav0").is_dir() else Path(dataset)
    csv = root / "cam0" / "data.csv"
    if not csv.is_file():
        raise FileNotFoundError(f"{csv} not found: {dataset} is not an EuRoC ASL folder")
    stamps = np.array([int(line.split(",")[0]) for line in csv.read_text().splitlines()
                       if line.strip() and not line.startswith("#")], np.int64)
    if seconds <= 0:
        return len(stamps)
    return int(np.sum(stamps - stamps[0] <= int(seconds * 1e9)))


def services_overrides(services: str) -> list[str]:
    """The settings that run the processes of ``services`` (comma-separated commands, e.g. 'frontend,backend,depth';
    'config': those of the config) and give the mapping the time to write its map after SIGTERM."""
    out = ["supervisor.shutdown_timeout_s=120"]
    if services != "config":
        names = [s for s in services.split(",") if s]
        out.append("supervisor.services=[" + ", ".join(f"{{name: {s}, argv: [{s}]}}" for s in names) + "]")
    return out


def pipeline_services(cfg, dataset: str, out: Path, rate: float, record: bool,
                      player_args: Sequence[str]) -> list[ServiceSpec]:
    """The configured services with the player of ``dataset`` (replacing a configured one) appended; ``rate`` 0:
    the player in lockstep."""
    services = []
    configured = [s for s in cfg.supervisor.services if s.argv and s.argv[0] not in ("player", "record")]
    listed = cfg.supervisor.services if configured else [*processes.default_pipeline(), *cfg.supervisor.services]
    for s in [*listed, *processes.switched_on(cfg, listed)]:
        d = processes.by_command(s.argv[0]) if s.argv else None
        if not s.enabled or s.name == "player" or (d is not None and d.name == "player"):
            continue
        if d is not None and d.name == "recorder" and not record:
            continue
        if d is not None and d.output is not None:  # its output goes into the run folder
            s = dataclasses.replace(s, argv=(s.argv[0], "--out", str(out / d.output.in_run) if d.output.in_run
                                             else str(out)))
        services.append(dataclasses.replace(s, restart="never"))
    if record and not any(s.argv and s.argv[0] == "record" for s in services):  # asked for, but not configured
        services.append(ServiceSpec(name="recorder", argv=("record", "--out", str(out / "recording.mcap")),
                                    restart="never"))
    if cfg.ros2.input.enabled:  # the sensors come over ROS 2: the player is the stand-in robot
        player_args = ["--as-ros2", *player_args]
    mode = ["--rate", f"{rate:g}"] if rate > 0 else ["--lockstep"]
    # the player waits for each service's heartbeat, which carries its node's name
    wait = ["--wait-for", ",".join(processes.heartbeat_name(s.argv[0]) for s in services)] if services else []
    services.append(ServiceSpec(name="player", argv=("player", dataset, *mode, *wait, *player_args), restart="never"))
    return services


def _config(dataset: str, out: Path, config: str | None, sets: Sequence[str], rate: float, record: bool,
            player_args: Sequence[str], saved_map: str | None, localise_only: bool, gt: Path | None):
    """The run's system config: a private router and namespace, the saved map, the services, the run folder."""
    port = free_local_port()
    overrides = [f"transport.namespace=sigmaslam/run-{uuid.uuid4().hex[:8]}",
                 f"transport.connect=[tcp/127.0.0.1:{port}]", f"transport.router_listen=[tcp/127.0.0.1:{port}]",
                 *sets]
    if saved_map:
        overrides += [f"loop.prior_map={saved_map}", f"mapping.prior_map={saved_map}"]
    if localise_only:
        overrides.append("loop.localise_only=true")
    cfg = load_system_config(config, overrides)
    changes: dict = {"supervisor.services": pipeline_services(cfg, dataset, out, rate, record, player_args),
                     "supervisor.start_router": True}
    if not cfg.rig.calibration:
        changes["rig.calibration"] = dataset
    if not cfg.loop.map_output:  # the run's sparse map goes beside the mapping's dense one, in DIR/map/
        changes["loop.map_output"] = str(out)
    if rate <= 0:  # lockstep: reproducible, the fast path waits for windows
        changes["backend.fast_path_waits_for_window"] = True
    if gt is not None and not cfg.viewer.ground_truth:
        changes["viewer.ground_truth"] = str(gt)  # the viewer overlays it (green)
    return override(cfg, changes), port  # a changed copy: the loaded config is frozen


def run_pipeline(dataset: str | Path, out: str | Path, config: str | None = None, sets: Sequence[str] = (),
                 rate: float = 0.0, max_frames: int = 0, record: bool = False, saved_map: str | None = None,
                 localise_only: bool = False, gt: Path | None = None, player_args: Sequence[str] = (),
                 settle_s: float = 5.0, timeout_s: float = 0.0, final_timeout_s: float = 600.0,
                 stage_log: Path | None = None, sample_processes: bool = False) -> RunResult:
    """The pipeline on the EuRoC folder ``dataset`` into ``out`` with the system config ``config`` and ``sets``
    (``key=value``); ``rate``: times sensor rate (0: lockstep); ``max_frames`` > 0: play that many frames;
    ``saved_map``: localise in it (a run folder or its map/ folder; ``localise_only``: do not extend it); ``gt``:
    the ground truth of the ATE (None: none); ``settle_s``: after the player ended, stop when no state came for this
    long [s]; ``timeout_s`` > 0: give up after this long [s]; ``final_timeout_s``: wait this long for the final
    bundle adjustment [s]; ``stage_log``: a folder where every process logs each item of its stages (its per-item
    times); ``sample_processes``: sample the processes' CPU, memory and scheduling while the run lasts."""
    dataset, out = str(Path(dataset).resolve()), Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    if max_frames > 0:
        player_args = [*player_args, f"--max-frames={max_frames}"]
    cfg, port = _config(dataset, out, config, sets, rate, record, player_args, saved_map, localise_only, gt)
    validate(cfg.supervisor, command_names())
    config_path = out / "config.yaml"
    config_path.write_text(to_yaml(cfg))
    sup = Supervisor(cfg.supervisor, config_path, out)
    names = [s.name for s in cfg.supervisor.services]
    print(f"[sigmaslam run] {dataset}: services {names}, namespace {cfg.transport.namespace}, port {port}", flush=True)
    if any(s.argv and s.argv[0] == "viewer" for s in cfg.supervisor.services):
        print(f"[sigmaslam run] viewer at http://{cfg.viewer.host}:{cfg.viewer.port} while the pipeline runs", flush=True)
    col, t_start = Collection(), time.monotonic()
    with _measured(stage_log, sample_processes) as measured:
        why, final = _collect_run(cfg, sup, col, settle_s, timeout_s, final_timeout_s)
    return _write(out, cfg, col, why, final, time.monotonic() - t_start, bool(saved_map), gt, measured)


def _collect_run(cfg, sup: Supervisor, col: Collection, settle_s: float, timeout_s: float, final_timeout_s: float):
    """Start the services (the supervisor in a thread of its own), collect until the end, stop them; returns how the
    run ended and the final trajectory (None: none)."""
    final = None
    with Node(RunCollectorNode.name, cfg.transport, declared=RunCollectorNode) as node:
        queues = subscribe(node, col)
        sup_thread = threading.Thread(target=sup.run, name="supervisor", daemon=True)
        sup_thread.start()
        try:
            why = collect(node, col, queues, sup_thread, settle_s, timeout_s)
            if why == "done" and cfg.loop.enabled and cfg.loop.final_ba:
                print("[sigmaslam run] waiting for the final bundle adjustment", flush=True)
                final = wait_final(queues["finals"], final_timeout_s, lambda: node.stopped)
        finally:
            sup.request_stop()
            sup_thread.join(timeout=sup.cfg.longest_stop_s() + sup.cfg.shutdown_timeout_s + 5)
    return why, final


class _measured:
    """While the run lasts: each stage's items logged to ``stage_dir`` (the services inherit the environment) and,
    with ``sample``, the run's processes sampled."""

    def __init__(self, stage_dir: Path | None, sample: bool) -> None:
        self.stage_dir = None if stage_dir is None else Path(stage_dir).resolve()
        self.sample, self.sampler, self._old = sample, None, None

    def __enter__(self) -> "_measured":
        if self.stage_dir is not None:
            import shutil

            from transport.stats import STAGE_LOG_ENV

            shutil.rmtree(self.stage_dir, ignore_errors=True)
            self.stage_dir.mkdir(parents=True)
            self._old = os.environ.get(STAGE_LOG_ENV)
            os.environ[STAGE_LOG_ENV] = str(self.stage_dir)
        if self.sample:
            from services.app.metrics.processes import ProcessSampler

            self.sampler = ProcessSampler(0.5).start()
        return self

    def __exit__(self, *exc) -> None:
        if self.stage_dir is not None:
            from transport.stats import STAGE_LOG_ENV

            if self._old is None:
                os.environ.pop(STAGE_LOG_ENV, None)
            else:
                os.environ[STAGE_LOG_ENV] = self._old
        if self.sampler is not None:
            self.sampler.stop()


def _write(out: Path, cfg, col: Collection, why: str, final, wall: float, saved: bool, gt: Path | None,
           measured: _measured) -> RunResult:
    """The run's files (trajectories, stats.json, ate.json, refined extrinsics) and its closing lines."""
    traj, frame = causal_trajectory(col.states)
    comment = frame_comment(frame, saved)
    for name in ("trajectory_causal", "trajectory"):
        write_tum(out / f"{name}.txt", traj, comment)
        write_euroc_csv(out / f"{name}.csv", traj, comment)
    summary = stats_summary(col)
    summary.update({"end_reason": why, "wall_s": wall, "poses": len(traj.stamps_ns), "trajectory_frame": frame})
    final_traj = write_final(out, final, saved) if final is not None else None
    if final is not None:
        summary["final_trajectory_frame"] = final.header.frame_id
        summary["loops"] = loop_summary(final)
    if col.extrinsics is not None:
        summary["extrinsics_refined"] = write_refined_extrinsics(out, cfg.rig, col.extrinsics)
    if cfg.backend.estimate_time_offset and col.time_offset_s is not None:
        summary["time_offset_ms"] = 1e3 * col.time_offset_s
        print(f"[sigmaslam run] camera-IMU time offset estimated online: {1e3 * col.time_offset_s:+.2f} ms (an image "
              f"stamped t was taken at IMU time t + offset; Kalibr's timeshift_cam_imu)", flush=True)
    if final is not None:
        print(f"[sigmaslam run] final trajectory: {summary['loops']}", flush=True)
    (out / "stats.json").write_text(json.dumps(summary, indent=2))
    write_occupancy_voxels(out, cfg.mapping.query)
    _closing_lines(summary, traj, why, wall)
    rc, ate = (0 if why == "done" else 1), None
    if len(traj.stamps_ns) < 3:
        rc = 1
    elif gt is not None:
        try:
            ate = write_ate(out, traj, final_traj, gt)
        except ValueError as exc:
            print(f"[sigmaslam run] ATE not computed ({gt}): {exc}", flush=True)
            rc = 1
    return RunResult(rc, out, why, wall, summary, ate, measured.sampler, measured.stage_dir)


def _closing_lines(summary: dict, traj, why: str, wall: float) -> None:
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
    print(f"[sigmaslam run] {why}: {len(traj.stamps_ns)} poses in {wall:.1f} s "
          f"({summary['frames_without_state']} of {summary['frames_sent']} frames without a state); "
          f"frontend + fast path median {'n/a' if fb is None else f'{fb:.1f}'} ms per frame; {lat_text}; "
          f"states {summary['states']}", flush=True)
