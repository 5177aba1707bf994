"""The player's loop (``sigmaslam player DATASET [CONFIG] [--lockstep | --realtime | --rate R]``): replays an EuRoC
folder or an MCAP file, paced by the sensor clock (services/player/node.py declares its topics). IMU samples go out on sensors/imu (keep-all), frames on sensors/frame, in time order, then ``StreamEnd`` on sensors/end
(header stamp = the last frame's time). ``--lockstep`` publishes a frame only after the estimator has
answered the previous one (estimator/state with its stamp, or ``--lockstep-timeout-s``): reproducible runs
whatever the machine's speed. ``--rate R`` plays at R times sensor rate (``--realtime`` = 1).
``--wait-for a,b`` waits until those services' heartbeats are seen before playing. The ``control`` topic
pauses, resumes or stops playback (target 'player' or '*'); time spent paused does not count in rate mode.
Defaults come from the ``player`` config section (:class:`services.player.config.PlayerConfig`).
From an EuRoC folder, IMU samples more than ``player.imu_margin_s`` before the first or after the last camera
frame are not played (a trimmed folder may keep the whole sequence's IMU: no minutes of IMU-only stream);
frames whose image files are missing are skipped. The closing line prints the dataset's non-zero counters.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from shared import topics
from services.player.source import open_source
from shared.euroc_reader import DatasetError
from shared.messages import Control, Header, ImuSample, StreamEnd
from services.player.node import PlayerNode
from transport.node import Node
from transport.queues import Empty

log = logging.getLogger("sigmaslam.player")


class _DatasetAndConfig(argparse.Action):
    """DATASET [CONFIG] in any order (the supervisor puts CONFIG first, a person DATASET first): sets ``dataset``
    and ``config`` (None without one)."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        configs = [v for v in values if v.endswith((".yaml", ".yml")) and Path(v).is_file()]
        data = [v for v in values if v not in configs]
        if len(data) != 1 or len(configs) > 1:
            parser.error(f"expected DATASET [CONFIG.yaml], got {values}")
        namespace.dataset, namespace.config = data[0], (configs[0] if configs else None)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("paths", nargs="+", metavar="DATASET [CONFIG]", action=_DatasetAndConfig,
                   help="EuRoC ASL folder or .mcap recording, and optionally a YAML system config (any order)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--lockstep", action="store_true", help="wait for the estimator after every frame (player.mode default)")
    mode.add_argument("--realtime", action="store_true", help="play at sensor rate")
    mode.add_argument("--rate", type=float, help="play at this multiple of sensor rate")
    p.add_argument("--lockstep-timeout-s", type=float, help="longest wait for the estimator [s] (player.lockstep_timeout_s)")
    p.add_argument("--max-frames", type=int, help="stop after this many frames (0: all; player.max_frames)")
    p.add_argument("--paused", action="store_true", help="start paused; a 'resume' on the control topic starts playing")
    p.add_argument("--wait-for", default="", help="comma-separated services whose heartbeat must be seen first")
    p.add_argument("--wait-timeout-s", type=float, default=60.0, help="longest wait for --wait-for [s]")
    p.add_argument("--as-ros2", action="store_true", help="a stand-in ROS 2 robot: the frames and IMU samples as "
                   "ROS 2 sensor messages over rmw_zenoh on the topics of ros2.input (services/player/ros2_out.py), "
                   "not on sensors/*; sensors/end still marks the end")
    p.add_argument("--ros2-encoding", default="mono8", choices=("mono8", "bgr8", "rgb8", "jpeg"),
                   help="--as-ros2: raw image encoding, or jpeg for the compressed topics (default PNG)")


def _wait_for_services(node: Node, names: list[str], timeout_s: float) -> bool:
    if not names:
        return True
    hb = node.subscriber(topics.HEARTBEAT, policy="all", depth=1000)
    seen: set[str] = set()
    deadline = time.monotonic() + timeout_s
    while not node.stopped and time.monotonic() < deadline:
        try:
            m = hb.get(timeout=0.1)
        except Empty:
            continue
        if m.state == "running" and m.header.seq >= 1:  # periodic: the service's subscriptions exist by now
            seen.add(m.service)
        if seen >= set(names):
            node.wait(0.3)
            return True
    log.warning("services %s not seen within %.0f s; playing anyway", sorted(set(names) - seen), timeout_s)
    return False


def play(cfg, args: argparse.Namespace) -> int:
    """Play ``args.dataset`` with the system config ``cfg`` (the player's main); returns the exit status."""
    pc = cfg.player
    try:
        ds = open_source(args.dataset)
    except DatasetError as exc:
        print(f"sigmaslam player: {exc}", flush=True)
        return 2
    if args.lockstep or args.realtime or args.rate:
        lockstep = args.lockstep
    else:
        lockstep = pc.mode == "lockstep"  # 'lockstep' or 'rate' (checked by the loader)
    rate = 0.0 if lockstep else (1.0 if args.realtime else (args.rate or pc.rate))
    if not lockstep and rate <= 0:
        print(f"sigmaslam player: the rate must be positive, got {rate}", flush=True)
        return 2
    timeout_s = pc.lockstep_timeout_s if args.lockstep_timeout_s is None else args.lockstep_timeout_s
    max_frames = pc.max_frames if args.max_frames is None else args.max_frames
    with Node("player", cfg.transport, declared=PlayerNode) as node:
        robot = _ros2_robot(cfg, args) if getattr(args, "as_ros2", False) else None  # a stand-in ROS 2 robot
        imu_pub, frame_pub = (robot.imu, robot.frame) if robot else (node.publisher(topics.IMU), node.publisher(topics.FRAME))
        end_pub = node.publisher(topics.STREAM_END)
        states = node.subscriber(topics.STATE, policy="latest", depth=64) if lockstep else None
        control = PlayerControl(node, paused=args.paused or pc.start_paused)
        _wait_for_services(node, [n for n in args.wait_for.split(",") if n], args.wait_timeout_s)
        frames = timeouts = 0
        last_frame_ns, last_imu_ns = 0, -1
        held = None  # lockstep: a frame read ahead while looking for the IMU sample that follows a frame
        t_wall0 = t_data0 = None
        try:
            messages = iter(pc.messages(ds))
        except DatasetError as exc:
            print(f"sigmaslam player: {exc}", flush=True)
            return 2
        while True:
            if not control.wait_while_paused():
                break
            try:
                if held is None:
                    msg = next(messages)
                else:
                    msg, held = held, None
            except StopIteration:
                break
            except DatasetError as exc:  # e.g. a recording cut short: end the stream cleanly
                log.error("player: %s", exc)
                break
            stamp = int(msg.header.stamp_ns)
            if rate > 0:
                if t_wall0 is None:
                    t_wall0, t_data0 = time.monotonic(), stamp
                t_wall0 += control.take_paused_s()
                delay = (stamp - t_data0) * 1e-9 / rate - (time.monotonic() - t_wall0)
                if delay > 0 and node.wait(delay):
                    break
            if isinstance(msg, ImuSample):
                imu_pub.publish(msg)
                last_imu_ns = stamp
                continue
            if max_frames and frames >= max_frames:
                break
            frame_pub.publish(msg)
            frames += 1
            last_frame_ns = stamp
            if lockstep:
                last_imu_ns, held = _imu_up_to(messages, imu_pub, stamp, last_imu_ns)
                if not _await_state(node, states, stamp, timeout_s):
                    timeouts += 1
        end_pub.publish(StreamEnd(header=Header(stamp_ns=last_frame_ns, seq=0, frame_id="player"),
                                  source="player", frames_sent=frames))
        log.info("player: %d frames, %d lockstep timeouts, dataset counters %s", frames, timeouts, ds.stats)
        skipped = ", ".join(f"{k} {v}" for k, v in ds.stats.items() if v)
        print(f"player: {frames} frames sent ({timeouts} lockstep timeouts)"
              + (f"; dataset: {skipped}" if skipped else ""), flush=True)
        node.wait(pc.end_linger_s)
        if robot is not None:
            robot.close()
    return 0


def _ros2_robot(cfg, args):
    """The stand-in robot's publishers (services/player/ros2_out.py), CameraInfo from the dataset's calibration."""
    from services.player.ros2_out import RosRobot
    from shared.camera import CalibrationError, load_rig

    try:
        cameras = load_rig(args.dataset)
    except (CalibrationError, FileNotFoundError, OSError) as exc:
        log.warning("player --as-ros2: no calibration in %s (%s): no CameraInfo", args.dataset, exc)
        cameras = []
    return RosRobot(cfg, cameras, args.ros2_encoding)


class PlayerControl:
    """'pause', 'resume' and 'stop' commands on the control topic (target 'player' or '*')."""

    def __init__(self, node: Node, paused: bool = False) -> None:
        self.node = node
        self.paused = paused
        self._paused_since = time.monotonic() if paused else None
        self._paused_s = 0.0
        self._sub = node.subscriber(topics.CONTROL, handler=self._on_control)
        self.commands = 0

    def _on_control(self, msg: Control) -> None:
        if msg.target not in ("player", "*"):
            return
        self.commands += 1
        if msg.command == "pause" and not self.paused:
            self.paused, self._paused_since = True, time.monotonic()
        elif msg.command == "resume" and self.paused:
            self._paused_s += time.monotonic() - self._paused_since
            self.paused, self._paused_since = False, None
        elif msg.command == "stop":
            self.node.stop()
        elif msg.command not in ("pause", "resume"):
            log.warning("player: unknown control command %r ignored", msg.command)
        log.info("player: control %r -> %s", msg.command, "paused" if self.paused else "playing")

    def wait_while_paused(self) -> bool:
        """Block while paused; False once the node is stopping."""
        while self.paused and not self.node.stopped:
            self.node.wait(0.02)
        return not self.node.stopped

    def take_paused_s(self) -> float:
        """Seconds spent paused since the last call (the rate clock skips them)."""
        s, self._paused_s = self._paused_s, 0.0
        return s


def _imu_up_to(messages, imu_pub, frame_ns: int, last_imu_ns: int):
    """Lockstep: publish the IMU samples that follow a frame until one is stamped at or after it (the estimator
    integrates up to the frame's stamp, and would otherwise wait for a sample the player holds back until the frame
    is answered). Returns the last published IMU stamp and the first message that is not an IMU sample (None: none
    read; the stream's end or a dataset error ends the look-ahead, and the player's next read ends the stream)."""
    while last_imu_ns < frame_ns:
        try:
            msg = next(messages)
        except StopIteration:
            return last_imu_ns, None
        except DatasetError as exc:
            log.error("player: %s", exc)
            return last_imu_ns, None
        if not isinstance(msg, ImuSample):
            return last_imu_ns, msg
        imu_pub.publish(msg)
        last_imu_ns = int(msg.header.stamp_ns)
    return last_imu_ns, None


def _await_state(node: Node, states, stamp_ns: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not node.stopped and time.monotonic() < deadline:
        try:
            st = states.get(timeout=0.05)
        except Empty:
            continue
        if st.header.stamp_ns >= stamp_ns:
            return True
    return False
