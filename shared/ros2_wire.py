"""ROS 2 on Zenoh as rmw_zenoh puts it (ros2/rmw_zenoh docs/design.md, Jazzy): the names, not the session.

What a ROS 2 node on ``rmw_zenoh_cpp`` expects of a peer, written down once for the processes that speak ROS 2
(the ROS 2 face ``sigmaslam ros2``, its live input ``sigmaslam ros2_input``) and the stand-in robot of the tests:

- a topic's data travels on the key ``<domain>/<topic without its leading '/'>/<DDS type name>/<RIHS01 type hash>``,
  e.g. ``0/robot/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_3cc9...``; the payload is the message in CDR (with its
  4-byte encapsulation header, as ``rosbags``' ``serialize_cdr`` writes it);
- each sample carries an attachment: the publisher's sequence number (int64), the source timestamp (int64, wall
  clock [ns]) and the publisher's 16-byte gid, in Zenoh's own serialisation (little-endian integers, a LEB128 length
  before strings and byte arrays). rmw_zenoh releases for Jazzy write each value after its name
  (``'labelled'``: "sequence_number", n, "source_timestamp", t, "source_gid", gid: 77 bytes); later ones drop the
  names (``'plain'``: 33 bytes). :func:`decode_attachment` reads both;
- discovery is by liveliness tokens under ``@ros2_lv/<domain>/<session id>/<node id>/<entity id>/<kind>/<enclave>/
  <namespace>/<node name>`` (kind ``NN`` a node, ``MP`` a publisher, ``MS`` a subscription), followed for a topic
  by ``/<topic>/<DDS type name>/<type hash>/<QoS>``; a '/' inside a name is written '%', an empty one is '%'.

Type names and hashes come from ``rosbags``' Jazzy type store (:func:`type_store`), never typed in here.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib

ATTACHMENT_LAYOUTS = ("labelled", "plain")
ADMIN_SPACE = "@ros2_lv"
_NAMES = ("sequence_number", "source_timestamp", "source_gid")


class WireError(ValueError):
    """Bytes or a key that do not follow rmw_zenoh's layout; the message says what is wrong."""


@functools.lru_cache(maxsize=1)
def type_store():
    """``rosbags``' ROS 2 Jazzy type store (message classes, CDR, RIHS01 hashes)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def dds_type_name(ros_type: str) -> str:
    """``'nav_msgs/msg/Odometry'`` -> ``'nav_msgs::msg::dds_::Odometry_'`` (the name rmw_zenoh puts in keys)."""
    parts = ros_type.split("/")
    if len(parts) != 3 or not all(parts):
        raise WireError(f"not a ROS 2 type name (package/msg/Name): {ros_type!r}")
    return f"{parts[0]}::{parts[1]}::dds_::{parts[2]}_"


@functools.lru_cache(maxsize=None)
def type_hash(ros_type: str) -> str:
    """The RIHS01 hash of ``ros_type`` in the Jazzy store, ``'RIHS01_<64 hex>'``."""
    return type_store().hash_rihs01(ros_type)


def fq_topic(namespace: str, name: str) -> str:
    """The fully qualified topic: ``name`` if absolute, else under ``namespace`` (``('/robot', 'odom')`` ->
    ``'/robot/odom'``; ``('', 'tf')`` -> ``'/tf'``)."""
    if not name or name.endswith("/") or "//" in name:
        raise WireError(f"not a ROS 2 topic name: {name!r}")
    if name.startswith("/"):
        return name
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return f"{ns}/{name}"


def data_key(domain_id: int, topic: str, ros_type: str) -> str:
    """The Zenoh key a ROS 2 message of ``ros_type`` on the fully qualified ``topic`` travels on."""
    return f"{int(domain_id)}/{topic.strip('/')}/{dds_type_name(ros_type)}/{type_hash(ros_type)}"


def topic_wildcard(domain_id: int, topic: str) -> str:
    """Every key of ``topic`` whatever its type: a subscriber on it sees, and can refuse, a wrong type or hash."""
    return f"{int(domain_id)}/{topic.strip('/')}/*/*"


def split_data_key(key: str) -> tuple[int, str, str, str]:
    """``key`` -> (domain id, fully qualified topic, DDS type name, type hash)."""
    parts = key.split("/")
    if len(parts) < 4 or not parts[0].isdigit():
        raise WireError(f"not an rmw_zenoh data key (<domain>/<topic>/<type>/<hash>): {key!r}")
    return int(parts[0]), "/" + "/".join(parts[1:-2]), parts[-2], parts[-1]


def mangle(name: str) -> str:
    """A name inside a liveliness key: '/' written '%', empty (or the root '/') as '%'."""
    return name.replace("/", "%") if name else "%"


@dataclasses.dataclass(frozen=True)
class Qos:
    """The QoS a token announces; what equals rmw_zenoh's default (reliable, volatile, keep last 10) is left empty."""

    reliable: bool = True
    transient_local: bool = False  # durability: late joiners get the last samples (tf_static)
    depth: int = 10

    def keyexpr(self) -> str:
        # reliability : durability : history,depth : deadline s,ns : lifespan s,ns : liveliness,lease s,ns
        rel = "" if self.reliable else "2"
        dur = "1" if self.transient_local else ""
        depth = "" if self.depth == 10 else str(int(self.depth))
        return f"{rel}:{dur}:,{depth}:,:,:,,"


def node_token(domain_id: int, zid: str, node_id: int, namespace: str, node_name: str) -> str:
    """The liveliness key that announces a node (kind ``NN``)."""
    ns = "/" + namespace.strip("/") if namespace.strip("/") else "/"
    return "/".join([ADMIN_SPACE, str(int(domain_id)), zid, str(node_id), str(node_id), "NN", mangle("/"),
                     mangle(ns), mangle(node_name)])


def entity_token(domain_id: int, zid: str, node_id: int, entity_id: int, kind: str, namespace: str, node_name: str,
                 topic: str, ros_type: str, qos: Qos = Qos()) -> str:
    """The liveliness key of a publisher (``kind='MP'``) or a subscription (``'MS'``) of the node."""
    if kind not in ("MP", "MS"):
        raise WireError(f"entity kind must be MP or MS, got {kind!r}")
    ns = "/" + namespace.strip("/") if namespace.strip("/") else "/"
    return "/".join([ADMIN_SPACE, str(int(domain_id)), zid, str(node_id), str(entity_id), kind, mangle("/"),
                     mangle(ns), mangle(node_name), mangle(topic), dds_type_name(ros_type), type_hash(ros_type),
                     qos.keyexpr()])


def gid_of(token: str) -> bytes:
    """A 16-byte gid for the entity announced by ``token`` (a hash of the key: unique per entity, stable)."""
    return hashlib.blake2b(token.encode(), digest_size=16).digest()


@dataclasses.dataclass(frozen=True)
class Attachment:
    """What rmw_zenoh attaches to every sample."""

    sequence_number: int
    source_timestamp_ns: int  # wall clock at publication [ns]
    gid: bytes  # 16 bytes: the publisher's

    def encode(self, layout: str = "labelled") -> bytes:
        if layout not in ATTACHMENT_LAYOUTS:
            raise WireError(f"attachment layout must be one of {ATTACHMENT_LAYOUTS}, got {layout!r}")
        if len(self.gid) != 16:
            raise WireError(f"a gid has 16 bytes, got {len(self.gid)}")
        values = [_int64(self.sequence_number), _int64(self.source_timestamp_ns), _leb128(16) + bytes(self.gid)]
        if layout == "plain":
            return b"".join(values)
        return b"".join(_leb128(len(n)) + n.encode() + v for n, v in zip(_NAMES, values))


def decode_attachment(data: bytes) -> Attachment:
    """Read an attachment in either layout (:data:`ATTACHMENT_LAYOUTS`)."""
    data = bytes(data)
    pos = 0

    def take(n: int) -> bytes:
        nonlocal pos
        if pos + n > len(data):
            raise WireError(f"attachment truncated: {len(data)} bytes")
        out = data[pos:pos + n]
        pos += n
        return out

    labelled = len(data) > 0 and data[0] == len(_NAMES[0]) and data[1:1 + len(_NAMES[0])] == _NAMES[0].encode()
    values = []
    for name in _NAMES:
        if labelled:
            got = take(_read_leb128(take)).decode(errors="replace")
            if got != name:
                raise WireError(f"attachment: expected {name!r}, found {got!r}")
        if name == "source_gid":
            n = _read_leb128(take)
            if n != 16:
                raise WireError(f"attachment: a gid has 16 bytes, found {n}")
            values.append(take(16))
        else:
            values.append(int.from_bytes(take(8), "little", signed=True))
    if pos != len(data):
        raise WireError(f"attachment: {len(data) - pos} bytes left over")
    return Attachment(values[0], values[1], values[2])


def _int64(v: int) -> bytes:
    return int(v).to_bytes(8, "little", signed=True)


def _leb128(n: int) -> bytes:
    out = bytearray()
    while True:
        b, n = n & 0x7F, n >> 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _read_leb128(take) -> int:
    n, shift = 0, 0
    while True:
        b = take(1)[0]
        n |= (b & 0x7F) << shift
        if not b & 0x80:
            return n
        shift += 7
        if shift > 63:
            raise WireError("attachment: length prefix too long")
