"""Bad input on the bus of a live replica run: garbage bytes, truncated messages and messages of the wrong
type on every topic, and well-formed messages with bad content (NaN/inf, duplicated and backwards stamps,
wrong image size). No service may crash or restart, undecodable payloads are counted as drops in each
subscriber's stats, and the estimator keeps tracking at its rate afterwards.

Reduced form: 3 garbage payloads per topic and kind; ``SIGMASLAM_E2E=full``: 20.
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from shared import codec, messages, topics
from shared.codec import Header
from tools import fault_inject

FULL = os.environ.get("SIGMASLAM_E2E", "") == "full"
N = 20 if FULL else 3
ALL_TOPICS = [t for t in vars(topics).values() if isinstance(t, topics.Topic)]


def _garbage(rng: np.random.Generator, topic: topics.Topic) -> list[bytes]:
    """Undecodable payloads: random bytes, a valid message of another type, and that message cut short."""
    hb = codec.encode(messages.Heartbeat(header=Header(stamp_ns=1), service="x", pid=1, state="running"))
    other = hb if topic.msg_type is not messages.Heartbeat else codec.encode(
        messages.ImuSample(header=Header(stamp_ns=1), omega_S=np.zeros(3), acc_S=np.zeros(3)))
    out = []
    for _ in range(N):
        out.append(rng.bytes(int(rng.integers(0, 2000))))
        out.append(other)
        out.append(other[: int(rng.integers(0, len(other)))])
    return out


def _bad_content(newest_ns: int, frame: messages.MultiCameraFrame | None) -> list[tuple[topics.Topic, object]]:
    """Well-formed messages whose content the services must refuse (or bridge) without harm."""
    t = newest_ns + 1
    nan3 = np.full(3, np.nan)
    bad = [(topics.IMU, messages.ImuSample(header=Header(stamp_ns=t), omega_S=nan3, acc_S=np.zeros(3))),
           (topics.IMU, messages.ImuSample(header=Header(stamp_ns=t), omega_S=np.zeros(3), acc_S=np.full(3, np.inf))),
           (topics.IMU, messages.ImuSample(header=Header(stamp_ns=1), omega_S=np.zeros(3), acc_S=np.zeros(3))),  # backwards
           (topics.FEATURES, messages.FeatureFrame(header=Header(stamp_ns=1), landmark_ids=np.arange(5),
                                                   camera_index=np.zeros(5, np.int16), uv=np.full((5, 2), np.nan, np.float32),
                                                   p_W_init=np.full((5, 3), np.nan), is_keyframe=True)),
           (topics.FRAME, messages.MultiCameraFrame(header=Header(stamp_ns=1), images=(np.zeros((7, 9), np.uint8),) * 2,
                                                    camera_names=("cam0", "cam1"), stamps_ns=np.ones(2, np.int64)))]
    if frame is not None:  # a duplicate of a frame already played
        bad.append((topics.FRAME, frame))
    depth = np.full((384, 512), np.nan, np.float32)
    depth[::2] = np.inf
    depth[1::4] = -1.0
    K = np.array([[300.0, 0, 256], [0, 300.0, 192], [0, 0, 1]])
    for topic in (topics.DEPTH_STEREO, topics.DEPTH_FUSED):
        bad.append((topic, messages.DepthFrame(header=Header(stamp_ns=newest_ns), depth=depth, sigma=np.full_like(depth, np.nan),
                                               K=K, T_WC=np.eye(4), T_SC=np.eye(4), source="stereo")))
    return bad


@pytest.mark.e2e
@pytest.mark.processes  # the pipeline's processes through tools.fault_inject, which the tier finder does not follow
def test_garbage_and_bad_content_on_every_topic(tmp_path):
    rng = np.random.default_rng(12)
    sent: dict[str, int] = {}

    def inject(node, probe) -> dict:
        frames = node.subscriber(topics.FRAME, depth=1)
        played = frames.get(timeout=10.0)  # republished below: a duplicate frame
        before = probe.queue_drops()
        for topic in ALL_TOPICS:
            keys = [topic.key] if "*" not in topic.key else [topics.per_service(topic, s) for s in fault_inject.PIPELINE]
            for key in keys:
                for payload in _garbage(rng, topic):
                    node.session.put(node.key_expr(topic, key), payload)
                    sent[topic.key] = sent.get(topic.key, 0) + 1
        newest = max((s[1] for s in probe.states), default=1)
        for topic, msg in _bad_content(newest, played):
            node.session.put(node.key_expr(topic), codec.encode(msg))
        time.sleep(2.0)  # stats period x 4
        return {"before": before, "after": probe.queue_drops(), "sent": dict(sent)}

    rep = fault_inject.run(_replica(), tmp_path / "bus", [], 0.5, 3.0, [], during=inject)
    assert rep.get("started"), rep
    # nobody crashed or restarted
    assert all(n == 0 for n in rep["restarts"].values()), rep["restarts"]
    # every subscriber counted the undecodable payloads of its topics as drops
    before, after = rep["during"]["before"], rep["during"]["after"]
    checked = 0
    for service in fault_inject.PIPELINE:
        for queue, d in after[service].items():
            if queue in sent and sent[queue] > 0:
                gained = d["dropped"] - before.get(service, {}).get(queue, {}).get("dropped", 0)
                assert gained >= 3 * N, (service, queue, gained, sent[queue])
                checked += 1
    assert checked >= 6, after
    # the estimator tracks on at its rate
    base, after_w = rep["baseline"], rep["measure"]
    assert after_w["rate_hz"] >= 0.6 * base["rate_hz"], (base, after_w)
    assert "tracking" in after_w["statuses"], after_w


def _replica() -> str:
    from services.app.synth.api import ensure_default_replica

    return str(ensure_default_replica())
