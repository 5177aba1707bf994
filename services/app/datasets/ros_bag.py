"""ROS bags read without ROS: ROS 2 (MCAP or sqlite3 storage) and ROS 1 bags, through the ``rosbags`` library.

- :func:`bag_topics`: topic -> (message type, count);
- :func:`choose_topics`: the camera and IMU topics, picked automatically when unambiguous (image topics of one
  kind, one IMU topic), else from the names given; clear errors otherwise;
- :func:`image_to_grey`: ``sensor_msgs/Image`` (mono8, mono16, bgr8, rgb8, bgra8, rgba8, bayer_*8) and
  ``sensor_msgs/CompressedImage`` to 8-bit grey;
- :func:`match_stereo`: frames of several cameras matched by header stamp within a tolerance;
- :func:`read_bag`: IMU samples and matched multi-camera frames, header stamps as the time (the cameras' Kalibr
  ``timeshift_cam_imu`` applied), what was dropped counted.

Header stamps are the time source (the sensor's time, not the recorder's receive time).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from shared import ros2_sensors
from shared.euroc_reader import DatasetError

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
IMU_TYPE = "sensor_msgs/msg/Imu"


class BagError(DatasetError):
    """A bag that cannot be used as asked; the message says what is missing or wrong."""


def is_ros_bag(path: str | Path) -> bool:
    """A ROS 1 ``.bag``, a ROS 2 bag folder (metadata.yaml), or an MCAP file whose channels are CDR (ROS 2)."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    if p.suffix == ".bag":
        return True
    if p.suffix == ".mcap" and p.is_file():
        from mcap.reader import make_reader

        try:
            with open(p, "rb") as f:
                summary = make_reader(f).get_summary()
        except Exception:  # noqa: BLE001 - not readable as MCAP: not a bag either
            return False
        return summary is not None and any(c.message_encoding == "cdr" for c in summary.channels.values())
    return False


def _reader(path: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if not path.exists():
        raise BagError(f"{path}: bag not found")
    return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))


def bag_topics(path: str | Path) -> dict[str, tuple[str, int]]:
    with _reader(Path(path)) as r:
        return {c.topic: (c.msgtype, c.msgcount) for c in r.connections}


def choose_topics(topics: dict[str, tuple[str, int]], cams: list[str] | None = None, imu: str | None = None,
                  path: str = "bag") -> tuple[list[str], str]:
    """(camera topics in rig order, IMU topic). Without names: every image topic (sorted; raw Image topics are
    preferred when the same camera also has a compressed one) and the one IMU topic."""
    listing = ", ".join(f"{t} ({m.split('/')[-1]}, {n})" for t, (m, n) in sorted(topics.items()))
    for t in (cams or []) + ([imu] if imu else []):
        if t not in topics:
            raise BagError(f"{path}: topic {t} not in the bag; it has: {listing}")
    if not cams:
        images = sorted(t for t, (m, _) in topics.items() if m in IMAGE_TYPES)
        raw = [t for t in images if topics[t][0] == IMAGE_TYPES[0]]
        cams = raw or images
        if not cams:
            raise BagError(f"{path}: no sensor_msgs/Image or CompressedImage topic; it has: {listing}")
        if len(cams) > 2:
            raise BagError(f"{path}: {len(cams)} image topics ({', '.join(cams)}): name the stereo pair with "
                           f"--cam LEFT --cam RIGHT")
    for t in cams:
        if topics[t][0] not in IMAGE_TYPES:
            raise BagError(f"{path}: {t} is {topics[t][0]}, not an image topic")
    if imu is None:
        imus = sorted(t for t, (m, _) in topics.items() if m == IMU_TYPE)
        if not imus:
            raise BagError(f"{path}: no sensor_msgs/Imu topic: sigmaslam is visual-inertial and needs the IMU; "
                           f"it has: {listing}")
        if len(imus) > 1:
            raise BagError(f"{path}: {len(imus)} IMU topics ({', '.join(imus)}): name one with --imu")
        imu = imus[0]
    elif topics[imu][0] != IMU_TYPE:
        raise BagError(f"{path}: {imu} is {topics[imu][0]}, not sensor_msgs/Imu")
    return list(cams), imu


def image_to_grey(msg, msgtype: str) -> np.ndarray:
    """8-bit grey image of an Image or CompressedImage message (shared/ros2_sensors.py); BagError for an encoding
    it does not know."""
    try:
        return ros2_sensors.image_to_grey(msg, msgtype)
    except ros2_sensors.UnreadableImage as exc:
        raise BagError(str(exc)) from None


_stamp_ns = ros2_sensors.stamp_ns


def match_stereo(stamps: list[np.ndarray], tolerance_ns: int) -> tuple[np.ndarray, list[int]]:
    """Frames of several cameras matched to the first camera's by nearest stamp within ``tolerance_ns`` (one to
    one). Returns (M, n_cams) indices into each camera's sorted stamps, and the unmatched count per camera."""
    base = np.sort(stamps[0])
    keep = np.ones(len(base), bool)
    idx = [np.arange(len(base))]
    for s in stamps[1:]:
        s = np.sort(s)
        if len(s) == 0 or len(base) == 0:
            keep[:] = False
            idx.append(np.zeros(len(base), int))
            continue
        hi = np.clip(np.searchsorted(s, base), 0, len(s) - 1)
        lo = np.clip(hi - 1, 0, len(s) - 1)
        j = np.where(np.abs(s[lo] - base) < np.abs(s[hi] - base), lo, hi)
        dist = np.abs(s[j] - base)
        cand = np.flatnonzero(dist <= tolerance_ns)
        order = cand[np.argsort(dist[cand], kind="stable")]
        _, first = np.unique(j[order], return_index=True)  # one to one: the nearest claim on a frame wins
        ok = np.zeros(len(base), bool)
        ok[order[first]] = True
        keep &= ok
        idx.append(j)
    out = np.stack([i[keep] for i in idx], 1) if len(base) else np.zeros((0, len(stamps)), int)
    unmatched = [len(s) - len(out) for s in stamps]
    return out, unmatched


@dataclass
class BagContent:
    imu_stamps_ns: np.ndarray  # (N,) int64
    imu: np.ndarray  # (N, 6): w xyz [rad/s], a xyz [m/s^2]
    frame_stamps_ns: np.ndarray  # (M,) int64: the first camera's stamps (timeshift applied)
    stats: dict = field(default_factory=dict)


def scan_bag(path: str | Path, cams: list[str], imu: str, timeshift_ns: list[int] | None = None,
             tolerance_ns: int = 2_000_000) -> tuple[BagContent, list[np.ndarray], np.ndarray]:
    """First pass: IMU samples and every camera's stamps (shifted), and the stereo matching."""
    shifts = timeshift_ns or [0] * len(cams)
    stamps: list[list[int]] = [[] for _ in cams]
    imu_t, imu_v = [], []
    stats = {"imu_nonfinite": 0, "imu_backwards": 0}
    with _reader(Path(path)) as r:
        conns = [c for c in r.connections if c.topic in cams or c.topic == imu]
        for conn, _, raw in r.messages(connections=conns):
            msg = r.deserialize(raw, conn.msgtype)
            if conn.topic == imu:
                v = [msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z,
                     msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z]
                if not np.all(np.isfinite(v)):
                    stats["imu_nonfinite"] += 1
                    continue
                imu_t.append(_stamp_ns(msg))
                imu_v.append(v)
            else:
                k = cams.index(conn.topic)
                stamps[k].append(_stamp_ns(msg) + shifts[k])
    t = np.asarray(imu_t, np.int64)
    order = np.argsort(t, kind="stable")
    t, v = t[order], np.asarray(imu_v, np.float64).reshape(-1, 6)[order]
    dup = np.r_[False, np.diff(t) <= 0]
    stats["imu_backwards"] = int(dup.sum())  # repeated or out-of-order stamps after sorting: dropped
    t, v = t[~dup], v[~dup]
    arrs = [np.unique(np.asarray(s, np.int64)) for s in stamps]
    for k, (s, a) in enumerate(zip(stamps, arrs)):
        stats[f"cam{k}_repeated_stamps"] = len(s) - len(a)
    if not len(t):
        raise BagError(f"{path}: no IMU sample on {imu}")
    if any(len(a) == 0 for a in arrs):
        raise BagError(f"{path}: no image on {[c for c, a in zip(cams, arrs) if len(a) == 0]}")
    pairs, unmatched = match_stereo(arrs, tolerance_ns)
    for k, n in enumerate(unmatched):
        stats[f"cam{k}_unmatched"] = n
    content = BagContent(t, v, arrs[0][pairs[:, 0]], stats)
    return content, arrs, pairs


def iter_frames(path: str | Path, cams: list[str], arrs: list[np.ndarray], pairs: np.ndarray,
                timeshift_ns: list[int] | None = None, progress: bool = False, stats: dict | None = None
                ) -> Iterator[tuple[int, list[np.ndarray]]]:
    """Second pass: (stamp_ns, [grey image per camera]) of the matched frames in stamp order. Images of a frame
    wait in a small buffer until every camera's has been read. A compressed image that does not decode drops its
    frame (counted in ``stats['undecodable_images']``); an unknown raw encoding is an error."""
    stats = {} if stats is None else stats
    stats.setdefault("undecodable_images", 0)
    shifts = timeshift_ns or [0] * len(cams)
    want = [dict(zip(a[pairs[:, k]].tolist(), range(len(pairs)))) for k, a in enumerate(arrs)]
    pending: dict[int, list] = {}
    next_out = 0
    done: dict[int, list] = {}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(pairs), unit="frame", desc="bag frames")
    with _reader(Path(path)) as r:
        conns = [c for c in r.connections if c.topic in cams]
        for conn, _, raw in r.messages(connections=conns):
            k = cams.index(conn.topic)
            msg = r.deserialize(raw, conn.msgtype)
            i = want[k].get(_stamp_ns(msg) + shifts[k])
            if i is None:
                continue
            slot = pending.setdefault(i, [None] * len(cams))
            if slot[k] is None:
                try:
                    slot[k] = image_to_grey(msg, conn.msgtype)
                except BagError:
                    if not conn.msgtype.endswith("CompressedImage"):
                        raise
                    stats["undecodable_images"] += 1
                    slot[k] = False  # the frame is dropped
            if all(x is not None for x in slot):
                done[i] = pending.pop(i)
            while next_out in done:
                imgs = done.pop(next_out)
                if all(x is not False for x in imgs):
                    yield int(arrs[0][pairs[next_out, 0]]), imgs
                next_out += 1
                if bar is not None:
                    bar.update(1)
        for i in sorted(done):  # after a frame that never completed: the rest, in order
            if all(x is not False for x in done[i]):
                yield int(arrs[0][pairs[i, 0]]), done[i]
    if bar is not None:
        bar.close()
