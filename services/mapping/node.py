"""Occupancy submapping as a transport-free process node (run by ``sigmaslam mapping``).

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
its own, atomic rename); a process restarted by the supervisor resumes from that checkpoint
(services/mapping/store.py, docs/reliability.md).

Occupancy for planners (docs/occupancy.md): the node answers ``map/query`` (points, segments, boxes of the combined
map, each submap at its current pose; :meth:`MappingNode.on_query`, on the query thread), publishes the 2D grid over a
height band on ``map/grid`` every ``grid.period_s``, and with an output folder writes ``occupancy_grid.pgm``/``.yaml``
(ROS map_server) beside ``mesh.ply``.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import time
from typing import TYPE_CHECKING, Callable

import numpy as np

from services.mapping.config import MappingConfig
from services.mapping.poses import PoseBuffer
from shared import messages, topics
from shared.codec import Header
from shared.dataflow import Emit, Input, ProcessNode, Served
from shared.occupancy.o2p_points import SubmapPointPool
from shared.process_description import Output, ProcessDescription, Scheduling, Start

if TYPE_CHECKING:
    from services.mapping.store import MapStore

log = logging.getLogger("sigmaslam.mapping")


class MappingNode(ProcessNode):
    """The mapping's process node: depth frames integrated into the submaps of ``store``'s initial map at the
    estimator's poses, with the periodic work (integration of waiting frames, meshing, fields, checkpoints) in
    :meth:`tick` and the finished map written when the final trajectory has been applied and at close."""

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
    outputs = (topics.SUBMAP, topics.MAP_FIELD, topics.MAP_O2P_POINTS, topics.MAP_GRID)
    served = (Served(topics.MAP_QUERY, "on_query", note="the combined map, each submap at its current pose"),)
    output_notes = {topics.SUBMAP.key: "changed submaps, at most every mapping.mesh_period_s",
                    topics.MAP_FIELD.key: "a closed submap's field; the current one every mapping.field_period_s",
                    topics.MAP_O2P_POINTS.key: "per closed submap (mapping.o2p_points > 0)",
                    topics.MAP_GRID.key: "the combined map's 2D grid over a height band, every mapping.grid.period_s"}

    def __init__(self, cfg: MappingConfig, store: MapStore, clock: Callable[[], float] = time.monotonic) -> None:
        self.cfg, self.store, self.clock = cfg, store, clock
        self.mapper, started = store.initial_map(cfg)
        self.poses = PoseBuffer(cfg.state_buffer)
        self.waiting: collections.deque[tuple[float, messages.DepthFrame]] = collections.deque(maxlen=32)
        # stamps whose state was a placeholder without a pose (initialising, reset): their frames never get one
        self.unposed: collections.deque[int] = collections.deque(maxlen=256)
        self.counts = collections.Counter(started)
        self.integrate_ms: list[float] = []
        self.to_publish: set[int] = set()
        self.fields_to_publish: set[int] = set()
        self.reset_pending = False
        # map-to-map points (shared/occupancy/o2p_points.py), published once per closed submap
        self.points = SubmapPointPool(cfg.o2p_points) if cfg.o2p_points > 0 else None
        self.points_to_publish: set[int] = set()
        self.unflushed = True  # the map changed since it was last completely published and written
        if self.mapper.submaps:  # resumed or a saved map's: meshed and published again
            self.mapper.remesh(None)
            self.to_publish.update(sm.id for sm in self.mapper.submaps)
        depth = topics.DEPTH_STEREO if cfg.depth_topic == topics.DEPTH_STEREO.key else topics.DEPTH_FUSED
        self.inputs = tuple(dataclasses.replace(i, depth=cfg.state_buffer) if i.handler == "on_state" else i
                            for i in type(self).inputs if i.handler != "on_depth" or i.topic == depth)
        now = clock()
        # when each periodic job last fell due (not when it ran: ticks come between integrations, so "ran + period"
        # would drift late by up to one integration each time; the live grid went out at 0.7-0.84 Hz for 1 s)
        self.due = {"mesh": now, "field": now, "grid": now, "checkpoint": now}
        self.final_pending = False
        self.newest_stamp_ns = 0  # of the newest depth frame integrated
        self.grids = None  # services.mapping.grid.GridBuilder, made at the first grid

    def on_query(self, msg: messages.OccupancyQuery) -> messages.OccupancyAnswer:
        """``map/query`` (on the query thread): a snapshot of the submaps at their current poses answers it
        (services/mapping/combined.py); ValueError for a request it refuses."""
        from services.mapping.combined import CombinedMap
        from services.mapping.query_service import answer

        with self.timer("query"):
            return answer(CombinedMap.of(self.mapper, self.cfg.query), msg, self.newest_stamp_ns)

    def on_state(self, msg: messages.EstimatorState) -> None:
        if msg.status == "reset":  # a restarted back end: new world frame and keyframe ids
            self.poses = PoseBuffer(self.cfg.state_buffer)  # forget the old frame's poses (atomic swap)
            self.reset_pending = True  # submaps are frozen before the next integration
        if msg.status in ("initialising", "reset"):  # placeholders without a pose
            self.counts["states_without_pose"] += 1
            self.unposed.append(int(msg.header.stamp_ns))
            return
        self.poses.add(msg.header.stamp_ns, msg.T_WS)

    def on_keyframes(self, msg: messages.Keyframes) -> None:
        moved = self.mapper.update_keyframes(msg.ids, msg.stamps_ns, msg.T_WS)
        self.to_publish.update(moved)
        self.unflushed |= bool(moved)

    def on_depth(self, msg: messages.DepthFrame) -> list[Emit]:
        if len(self.waiting) == self.waiting.maxlen:
            self.counts["dropped_waiting_full"] += 1
        self.waiting.append((time.monotonic(), msg))
        return self.tick()

    def on_final(self, msg: messages.FinalTrajectory) -> list[Emit]:
        """The non-causal trajectory: submaps follow it (``mapping.follow_final``), and the map, finished, is
        published and written now, not only when stopped."""
        if self.cfg.follow_final:
            moved = self.mapper.follow_trajectory(msg.stamps_ns, msg.T_WS)
            self.to_publish.update(moved)
            self.unflushed |= bool(moved)
            self.counts["final_trajectories"] += 1
            log.info("final trajectory: %d of %d submaps moved onto it", len(moved), len(self.mapper.submaps))
        self.final_pending = True
        return self.tick()

    def _pose(self, msg: messages.DepthFrame) -> np.ndarray | None:
        if self.cfg.pose_source == "frame" and not np.allclose(msg.T_WC, np.eye(4)):
            return np.asarray(msg.T_WC, float)
        T_WS = self.poses.lookup(msg.header.stamp_ns, int(self.cfg.pose_tolerance_ms * 1e6),
                                 int(self.cfg.max_interp_gap_ms * 1e6))
        return None if T_WS is None else T_WS @ np.asarray(msg.T_SC, float)

    def integrate_waiting(self) -> int:
        """Integrate every waiting frame whose pose is known; drop those that waited too long."""
        if self.reset_pending:
            self.reset_pending = False
            self.mapper.estimator_reset()
            self.unflushed = True
            self.counts["estimator_resets"] += 1
            log.warning("estimator reset: submaps so far frozen, the next frame starts a new submap")
        done, keep = 0, collections.deque(maxlen=self.waiting.maxlen)
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
            done += self._integrate(msg, T_WC)
        self.waiting = keep
        return done

    def _integrate(self, msg: messages.DepthFrame, T_WC: np.ndarray) -> int:
        t0 = time.perf_counter()
        try:
            with self.timer("integrate", self.cfg.integrate_budget_ms):
                rep = self.mapper.integrate(msg.depth, msg.sigma, msg.K, T_WC, msg.T_SC, msg.header.stamp_ns,
                                            msg.surface_max_relative_sigma)
        except ValueError as exc:
            self.counts["dropped_bad_frame"] += 1
            log.warning("depth frame %d dropped: %s", msg.header.stamp_ns, exc)
            return 0
        self.integrate_ms.append(1e3 * (time.perf_counter() - t0))
        self.newest_stamp_ns = max(self.newest_stamp_ns, int(msg.header.stamp_ns))
        self.unflushed = True
        self.counts["integrated"] += 1
        self.counts["surface_pixels"] += rep.result.n_pixels - rep.result.n_carve_only
        self.counts["carve_only_pixels"] += rep.result.n_carve_only
        if self.points is not None:
            T_WM = self.mapper.submaps[rep.submap_id].T_WM
            self.points.add(rep.submap_id, msg.surface_depth(), msg.sigma, msg.K, np.linalg.inv(T_WM) @ T_WC)
        if rep.new_submap:
            self.counts["submaps"] += 1
            if rep.submap_id > 0:
                self.fields_to_publish.add(rep.submap_id - 1)  # closed: its field is final
                self.points_to_publish.add(rep.submap_id - 1)
            log.info("submap %d started (overlap %.2f)", rep.submap_id, rep.overlap)
        return 1

    def remesh(self, budget_s: float | None) -> None:
        """Re-mesh changed submaps within ``budget_s`` (None: all of them); they are published next."""
        self.to_publish.update(self.mapper.remesh(budget_s))

    def submap_messages(self) -> list[Emit]:
        out = []
        for sid in sorted(self.to_publish):
            sm = self.mapper.submaps[sid]
            if self.cfg.vertex_colors:
                v, f, c = self.mapper.colored_mesh(sm)
            else:
                (v, f, _), c = self.mapper.mesh(sm), np.empty((0, 3), np.uint8)
            out.append(Emit(topics.SUBMAP, messages.SubmapMesh(
                header=Header(stamp_ns=sm.anchor_stamp_ns, frame_id=f"M{sm.id}"), submap_id=sm.id, T_WM=sm.T_WM,
                vertices_M=v, faces=f, vertex_colors=c)))
        self.to_publish.clear()
        return out

    def field_messages(self) -> list[Emit]:
        from services.mapping.export import field_message

        out = [Emit(topics.MAP_FIELD, field_message(self.mapper.submaps[i], self.cfg.sensor.l_min))
               for i in sorted(self.fields_to_publish)]
        self.fields_to_publish.clear()
        return out

    def points_messages(self) -> list[Emit]:
        out = []
        for sid in sorted(self.points_to_publish):
            got = self.points.pop(sid) if self.points is not None else None
            if got is not None:
                sm = self.mapper.submaps[sid]
                out.append(Emit(topics.MAP_O2P_POINTS, messages.SubmapPoints(
                    header=Header(stamp_ns=sm.anchor_stamp_ns, frame_id=f"M{sid}"), submap_id=sid,
                    points_M=got[0].astype(np.float32), sigma=got[1].astype(np.float32))))
        self.points_to_publish.clear()
        return out

    def grid(self):
        """The 2D grid of the map now (services/mapping/grid.py), None while nothing is mapped."""
        if self.grids is None:
            from services.mapping.grid import GridBuilder

            self.grids = GridBuilder(self.cfg.grid, self.cfg.query)
        return self.grids.build(self.mapper)

    def grid_messages(self) -> list[Emit]:
        with self.timer("grid"):
            g = self.grid()
        if g is None:
            return []
        self.counts["grids"] += 1
        return [Emit(topics.MAP_GRID, g.message(self.newest_stamp_ns, seq=self.counts["grids"] - 1))]

    def tick(self) -> list[Emit]:
        cfg, now = self.cfg, self.clock()
        self.integrate_waiting()
        out: list[Emit] = []
        if self.final_pending:
            self.final_pending = False
            out += self.flush()
        if cfg.mesh_period_s <= 0 or self._due("mesh", cfg.mesh_period_s, now):  # 0: every tick
            with self.timer("mesh"):
                self.remesh(cfg.mesh_budget_ms / 1e3)
            out += self.submap_messages()
        if self.mapper.submaps and self._due("field", cfg.field_period_s, now):
            self.fields_to_publish.add(self.mapper.current.id)
        out += self.field_messages()
        out += self.points_messages()  # after the field: the back end pairs them by submap id
        if self._due("grid", cfg.grid.period_s, now):
            out += self.grid_messages()
        if self.store.out_dir and self._due("checkpoint", cfg.checkpoint_period_s, now):
            self.checkpoint()
        return out

    def _due(self, job: str, period_s: float, now: float) -> bool:
        """Whether ``job`` (every ``period_s``; <= 0: never) falls due at ``now``; the next time it falls due is one
        period after this one was due, so that it keeps its rate, unless it is a whole period late (then one period
        from now: no burst to catch up)."""
        if period_s <= 0 or now - self.due[job] < period_s:
            return False
        self.due[job] = self.due[job] + period_s if now - self.due[job] < 2 * period_s else now
        return True

    def checkpoint(self) -> None:
        """Snapshot the map here (the timed part) and write it in the store's thread; a checkpoint falling due while
        the previous one is still being written is skipped (counted)."""
        if self.store.writing:
            self.counts["checkpoints_skipped_busy"] += 1
            return
        with self.timer("checkpoint"):
            arrays = self.store.snapshot(self.mapper)
        self.store.checkpoint(arrays, self.counts)

    def flush(self) -> list[Emit]:
        """Mesh every submap completely, publish all meshes and fields, and write the outputs (with an output
        folder)."""
        t0 = time.monotonic()
        self.mapper.remesh(None)
        self.to_publish.update(sm.id for sm in self.mapper.submaps)
        out = self.submap_messages()
        self.fields_to_publish.update(sm.id for sm in self.mapper.submaps)
        out += self.field_messages()
        out += self.grid_messages()
        if self.store.out_dir:
            self.store.write(self.mapper, self.counts, self.integrate_ms)
            self.write_occupancy()
            print(f"mapping: wrote {self.store.out_dir}/mesh.ply ({len(self.mapper.submaps)} submaps, "
                  f"{time.monotonic() - t0:.1f} s)", flush=True)
        self.unflushed = False
        return out

    def write_occupancy(self) -> None:
        """The 2D grid of the map (occupancy_grid.pgm/.yaml) into the output folder (the 3D voxels take seconds: the
        run writes them from the saved map after the pipeline, services/app/run_outputs.py)."""
        from services.mapping.grid_files import write_grid

        with self.timer("grid_write"):
            g = self.grid()
            if g is not None:
                write_grid(g, self.store.out_dir)

    def close(self) -> list[Emit]:
        """Everything received is integrated and meshed before exit (the runner has handed over what arrived)."""
        self.integrate_waiting()
        out: list[Emit] = []
        if self.unflushed:
            out = self.flush()
        elif self.store.out_dir:  # counts may have moved (drops); the map on disk is current
            self.store.write(self.mapper, self.counts, self.integrate_ms, report_only=True)
            log.info("map unchanged since it was last written; mapping.json updated")
        log.info("mapping done: %s", dict(self.counts))
        return out


def make_node(cfg: MappingConfig, out_dir: str | None = None, clock: Callable[[], float] = time.monotonic,
              restarts: int = 0) -> MappingNode:
    """The mapping node with its map store (``out_dir``: the output folder, None: write nothing; ``restarts`` > 0:
    resume from the folder's checkpoint)."""
    from services.mapping.store import MapStore

    return MappingNode(cfg, MapStore(out_dir, restarts), clock)


def _build(cfg, start: Start) -> MappingNode:
    out = cfg.mapping.output_dir if start.out_dir is None else start.out_dir
    clock = {} if start.clock is None else {"clock": start.clock}
    return make_node(cfg.mapping, out or None, restarts=start.restarts, **clock)


def _warm_up(node: MappingNode) -> None:
    from services.mapping.combined import warm_up as warm_up_queries
    from services.mapping.integrate import warm_up

    from services.mapping.grid import warm_up as warm_up_grid

    warm_up(node.cfg.sensor)
    warm_up_queries(node.cfg.sensor.voxel_size_m)
    warm_up_grid()


DESCRIPTION = ProcessDescription(
    name="mapping", node=MappingNode, build=_build, warm_up=_warm_up, in_process=True,
    ready=lambda node, cfg: f"mapping: {node.cfg.depth_topic} -> {topics.SUBMAP.key}",
    output=Output(in_run="", help="write mesh.ply, submaps/, map/dense.npz and occupancy_grid.pgm/.yaml here at exit "
                                  "(overrides mapping.output_dir)"),
    # what the path to a pose and other work leave; meshes and writes its map when stopped: give it time to finish
    scheduling=Scheduling(nice=19, stop_timeout_s=60.0),
    help="occupancy submapping: depth + estimator poses -> map/submap meshes, map/field, map/grid; answers map/query; "
         "the map at exit")
