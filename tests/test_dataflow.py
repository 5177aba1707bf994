"""The in-process runner (shared/dataflow.py) on tiny nodes: the order a lockstep run gives, held triggers,
pacing, idle inputs, ticks and the graph of declarations."""

from __future__ import annotations

import numpy as np
import pytest

from shared import topics
from shared.dataflow import Emit, InProcessRunner, Input, ProcessNode, graph
from shared.messages import EstimatorState, Header, ImuSample, MultiCameraFrame, StreamEnd


def _frame(t: int) -> MultiCameraFrame:
    return MultiCameraFrame(header=Header(stamp_ns=t, seq=0, frame_id="rig"), images=(np.zeros((2, 2), np.uint8),),
                            camera_names=("cam0",), stamps_ns=np.array([t], np.int64))


def _state(t: int) -> EstimatorState:
    return EstimatorState(header=Header(stamp_ns=t, seq=0, frame_id="W"), T_WS=np.eye(4), v_W=np.zeros(3),
                          gyro_bias=np.zeros(3), acc_bias=np.zeros(3), covariance=np.eye(15), status="tracking")


class Poser(ProcessNode):
    """Turns each frame into a state of the same stamp (a stand-in for frontend + back end)."""

    name = "poser"
    inputs = (Input(topics.FRAME, "on_frame", role="trigger"),)
    outputs = (topics.STATE,)

    def on_frame(self, f):
        return [Emit(topics.STATE, _state(f.header.stamp_ns))]


class Waiter(ProcessNode):
    """Handles a frame only with the state of its stamp (as depth waits for its pose); paced; counts ticks."""

    name = "waiter"
    inputs = (Input(topics.FRAME, "on_frame", role="trigger"),
              Input(topics.STATE, "on_state", wait_until_trigger_stamp=True),
              Input(topics.STREAM_END, "on_end", role="idle"))
    outputs = ()

    def __init__(self, period_s: float = 0.0) -> None:
        self.trigger_period_s = period_s
        self.poses, self.handled, self.ticks, self.log = set(), [], 0, []

    def on_state(self, s):
        self.poses.add(s.header.stamp_ns)
        self.log.append(("state", s.header.stamp_ns))

    def on_frame(self, f):
        t = f.header.stamp_ns
        self.handled.append((t, t in self.poses))
        self.log.append(("frame", t))

    def on_end(self, e):
        self.log.append(("end", e.header.stamp_ns))

    def tick(self):
        self.ticks += 1
        return []


class ImuWaiter(Waiter):
    """Waits for an IMU sample at its frame's stamp, which never comes: released when nothing else is pending."""

    name = "imu_waiter"
    inputs = (Input(topics.FRAME, "on_frame", role="trigger"),
              Input(topics.IMU, "on_imu", wait_until_trigger_stamp=True))

    def on_imu(self, s):
        self.log.append(("imu", s.header.stamp_ns))


def _source(n: int, dt: int = 50_000_000):
    for k in range(n):
        t = 1_000_000_000 + k * dt
        yield topics.IMU, ImuSample(header=Header(stamp_ns=t - 1_000_000, seq=k, frame_id="S"), omega_S=np.zeros(3),
                                    acc_S=np.zeros(3))
        yield topics.FRAME, _frame(t)
    yield topics.STREAM_END, StreamEnd(header=Header(stamp_ns=t, seq=0, frame_id="player"), source="player",
                                       frames_sent=n)


def test_a_trigger_waits_for_its_side_input_within_the_cascade():
    waiter, imu_waiter = Waiter(), ImuWaiter()
    runner = InProcessRunner([waiter, imu_waiter, Poser()])  # the waiter gets each frame before the poser
    runner.run(_source(6))
    assert [ok for _, ok in waiter.handled] == [True] * 6  # every frame handled with its own state
    assert waiter.log[-1][0] == "end"  # the idle input after everything else
    assert waiter.ticks == 13  # once after each source message
    # the IMU never reaches the frame's stamp: the frame is handled anyway, once the cascade has nothing else
    assert len(imu_waiter.handled) == 6 and imu_waiter.log[:2] == [("imu", 999_000_000), ("frame", 1_000_000_000)]
    assert runner.emitted == {"estimator/state": 6} and runner.now_ns == 1_250_000_000


def test_a_paced_trigger_skips_frames_by_their_stamps():
    waiter = Waiter(period_s=0.1)
    InProcessRunner([waiter, Poser()]).run(_source(7))
    assert [t for t, _ in waiter.handled] == [1_000_000_000, 1_100_000_000, 1_200_000_000, 1_300_000_000]


def test_graph_of_declarations():
    g = graph([Poser, Waiter])
    assert g["sensors/frame"] == {"publishers": [], "subscribers": ["poser", "waiter"]}
    assert g["estimator/state"] == {"publishers": ["poser"], "subscribers": ["waiter"]}


class Picky(ProcessNode):
    """Refuses frames of an odd second: a counted, logged drop, and the node goes on."""

    name = "picky"
    inputs = (Input(topics.FRAME, "on_frame", role="trigger"),)
    outputs = ()

    def __init__(self) -> None:
        self.seen = []

    def on_frame(self, f):
        from shared.dataflow import RejectedMessage

        if (f.header.stamp_ns // 50_000_000) % 2:
            raise RejectedMessage("odd")
        self.seen.append(f.header.stamp_ns)


def test_a_rejected_message_is_counted_and_the_node_goes_on():
    picky = Picky()
    runner = InProcessRunner([picky])
    runner.run(_source(6))
    assert len(picky.seen) == 3 and runner.rejected == {("picky", "sensors/frame"): 3}


class LatePoser(Poser):
    """Emits the state from its handler and leaves work for after_publish, which logs when it runs."""

    name = "late_poser"

    def __init__(self) -> None:
        self.log = []

    def on_frame(self, f):
        self.log.append(("frame", f.header.stamp_ns))
        return super().on_frame(f)

    def after_publish(self):
        self.log.append(("after", self.log[-1][1]))
        return []


def test_after_publish_runs_after_each_trigger_before_the_next():
    node, waiter = LatePoser(), Waiter()
    runner = InProcessRunner([node, waiter])
    runner.run(_source(3))
    assert node.log == [(k, 1_000_000_000 + i * 50_000_000) for i in range(3) for k in ("frame", "after")]
    assert [ok for _, ok in waiter.handled] == [True] * 3  # what the handler emitted still arrives
    assert len(runner.times[("late_poser", "after_publish")]) == 3


def _paced_rate(costs_s, period_s: float = 0.1, frame_dt_s: float = 0.05, rule=None) -> float:
    """Messages handled per second by the live runner's pacing (a frame every ``frame_dt_s``, handling costs
    ``costs_s`` in turn), simulated on a clock: the frame taken is the newest one at the take."""
    from transport.runner import next_trigger_time
    rule = rule or next_trigger_time
    now, next_t, taken, last_frame = 0.0, 0.0, 0, -1
    for cost in costs_s:
        now = max(now, next_t)
        frame = int(np.floor(now / frame_dt_s + 1e-9))  # the newest frame; wait for the next when it was taken
        if frame <= last_frame:
            frame, now = last_frame + 1, (last_frame + 1) * frame_dt_s
        last_frame, taken = frame, taken + 1
        next_t = rule(next_t, now, period_s)
        now += cost
    return taken / now


def test_paced_trigger_keeps_its_average_rate_when_some_messages_are_slow():
    # the depth service at 10 Hz on 20 Hz frames: 40 ms per frame, every fifth 160 ms (an MVS keyframe)
    costs = [0.04, 0.04, 0.04, 0.04, 0.16] * 40
    assert _paced_rate(costs) == pytest.approx(10.0, abs=0.15)
    # the old rule (a period after each take) loses the slow ones' overrun: ~9.2 Hz
    assert _paced_rate(costs, rule=lambda scheduled, now, period: now + period) < 9.4
    # a node slower than its period on every message runs as fast as it can, without bursts
    assert _paced_rate([0.15] * 100) == pytest.approx(1 / 0.15, rel=0.05)
    from transport.runner import next_trigger_time
    assert next_trigger_time(0.0, 10.0, 0.1) == pytest.approx(9.95)  # after a long stall: one more at once,
    assert next_trigger_time(9.95, 10.01, 0.1) == pytest.approx(10.05)  # then on the schedule again
