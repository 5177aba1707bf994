"""Live ROS 2 input (``sigmaslam ros2_input``): a robot's camera and IMU topics, subscribed on Zenoh under rmw_zenoh's
keys, published as the pipeline's ``sensors/imu`` and ``sensors/frame``, as the player publishes a dataset.

The topics are named in ``ros2.input`` (relative names under ``ros2.input.namespace``); the rig calibration is
``rig.calibration`` as for any run. The stamps are the messages' header stamps. Samples are handled in arrival order
on the process's main thread (Zenoh's threads only queue them); what cannot be used is counted per reason in
``stats/ros2_input`` (``drop_<reason>``) and logged (services/ros2_input/assembler.py). A loop of its own, like the
player's: it is a source, not driven by topics.
"""

from __future__ import annotations

import argparse
import logging
import queue

from shared import topics
from shared.dataflow import ProcessNode
from shared.process_description import ProcessDescription, Scheduling

log = logging.getLogger("sigmaslam.ros2_input")
MAX_QUEUED = 512  # samples waiting for the main thread beyond which new ones are dropped (counted)


class Ros2InputNode(ProcessNode):
    name = "ros2_input"
    inputs = ()
    outputs = (topics.IMU, topics.FRAME)
    output_notes = {topics.IMU.key: "each IMU message of the robot", topics.FRAME.key: "each frame of paired images"}


def _run(cfg, args: argparse.Namespace) -> int:
    from services.ros2_input.assembler import SensorAssembler
    from shared import ros2_wire as wire
    from shared.camera import CalibrationError
    from shared.messages import ImuSample
    from shared.rig import load_rig_config
    from transport.node import Node
    from transport.rmw_zenoh import RosParticipant, participant_config

    rcfg, icfg = cfg.ros2, cfg.ros2.input
    try:
        cameras = load_rig_config(cfg.rig)
    except (CalibrationError, FileNotFoundError) as exc:
        print(f"sigmaslam ros2_input: {exc}", flush=True)
        return 2
    fq = [wire.fq_topic(icfg.namespace, t) for t in icfg.topics.cameras]
    info = [wire.fq_topic(icfg.namespace, t) if t else "" for t in icfg.topics.camera_info]
    imu = wire.fq_topic(icfg.namespace, icfg.topics.imu)
    try:
        asm = SensorAssembler(cameras, fq, imu, info, icfg.sync_tolerance_ms, icfg.max_pending_frames)
    except ValueError as exc:
        print(f"sigmaslam ros2_input: ros2.input.topics.cameras: {exc}", flush=True)
        return 2
    samples: queue.SimpleQueue = queue.SimpleQueue()
    overflow = [0]

    def on_sample(s) -> None:  # Zenoh's thread: queue only
        if samples.qsize() >= MAX_QUEUED:
            overflow[0] += 1
            return
        samples.put(s)

    with Node("ros2_input", cfg.transport, declared=Ros2InputNode) as node:
        imu_pub, frame_pub = node.publisher(topics.IMU), node.publisher(topics.FRAME)
        for reason in asm.drops:
            node.stats.add_counter(f"drop_{reason}", lambda r=reason: asm.drops[r])
        node.stats.add_counter("drop_overflow", lambda: overflow[0])
        node.stats.add_counter("received", lambda: asm.received)
        with RosParticipant(participant_config(cfg.transport, rcfg.connect), rcfg.domain_id, rcfg.namespace,
                            f"{rcfg.node_name}_input", rcfg.attachment) as ros:
            for t, typ in asm.types.items():
                ros.subscribe(t, typ, on_sample)
            print(f"ros2_input: {', '.join(fq)} and {imu} in domain {rcfg.domain_id} -> {topics.FRAME.key}, "
                  f"{topics.IMU.key}", flush=True)
            while not node.stopped:
                try:
                    s = samples.get(timeout=0.1)
                except queue.Empty:
                    continue
                for msg in asm.on_sample(s.topic, s.dds_type, s.type_hash, s.payload):
                    (imu_pub if isinstance(msg, ImuSample) else frame_pub).publish(msg)
            log.info("ros2_input: %d samples received", asm.received)
        dropped = ", ".join(f"{k} {v}" for k, v in asm.drops.items() if v)
        print(f"ros2_input: {asm.seq_frame} frames, {asm.seq_imu} IMU samples published; dropped: {dropped or 'none'}"
              + (f", {overflow[0]} on overflow" if overflow[0] else ""), flush=True)
    return 0


DESCRIPTION = ProcessDescription(
    name="ros2_input", node=Ros2InputNode, main=_run, switch="ros2.input.enabled",
    scheduling=Scheduling(nice=-10, sched="fifo"),  # the sensor input, as the player: the path to a pose starts here
    help="live ROS 2 input: a robot's camera and IMU topics (rmw_zenoh on Zenoh) as sensors/frame and sensors/imu")
