"""Sensor data sources for the player: an EuRoC ASL folder or a sigmaslam MCAP recording.

:func:`open_source` gives a :class:`Source` whose ``messages()`` yields ``ImuSample`` and
``MultiCameraFrame`` in time order (no transport involved). Bad data is counted in ``stats`` and
skipped (unreadable images, samples whose time goes backwards, undecodable MCAP payloads); a missing
or malformed dataset raises :class:`shared.euroc_reader.DatasetError` with the path.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Iterator

from shared import codec, topics
from shared.euroc_reader import DatasetError, EurocDataset
from shared.messages import ImuSample, MultiCameraFrame

log = logging.getLogger(__name__)


class Source:
    """Common interface: ``name``, ``stats`` (dict of counters), ``messages()``."""

    name: str
    stats: dict[str, int]

    def messages(self, imu_margin_ns: int | None = None, start_ns: int = 0) -> Iterator[ImuSample | MultiCameraFrame]:
        """Messages in time order. ``imu_margin_ns`` (not None): leave out IMU samples more than this long before
        the first or after the last frame, where the source knows its frames' span up front (EuRoC folders;
        a recording plays every sample). ``start_ns`` > 0: begin this long into the data (EuRoC: after the first
        frame; a recording: after its first message)."""
        raise NotImplementedError


class EurocSource(Source):
    def __init__(self, path: str | Path):
        self.ds = EurocDataset(path)
        self.name = str(path)
        self.stats = self.ds.stats

    def messages(self, imu_margin_ns: int | None = None, start_ns: int = 0):
        return self.ds.messages(imu_margin_ns, start_ns)


class McapSource(Source):
    """IMU and frame messages of a recording (any namespace), re-sequenced, in stamp order per type."""

    def __init__(self, path: str | Path):
        p = Path(path)
        if not p.is_file():
            raise DatasetError(f"{p}: recording not found")
        with open(p, "rb") as f:
            if f.read(8) != b"\x89MCAP0\r\n":
                raise DatasetError(f"{p}: not an MCAP file")
        self.path, self.name = p, str(p)
        self.stats = {"undecodable": 0, "backwards_stamps": 0, "other_messages": 0}

    def messages(self, imu_margin_ns: int | None = None, start_ns: int = 0):
        from mcap.reader import make_reader

        from shared.codec import NATIVE_ENCODING

        last = {ImuSample: -1, MultiCameraFrame: -1}
        seq = {ImuSample: 0, MultiCameraFrame: 0}
        begin = None  # stamp of the first message + start_ns: earlier ones are not played
        suffixes = ("/" + topics.IMU.key, "/" + topics.FRAME.key)
        with open(self.path, "rb") as f:
            try:
                stream = make_reader(f).iter_messages(log_time_order=True)
                for _schema, channel, message in stream:
                    if channel.message_encoding != NATIVE_ENCODING or not channel.topic.endswith(suffixes):
                        self.stats["other_messages"] += 1
                        continue
                    try:
                        msg = codec.decode(message.data)
                    except codec.DecodeError as exc:
                        self.stats["undecodable"] += 1
                        log.warning("%s: %s: undecodable message skipped (%s)", self.path, channel.topic, exc)
                        continue
                    kind = type(msg)
                    if kind not in last:
                        self.stats["other_messages"] += 1
                        continue
                    if msg.header.stamp_ns <= last[kind]:
                        self.stats["backwards_stamps"] += 1
                        log.warning("%s: %s at %d not after %d; skipped", self.path, kind.__name__, msg.header.stamp_ns,
                                    last[kind])
                        continue
                    last[kind] = msg.header.stamp_ns
                    begin = msg.header.stamp_ns + start_ns if begin is None else begin
                    if msg.header.stamp_ns < begin:
                        continue
                    yield _with_seq(msg, seq[kind])
                    seq[kind] += 1
            except Exception as exc:  # a truncated/corrupt file: stop cleanly, say why
                if isinstance(exc, (KeyboardInterrupt, GeneratorExit)):
                    raise
                raise DatasetError(f"{self.path}: cannot read recording ({type(exc).__name__}: {exc}); "
                                   "a cut file can be repaired with 'sigmaslam record --recover'") from exc


def _with_seq(msg, seq: int):
    import dataclasses

    return dataclasses.replace(msg, header=dataclasses.replace(msg.header, seq=seq))


def open_source(path: str | Path) -> Source:
    """EuRoC folder (``mav0`` or its parent) or ``.mcap`` file."""
    p = Path(path)
    if p.suffix == ".mcap" or p.is_file():
        return McapSource(p)
    return EurocSource(p)
