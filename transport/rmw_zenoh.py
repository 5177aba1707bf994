"""A ROS 2 participant on Zenoh, as an rmw_zenoh node appears (names and bytes: shared/ros2_wire.py).

::

    with RosParticipant(session_cfg, domain_id=0, namespace="/robot0", node_name="sigmaslam") as ros:
        odom = ros.publisher("odom", "nav_msgs/msg/Odometry")
        odom.put(cdr_bytes)                               # key 0/robot0/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_...
        ros.subscribe("imu", "sensor_msgs/msg/Imu", on_sample)   # on_sample(RosSample): every type seen on the topic

Its own Zenoh session (the ROS 2 network can be another Zenoh network than sigmaslam's: rmw_zenoh's router on the
robot), a liveliness token for the node, one per publisher (``MP``) and one per subscription (``MS``), the
attachment on every sample. A subscription listens to every type on its topic so that a publisher of the wrong type
or type hash is seen and refused by the caller (a counted drop), not silently missed.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import threading
import time
from typing import Callable

import zenoh

from shared import ros2_wire as wire

log = logging.getLogger(__name__)


def participant_config(transport_cfg, connect=()) -> zenoh.Config:
    """The Zenoh config of a ROS 2 side: ``connect`` (``ros2.connect``), else the transport's endpoints (and its
    JSON5 file); no shared memory (an rmw_zenoh peer need not have it on)."""
    from transport.session import zenoh_config

    return zenoh_config(dataclasses.replace(transport_cfg, connect=tuple(connect) or transport_cfg.connect,
                                            shared_memory=False,
                                            zenoh_json5=transport_cfg.zenoh_json5 if not connect else ""))


@dataclasses.dataclass(frozen=True)
class RosSample:
    """One sample as received: its key's parts, the CDR payload, the attachment bytes (empty when none)."""

    topic: str  # fully qualified
    dds_type: str
    type_hash: str
    payload: bytes
    attachment: bytes


class RosPublisher:
    """One ROS 2 publisher: a Zenoh publisher on the data key, its token, a sequence number."""

    def __init__(self, session: zenoh.Session, key: str, token: str, layout: str, reliable: bool) -> None:
        self.key, self.token_key, self.layout = key, token, layout
        self.gid = wire.gid_of(token)
        self._seq = itertools.count(1)
        self.sent = 0
        self.bytes_sent = 0
        cc = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
        self._pub = session.declare_publisher(key, congestion_control=cc)
        self._token = session.liveliness().declare_token(token)

    def put(self, payload: bytes) -> None:
        att = wire.Attachment(next(self._seq), time.time_ns(), self.gid).encode(self.layout)
        self._pub.put(payload, attachment=att)
        self.sent += 1
        self.bytes_sent += len(payload)

    def close(self) -> None:
        for h in (self._token, self._pub):
            try:
                h.undeclare()
            except Exception:  # already gone with the session
                pass


class RosParticipant:
    """A ROS 2 node on a Zenoh session of its own (see the module's docstring)."""

    def __init__(self, zenoh_config: zenoh.Config, domain_id: int = 0, namespace: str = "", node_name: str = "sigmaslam",
                 attachment_layout: str = "labelled") -> None:
        if attachment_layout not in wire.ATTACHMENT_LAYOUTS:
            raise ValueError(f"attachment layout must be one of {wire.ATTACHMENT_LAYOUTS}, got {attachment_layout!r}")
        self.zenoh_config, self.domain_id, self.namespace = zenoh_config, int(domain_id), namespace
        self.node_name, self.layout = node_name, attachment_layout
        self.session: zenoh.Session | None = None
        self.zid = ""
        self._entity_ids = itertools.count(1)
        self._handles: list = []
        self._lock = threading.Lock()

    def open(self) -> RosParticipant:
        self.session = zenoh.open(self.zenoh_config)
        self.zid = str(self.session.info.zid())
        self.node_token = wire.node_token(self.domain_id, self.zid, 0, self.namespace, self.node_name)
        self._handles.append(self.session.liveliness().declare_token(self.node_token))
        return self

    def topic(self, name: str) -> str:
        return wire.fq_topic(self.namespace, name)

    def publisher(self, name: str, ros_type: str, qos: wire.Qos = wire.Qos()) -> RosPublisher:
        """A publisher of ``ros_type`` on topic ``name`` (relative names are under the namespace)."""
        topic = self.topic(name)
        token = wire.entity_token(self.domain_id, self.zid, 0, next(self._entity_ids), "MP", self.namespace,
                                  self.node_name, topic, ros_type, qos)
        pub = RosPublisher(self.session, wire.data_key(self.domain_id, topic, ros_type), token, self.layout, qos.reliable)
        self._handles.append(pub)
        return pub

    def subscribe(self, name: str, ros_type: str, callback: Callable[[RosSample], None],
                  qos: wire.Qos = wire.Qos()) -> str:
        """Call ``callback`` (on Zenoh's thread) with every sample on topic ``name``, whatever its type; announces a
        subscription of ``ros_type``. Returns the fully qualified topic."""
        topic = self.topic(name)
        token = wire.entity_token(self.domain_id, self.zid, 0, next(self._entity_ids), "MS", self.namespace,
                                  self.node_name, topic, ros_type, qos)

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                _, t, dds, h = wire.split_data_key(str(sample.key_expr))
            except wire.WireError:
                return
            att = sample.attachment
            callback(RosSample(t, dds, h, sample.payload.to_bytes(), b"" if att is None else att.to_bytes()))

        self._handles.append(self.session.declare_subscriber(wire.topic_wildcard(self.domain_id, topic), on_sample))
        self._handles.append(self.session.liveliness().declare_token(token))
        return topic

    def close(self) -> None:
        for h in reversed(self._handles):
            try:
                h.close() if isinstance(h, RosPublisher) else h.undeclare()
            except Exception:  # the session may have closed it already
                pass
        self._handles.clear()
        if self.session is not None:
            session, self.session = self.session, None
            session.close()

    def __enter__(self) -> RosParticipant:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()
