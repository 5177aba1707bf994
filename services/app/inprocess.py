"""The pipeline's process nodes in one process, fed from a dataset: the in-process counterpart of ``sigmaslam run``.

::

    run = run_in_process("data/replicas/V1_02-...", load_system_config(None, ["loop.enabled=false"]))
    run.states            # every estimator/state, in order
    run.final             # estimator/trajectory_final (loop closure on), else None
    run.runner.times      # per (node, handler): wall and CPU time of every call

    run = run_in_process(dataset, cfg, depth=True, mapping=True)   # the whole pipeline (sigmaslam eval ablation)
    run.nodes["mapping"].mapper                                      # the map as the mapping node holds it
    run.mesh_causal       # the map's vertices in W just before it followed the final trajectory

The nodes are the processes' own (services/<process>/node.py), built from the system config in one place,
:func:`pipeline_nodes`, and driven by :class:`shared.dataflow.InProcessRunner` in stamp order, the order a
lockstep run over Zenoh gives: tools that need the pipeline without processes (offline VIO, loop evaluation, the
ablation table) use this instead of wiring the algorithms by hand. Pacing is by stamps: the depth node handles a
frame at most every 1 / ``depth.rate_hz`` of sensor time, and the mapping node's periods (meshes, fields) run on
the sensor clock (the newest source stamp), so a run's result depends on its input alone.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from services.app.processes import PROCESSES, in_process_nodes
from services.player.config import PlayerConfig
from shared import topics
from shared.config import override
from shared.dataflow import InProcessRunner, ProcessNode
from shared.euroc_reader import EurocDataset
from shared.messages import EstimatorState, FinalTrajectory, Header, ImuSample, StreamEnd
from shared.process_description import Start
from shared.rig import load_rig_config


def dataset_source(ds: EurocDataset, player: PlayerConfig, max_frames: int = 0, seconds: float = 0.0) -> Iterator:
    """(topic, message) of a dataset as the player of config ``player`` sends them (IMU and frames in time order,
    within its IMU margin, from its start; ``max_frames`` > 0 stops after that many frames, ``seconds`` > 0 before
    the first frame more than that long after the first one played [s]), then the player's StreamEnd."""
    frames, first, last = 0, None, 0
    for msg in player.messages(ds):
        if isinstance(msg, ImuSample):
            yield topics.IMU, msg
            continue
        stamp = int(msg.header.stamp_ns)
        first = stamp if first is None else first
        if (max_frames and frames >= max_frames) or (seconds > 0 and stamp - first > seconds * 1e9):
            break
        frames += 1
        last = stamp
        yield topics.FRAME, msg
    yield topics.STREAM_END, StreamEnd(header=Header(stamp_ns=last, seq=0, frame_id="player"), source="player",
                                       frames_sent=frames)


def pipeline_nodes(cfg, cams, depth: bool = False, mapping: bool = False,
                   clock: Callable[[], float] | None = None) -> dict[str, ProcessNode]:
    """The pipeline's nodes, each built by its process's description (services/app/processes.py) from the system
    config ``cfg`` and the rig ``cams``: the default pipeline (frontend: tracking and the fast path, every frame's
    state; back end: keyframe window), with ``depth`` the depth node, with ``mapping`` the mapping node (no output
    folder; ``clock`` [s] paces its meshes and fields, the wall clock when None), in the registry's order."""
    names = [d.name for d in PROCESSES if d.default_pipeline] + ["depth"] * depth + ["mapping"] * mapping
    return in_process_nodes(cfg, names, Start(out_dir="", clock=clock, cameras=cams))


@dataclasses.dataclass
class InProcessRun:
    runner: InProcessRunner
    nodes: dict[str, ProcessNode]
    states: list[EstimatorState]
    final: FinalTrajectory | None
    frames: int
    groundtruth_path: Path | None  # the dataset's ground truth file
    # with the mapping node: the map's world mesh vertices (N,3) [m] as built at the causal poses, taken just before
    # the mapping moved its submaps onto the final trajectory (at the end of the run when none came); else None
    mesh_causal: np.ndarray | None = None
    # with loop closure: the loop closer's time inside each back-end frame call (the entries of
    # runner.times[("backend", "on_features")], in order) [s]; empty without loop closure
    loop_s: list[float] = dataclasses.field(default_factory=list)

    @property
    def time_offset_ms(self) -> float | None:
        """The back end's camera-IMU time offset estimate at the end [ms] (backend.estimate_time_offset), else None."""
        offset = self.nodes["backend"].estimator.time_offset
        return None if offset is None else 1e3 * offset.td


class _Collector:
    """The run's taps: states, the final trajectory, the causal map before the mapping follows the final one, and
    the loop closer's time inside each back-end frame call. With ``loop.synchronous`` the closer works inside the
    call (the back-end service runs it in its own thread): its busy time is read when a feature frame is delivered
    (just before the back end handles it) and when that frame's state comes out (just after)."""

    def __init__(self, nodes: dict[str, ProcessNode]) -> None:
        self.nodes, self.states, self.final, self.mesh_causal = nodes, [], [], None
        loop = nodes["backend"].loop_closure
        self.loop_runner = None if loop is None else loop.runner
        self.busy_before: list[float] = []
        self.loop_s: list[float] = []  # one entry per back-end frame call, in call order [s]

    def _loop_time(self, topic) -> None:
        if self.loop_runner is None:
            return
        busy = self.loop_runner.busy_s
        if topic == topics.FEATURES:
            if len(self.loop_s) < len(self.busy_before):  # the previous call published no state
                self.loop_s.append(busy - self.busy_before[-1])
            self.busy_before.append(busy)
        elif topic == topics.STATE and len(self.loop_s) < len(self.busy_before):
            self.loop_s.append(busy - self.busy_before[-1])

    def snapshot_map(self) -> None:
        node = self.nodes.get("mapping")
        if node is None or self.mesh_causal is not None:
            return
        node.integrate_waiting()  # what arrived is in the map
        node.remesh(None)
        self.mesh_causal = np.asarray(node.mapper.world_mesh()[0], float)

    def __call__(self, topic, msg) -> None:
        self._loop_time(topic)
        if topic == topics.STATE:
            self.states.append(msg)
        elif topic == topics.TRAJECTORY_FINAL:
            self.snapshot_map()  # taps see a message before the nodes do
            self.final.append(msg)


def run_in_process(dataset: str, cfg, max_frames: int = 0, depth: bool = False, mapping: bool = False,
                   seconds: float = 0.0, taps: Iterable[Callable] = ()) -> InProcessRun:
    """The pipeline of :func:`pipeline_nodes` (frontend, fast path and back end with whatever ``cfg`` enables: loop closure,
    occupancy-to-point factors; the depth and mapping nodes when asked) on ``dataset``, in this process; ``taps``
    see every (topic, message) delivered, after the run's own."""
    if not cfg.rig.calibration:
        cfg = override(cfg, {"rig.calibration": str(dataset)})
    cams = load_rig_config(cfg.rig)
    runner: InProcessRunner | None = None
    nodes = pipeline_nodes(cfg, cams, depth, mapping, clock=lambda: 1e-9 * (runner.now_ns if runner else 0))
    collect = _Collector(nodes)
    runner = InProcessRunner(list(nodes.values()), taps=[collect, *taps])
    ds = EurocDataset(dataset)
    runner.run(dataset_source(ds, cfg.player, max_frames, seconds))
    if mapping and not collect.final:
        collect.snapshot_map()
    if len(collect.loop_s) < len(collect.busy_before):  # the last frame call published no state
        collect.loop_s.append(collect.loop_runner.busy_s - collect.busy_before[-1])
    frames = len(runner.times.get(("frontend", "on_frame"), []))
    return InProcessRun(runner, nodes, collect.states, collect.final[0] if collect.final else None, frames,
                        ds.groundtruth_path, collect.mesh_causal, collect.loop_s)
