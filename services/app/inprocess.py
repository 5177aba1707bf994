"""The pipeline's process nodes in one process, fed from a dataset: the in-process counterpart of ``sigmaslam run``.

::

    run = run_in_process("data/replicas/V1_02-...", load_system_config(None, ["loop.enabled=false"]))
    run.states            # every estimator/state, in order
    run.final             # estimator/trajectory_final (loop closure on), else None
    run.runner.times      # per (node, handler): wall and CPU time of every call

The nodes are the services' own (services/frontend/node.py, services/backend/odometry_node.py,
services/backend/node.py), driven by
:class:`shared.dataflow.InProcessRunner` in stamp order, the order a lockstep run over Zenoh gives: tools that
need the pipeline without processes (offline VIO, loop evaluation) use this instead of wiring the algorithms by hand.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Iterator

from services.backend.node import BackendNode
from services.backend.odometry_node import OdometryNode
from services.frontend.node import FrontendNode
from shared import topics
from shared.config import override
from shared.dataflow import InProcessRunner, ProcessNode
from shared.euroc_reader import EurocDataset
from shared.messages import EstimatorState, FinalTrajectory, Header, ImuSample, StreamEnd
from shared.rig import load_rig_config


def dataset_source(ds: EurocDataset, max_frames: int = 0, imu_margin_s: float = 1.0) -> Iterator:
    """(topic, message) of a dataset as the player sends them (IMU and frames in time order, IMU only within
    ``imu_margin_s`` of the frames; ``max_frames`` > 0 stops after that many frames), then the player's StreamEnd."""
    frames, last = 0, 0
    for msg in ds.messages(None if imu_margin_s < 0 else int(round(imu_margin_s * 1e9))):
        if isinstance(msg, ImuSample):
            yield topics.IMU, msg
            continue
        if max_frames and frames >= max_frames:
            break
        frames += 1
        last = int(msg.header.stamp_ns)
        yield topics.FRAME, msg
    yield topics.STREAM_END, StreamEnd(header=Header(stamp_ns=last, seq=0, frame_id="player"), source="player",
                                       frames_sent=frames)


@dataclasses.dataclass
class InProcessRun:
    runner: InProcessRunner
    nodes: dict[str, ProcessNode]
    states: list[EstimatorState]
    final: FinalTrajectory | None
    frames: int
    groundtruth_path: Path | None  # the dataset's ground truth file


def run_in_process(dataset: str, cfg, max_frames: int = 0, taps=()) -> InProcessRun:
    """Frontend, fast path and back end (with whatever ``cfg`` enables: loop closure) on ``dataset``, in this
    process; ``taps`` are called with every (topic, message) delivered."""
    if not cfg.rig.calibration:
        cfg = override(cfg, {"rig.calibration": str(dataset)})
    cams = load_rig_config(cfg.rig)
    # the fast path before the back end: a keyframe's state comes from the previous window, as in a live run
    nodes = {"frontend": FrontendNode(cfg.frontend, cams), "odometry": OdometryNode(cfg, cams),
             "backend": BackendNode(cfg, cams)}
    states: list[EstimatorState] = []
    final: list[FinalTrajectory] = []

    def tap(topic, msg) -> None:
        if topic == topics.STATE:
            states.append(msg)
        elif topic == topics.TRAJECTORY_FINAL:
            final.append(msg)

    runner = InProcessRunner(list(nodes.values()), taps=[tap, *taps])
    ds = EurocDataset(dataset)
    runner.run(dataset_source(ds, max_frames, cfg.player.imu_margin_s))
    frames = len(runner.times.get(("frontend", "on_frame"), []))
    return InProcessRun(runner, nodes, states, final[0] if final else None, frames, ds.groundtruth_path)
