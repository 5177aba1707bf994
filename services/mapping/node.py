"""Occupancy submapping as a transport-free process node (run by ``sigmaslam mapping``, services/mapping/service.py).

Subscribes ``mapping.depth_topic`` (depth/fused or depth/stereo), ``estimator/state`` (buffered by
stamp), ``estimator/keyframes`` (submap poses follow them) and ``estimator/trajectory_final`` (after the
stream, with ``follow_final``, every submap moves onto the non-causal trajectory). Each depth frame is integrated at
``T_WC = T_WS(stamp) T_SC`` (or at its own T_WC when ``pose_source: frame`` and it is not identity);
a frame whose state has not arrived waits up to ``pose_wait_s`` and is then dropped (counted); a frame whose state
said it has no pose (the estimator was initialising or had just restarted) will never get one and is skipped at once
(counted apart, as ``skipped_no_estimate``: not a frame the mapping lost).
Changed submaps are re-meshed within a time budget at most every ``mesh_period_s`` and published on
``map/submap``; a submap that moved is re-published with its new pose. The near-surface field of a
submap (``OccupancyField`` on ``map/field``, for the occupancy-to-point factors) goes out when the
submap closes, and for the current submap every ``field_period_s``. When the final trajectory has been
applied (the stream is over) and again at exit (SIGTERM/SIGINT) if anything changed since, the map is
meshed completely, published, and, if ``output_dir`` is set, written there: ``mesh.ply``
(world), ``submaps/submap_NNN.ply`` (each in its own frame M), ``map/dense.npz`` and ``mapping.json``. Writing
at the final trajectory keeps the finished map on disk even when the process is stopped hard soon after. With an
output folder, ``map/dense.npz`` is also checkpointed every ``checkpoint_period_s`` (a snapshot written by a thread of
its own, atomic rename); a service
restarted by the supervisor resumes from that checkpoint (see :func:`resume_map`, docs/reliability.md).
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import threading
import time
from pathlib import Path

import numpy as np

from services.mapping.config import MappingConfig
from services.mapping.io import MapFileError, load_map, map_arrays, save_map, write_map_arrays, write_ply
from shared.map_folder import DENSE_FILE, dense_path, remove_stale_temps, run_map_dir
from shared.occupancy.o2p_points import SubmapPointPool
from services.mapping.poses import PoseBuffer
from services.mapping.submaps import SubmapMapper
from shared.supervision import restart_count
from shared import messages, topics
from shared.codec import Header
from shared.dataflow import Emit, Input, ProcessNode

log = logging.getLogger("sigmaslam.mapping")


class MappingLoop:
    """The service's state between messages; transport-free so that it reads as the algorithm's shell."""

    def __init__(self, cfg: MappingConfig) -> None:
        self.cfg = cfg
        self.mapper = SubmapMapper(cfg.sensor, cfg.submaps)
        self.poses = PoseBuffer(cfg.state_buffer)
        self.waiting: collections.deque[tuple[float, messages.DepthFrame]] = collections.deque(maxlen=32)
        # stamps whose state was a placeholder without a pose (initialising, reset): their frames never get one
        self.unposed: collections.deque[int] = collections.deque(maxlen=256)
        self.counts = collections.Counter()
        self.integrate_ms: list[float] = []
        self.to_publish: set[int] = set()
        self.fields_to_publish: set[int] = set()
        self.reset_pending = False
        # map-to-map points (shared/occupancy/o2p_points.py), published once per closed submap
        self.points = SubmapPointPool(cfg.o2p_points) if cfg.o2p_points > 0 else None
        self.points_to_publish: set[int] = set()
        self.unflushed = True  # the map changed since it was last completely published and written

    def on_state(self, msg: messages.EstimatorState) -> None:
        if msg.status == "reset":  # a restarted back end: new world frame and keyframe ids
            self.poses = PoseBuffer(self.cfg.state_buffer)  # forget the old frame's poses (atomic swap)
            self.reset_pending = True  # submaps are frozen in the main loop
        if msg.status in ("initialising", "reset"):  # placeholders without a pose
            self.counts["states_without_pose"] += 1
            self.unposed.append(int(msg.header.stamp_ns))
            return
        self.poses.add(msg.header.stamp_ns, msg.T_WS)

    def on_keyframes(self, msg: messages.Keyframes) -> None:
        moved = self.mapper.update_keyframes(msg.ids, msg.stamps_ns, msg.T_WS)
        self.to_publish.update(moved)
        self.unflushed |= bool(moved)

    def on_final(self, msg: messages.FinalTrajectory) -> None:
        """The non-causal trajectory: submaps follow it (``mapping.follow_final``); counted."""
        if not self.cfg.follow_final:
            return
        moved = self.mapper.follow_trajectory(msg.stamps_ns, msg.T_WS)
        self.to_publish.update(moved)
        self.unflushed |= bool(moved)
        self.counts["final_trajectories"] += 1
        log.info("final trajectory: %d of %d submaps moved onto it", len(moved), len(self.mapper.submaps))

    def on_depth(self, msg: messages.DepthFrame) -> None:
        if len(self.waiting) == self.waiting.maxlen:
            self.counts["dropped_waiting_full"] += 1
        self.waiting.append((time.monotonic(), msg))

    def _pose(self, msg: messages.DepthFrame) -> np.ndarray | None:
        if self.cfg.pose_source == "frame" and not np.allclose(msg.T_WC, np.eye(4)):
            return np.asarray(msg.T_WC, float)
        T_WS = self.poses.lookup(msg.header.stamp_ns, int(self.cfg.pose_tolerance_ms * 1e6), int(self.cfg.max_interp_gap_ms * 1e6))
        return None if T_WS is None else T_WS @ np.asarray(msg.T_SC, float)

    def process_waiting(self, timer=None) -> int:
        """Integrate every waiting frame whose pose is known; drop those that waited too long."""
        if self.reset_pending:
            self.reset_pending = False
            self.mapper.estimator_reset()
            self.unflushed = True
            self.counts["estimator_resets"] += 1
            log.warning("estimator reset: submaps so far frozen, the next frame starts a new submap")
        done = 0
        keep: collections.deque = collections.deque(maxlen=self.waiting.maxlen)
        while self.waiting:
            t_rx, msg = self.waiting.popleft()
            T_WC = self._pose(msg)
            if T_WC is None:
                if msg.header.stamp_ns in self.unposed:  # the estimator said it has no pose for this stamp
                    self.counts["skipped_no_estimate"] += 1
                elif time.monotonic() - t_rx > self.cfg.pose_wait_s:
                    self.counts["dropped_no_pose"] += 1
                    log.warning("depth frame %d dropped: no estimator state for its stamp", msg.header.stamp_ns)
                else:
                    keep.append((t_rx, msg))
                continue
            t0 = time.perf_counter()
            try:
                if timer is not None:
                    with timer:
                        rep = self.mapper.integrate(msg.depth, msg.sigma, msg.K, T_WC, msg.T_SC, msg.header.stamp_ns)
                else:
                    rep = self.mapper.integrate(msg.depth, msg.sigma, msg.K, T_WC, msg.T_SC, msg.header.stamp_ns)
            except ValueError as exc:
                self.counts["dropped_bad_frame"] += 1
                log.warning("depth frame %d dropped: %s", msg.header.stamp_ns, exc)
                continue
            self.integrate_ms.append(1e3 * (time.perf_counter() - t0))
            self.unflushed = True
            self.counts["integrated"] += 1
            if self.points is not None:
                T_WM = self.mapper.submaps[rep.submap_id].T_WM
                self.points.add(rep.submap_id, msg.depth, msg.sigma, msg.K, np.linalg.inv(T_WM) @ T_WC)
            if rep.new_submap:
                self.counts["submaps"] += 1
                if rep.submap_id > 0:
                    self.fields_to_publish.add(rep.submap_id - 1)  # closed: its field is final
                    self.points_to_publish.add(rep.submap_id - 1)
                log.info("submap %d started (overlap %.2f)", rep.submap_id, rep.overlap)
            done += 1
        self.waiting = keep
        return done

    def remesh(self, budget_s: float | None) -> None:
        self.to_publish.update(self.mapper.remesh(budget_s))

    def submap_messages(self) -> list[messages.SubmapMesh]:
        out = []
        for sid in sorted(self.to_publish):
            sm = self.mapper.submaps[sid]
            if self.cfg.vertex_colors:
                v, f, c = self.mapper.colored_mesh(sm)
            else:
                (v, f), c = sm.mesher.mesh(), np.empty((0, 3), np.uint8)
            out.append(messages.SubmapMesh(header=Header(stamp_ns=sm.anchor_stamp_ns, frame_id=f"M{sm.id}"), submap_id=sm.id,
                                           T_WM=sm.T_WM, vertices_M=v, faces=f, vertex_colors=c))
        self.to_publish.clear()
        return out

    def field_messages(self) -> list[messages.OccupancyField]:
        from services.mapping.export import field_message

        out = [field_message(self.mapper.submaps[i], self.cfg.sensor.l_min) for i in sorted(self.fields_to_publish)]
        self.fields_to_publish.clear()
        return out

    def points_messages(self) -> list[messages.SubmapPoints]:
        out = []
        for sid in sorted(self.points_to_publish):
            got = self.points.pop(sid) if self.points is not None else None
            if got is not None:
                sm = self.mapper.submaps[sid]
                out.append(messages.SubmapPoints(header=Header(stamp_ns=sm.anchor_stamp_ns, frame_id=f"M{sid}"),
                                                 submap_id=sid, points_M=got[0].astype(np.float32),
                                                 sigma=got[1].astype(np.float32)))
        self.points_to_publish.clear()
        return out

    def write_outputs(self, out_dir: Path, report_only: bool = False) -> None:
        """The map (mesh.ply, submaps/, map/dense.npz) and mapping.json; with ``report_only`` only mapping.json."""
        out_dir.mkdir(parents=True, exist_ok=True)
        if not report_only:
            v, f = self.mapper.world_mesh()
            write_ply(out_dir / "mesh.ply", v, f)
            for sm in self.mapper.submaps:
                sv, sf = sm.mesher.mesh()
                write_ply(out_dir / "submaps" / f"submap_{sm.id:03d}.ply", sv, sf)
            save_map(self.mapper, run_map_dir(out_dir) / DENSE_FILE)
        ms = np.array(self.integrate_ms) if self.integrate_ms else np.array([np.nan])
        report = {"counts": dict(self.counts), "integrate_ms_p50": float(np.median(ms)),
                  "integrate_ms_p90": float(np.percentile(ms, 90)), "map_bytes": self.mapper.nbytes(),
                  "submaps": [{"id": sm.id, "bytes": sm.store.nbytes(), "blocks": sm.store.n_blocks,
                               "refined_blocks": sm.store.n_refined - len(sm.store.free_rows), "frames": sm.n_frames,
                               "T_WM": sm.T_WM.tolist(), "keyframe_id": sm.keyframe_id} for sm in self.mapper.submaps]}
        (out_dir / "mapping.json").write_text(json.dumps(report, indent=1))


def resume_map(loop: MappingLoop, out_dir: str | None) -> bool:
    """After a supervisor restart (``$SIGMASLAM_RESTARTS`` > 0), continue from the last checkpoint
    ``<out_dir>/map/dense.npz``: same submaps, ids continue, everything is re-meshed and re-published. A first
    start, or a restart without a readable checkpoint, begins an empty map (logged)."""
    if out_dir:
        for tmp in remove_stale_temps(run_map_dir(out_dir)):
            log.warning("removed %s, left by a save that was killed", tmp)
    if restart_count() <= 0 or not out_dir:
        return False
    path = run_map_dir(out_dir) / DENSE_FILE
    try:
        loop.mapper = load_map(path)
    except (MapFileError, FileNotFoundError) as exc:
        log.warning("mapping restarted without a usable checkpoint (%s): starting an empty map", exc)
        loop.counts["resumed"] = 0
        return False
    loop.mapper.remesh(None)
    loop.to_publish.update(sm.id for sm in loop.mapper.submaps)
    loop.counts["resumed"] = 1
    log.warning("mapping restarted: resumed %d submaps from %s", len(loop.mapper.submaps), path)
    print(f"mapping: resumed {len(loop.mapper.submaps)} submaps from {path}", flush=True)
    return True


def load_prior_map(loop: MappingLoop, prior: str) -> bool:
    """Start from the dense submaps of a saved map (``mapping.prior_map``: a run folder or its map/ folder): they
    stay where they are, in the saved map's frame (frozen: the keyframes they followed belong to the run that made
    them); new depth goes into new submaps, which follow this run's keyframes, in the map's frame once the back end
    has relocalised. A map without a readable dense file starts empty (logged)."""
    path = dense_path(prior)
    try:
        loop.mapper = load_map(path)
    except (MapFileError, FileNotFoundError) as exc:
        log.warning("mapping: no dense submaps from the saved map (%s): starting an empty map", exc)
        return False
    loop.mapper.estimator_reset()  # freeze them; the next depth frame starts a new submap
    loop.mapper.remesh(None)
    loop.to_publish.update(sm.id for sm in loop.mapper.submaps)
    loop.counts["prior_submaps"] = len(loop.mapper.submaps)
    print(f"mapping: {len(loop.mapper.submaps)} submaps of the saved map {path}", flush=True)
    return True


class MappingNode(ProcessNode):
    """The mapping's process node: :class:`MappingLoop` fed by its inputs, with the periodic work (integration of
    waiting frames, meshing, fields, checkpoints) in :meth:`tick` and the finished map written when the final
    trajectory has been applied and at close."""

    name = "mapping"
    inputs = (
        Input(topics.STATE, "on_state", policy="all", note="poses by stamp (mapping.state_buffer of them)"),
        Input(topics.KEYFRAMES, "on_keyframes", note="submap poses follow their keyframes"),
        # 32 frames (~3.2 s at 10 Hz, ~50 MB) absorb a burst of slow integrations or a mesh pause without dropping
        Input(topics.DEPTH_STEREO, "on_depth", depth=32, when="mapping.depth_topic = depth/stereo (default)",
              note="depth to integrate"),
        Input(topics.DEPTH_FUSED, "on_depth", depth=32, when="mapping.depth_topic = depth/fused",
              note="depth to integrate"),
        Input(topics.TRAJECTORY_FINAL, "on_final", note="submaps move onto it (mapping.follow_final)"),
    )
    outputs = (topics.SUBMAP, topics.MAP_FIELD, topics.MAP_O2P_POINTS)
    output_notes = {topics.SUBMAP.key: "changed submaps, at most every mapping.mesh_period_s",
                    topics.MAP_FIELD.key: "a closed submap's field; the current one every mapping.field_period_s",
                    topics.MAP_O2P_POINTS.key: "per closed submap (mapping.o2p_points > 0)"}

    def __init__(self, cfg: MappingConfig, out_dir: str | None = None, clock=time.monotonic) -> None:
        self.cfg, self.out_dir, self.clock = cfg, out_dir, clock
        self.loop = MappingLoop(cfg)
        if not resume_map(self.loop, out_dir) and cfg.prior_map:
            load_prior_map(self.loop, cfg.prior_map)
        depth = topics.DEPTH_STEREO if cfg.depth_topic == topics.DEPTH_STEREO.key else topics.DEPTH_FUSED
        self.inputs = tuple(dataclasses.replace(i, depth=cfg.state_buffer) if i.handler == "on_state" else i
                            for i in type(self).inputs if i.handler != "on_depth" or i.topic == depth)
        now = clock()
        self.last_mesh = self.last_field = self.last_checkpoint = now
        self.final_pending = False
        self._writer: threading.Thread | None = None  # the checkpoint being written
        self._unchanged: dict = {}  # the last copies of the submaps' fields (map_arrays' reuse)

    def on_state(self, msg: messages.EstimatorState) -> None:
        self.loop.on_state(msg)

    def on_keyframes(self, msg: messages.Keyframes) -> None:
        self.loop.on_keyframes(msg)

    def on_depth(self, msg: messages.DepthFrame) -> list[Emit]:
        self.loop.on_depth(msg)
        return self.tick()

    def on_final(self, msg: messages.FinalTrajectory) -> list[Emit]:
        self.loop.on_final(msg)
        self.final_pending = True  # the map is finished: publish and write it now, not only when stopped
        return self.tick()

    def tick(self) -> list[Emit]:
        cfg, loop, now = self.cfg, self.loop, self.clock()
        loop.process_waiting(self.timer("integrate", cfg.integrate_budget_ms))
        out: list[Emit] = []
        if self.final_pending:
            self.final_pending = False
            out += self.flush()
        if now - self.last_mesh >= cfg.mesh_period_s:
            self.last_mesh = now
            with self.timer("mesh"):
                loop.remesh(cfg.mesh_budget_ms / 1e3)
            out += [Emit(topics.SUBMAP, m) for m in loop.submap_messages()]
        if cfg.field_period_s > 0 and loop.mapper.submaps and now - self.last_field >= cfg.field_period_s:
            self.last_field = now
            loop.fields_to_publish.add(loop.mapper.current.id)
        out += [Emit(topics.MAP_FIELD, m) for m in loop.field_messages()]
        # after the field: the back end pairs them by submap id
        out += [Emit(topics.MAP_O2P_POINTS, m) for m in loop.points_messages()]
        if self.out_dir and cfg.checkpoint_period_s > 0 and now - self.last_checkpoint >= cfg.checkpoint_period_s:
            self.last_checkpoint = now
            self.checkpoint()
        return out

    def checkpoint(self) -> None:
        """Snapshot the map here (the timed part; closed submaps' copies are kept from the last snapshot) and write it
        to map/dense.npz in a thread of its own: a large map takes seconds to write (1.8 s median at 34 submaps),
        during which depth frames would pile up. A checkpoint
        falling due while the previous one is still being written is skipped (counted)."""
        if self._writer is not None and self._writer.is_alive():
            self.loop.counts["checkpoints_skipped_busy"] += 1
            return
        with self.timer("checkpoint"):
            arrays = map_arrays(self.loop.mapper, self._unchanged)
        self._writer = threading.Thread(target=self._write_checkpoint, name="mapping-checkpoint", daemon=True,
                                        args=(arrays, run_map_dir(self.out_dir) / DENSE_FILE))
        self._writer.start()

    def _write_checkpoint(self, arrays: dict[str, np.ndarray], path: Path) -> None:
        try:
            write_map_arrays(arrays, path)
        except OSError as exc:  # a full disk: the run goes on, the last complete checkpoint stays
            self.loop.counts["checkpoints_failed"] += 1
            log.warning("checkpoint %s not written: %s", path, exc)

    def wait_for_checkpoint(self) -> None:
        """Let a checkpoint being written finish (before the final map is written to the same file)."""
        if self._writer is not None:
            self._writer.join()
            self._writer = None

    def flush(self) -> list[Emit]:
        """Mesh every submap completely, publish all meshes and fields, and write the outputs (if ``out_dir``)."""
        loop, t0 = self.loop, time.monotonic()
        loop.remesh(None)
        loop.to_publish.update(sm.id for sm in loop.mapper.submaps)
        out = [Emit(topics.SUBMAP, m) for m in loop.submap_messages()]
        loop.fields_to_publish.update(sm.id for sm in loop.mapper.submaps)
        out += [Emit(topics.MAP_FIELD, m) for m in loop.field_messages()]
        if self.out_dir:
            self.wait_for_checkpoint()
            loop.write_outputs(Path(self.out_dir))
            print(f"mapping: wrote {self.out_dir}/mesh.ply ({len(loop.mapper.submaps)} submaps, "
                  f"{time.monotonic() - t0:.1f} s)", flush=True)
        loop.unflushed = False
        return out

    def close(self) -> list[Emit]:
        """Everything received is integrated and meshed before exit (the runner has handed over what arrived)."""
        loop = self.loop
        loop.process_waiting(self.timer("integrate", self.cfg.integrate_budget_ms))
        out: list[Emit] = []
        if loop.unflushed:
            out = self.flush()
        elif self.out_dir:  # counts may have moved (drops); the map on disk is current
            self.wait_for_checkpoint()
            loop.write_outputs(Path(self.out_dir), report_only=True)
            log.info("map unchanged since it was last written; mapping.json updated")
        log.info("mapping done: %s", dict(loop.counts))
        return out
