"""Writing sigmaslam messages to MCAP: native channels plus Foxglove mirrors.

Native channels (one per key expression and message type seen) carry the exact wire bytes of
:mod:`shared.codec`: message encoding :data:`NATIVE_ENCODING`, schema name = message class name,
schema encoding :data:`NATIVE_ENCODING`, schema data = JSON description of the fields (name, kind,
dtype, shape, doc). ``log_time`` is the receive time [ns since the Unix epoch], ``publish_time`` the
message's ``header.stamp_ns``, ``sequence`` its ``header.seq`` (mod 2^32).

The file is chunked; the writer goes straight to the OS (no user-space buffer), so after a SIGKILL
everything up to the last completed chunk is on disk and :func:`services.recorder.recovery.recover`
can rebuild an indexed file. :meth:`RecordingWriter.close` writes the summary and index.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from pathlib import Path

from mcap.writer import CompressionType, Writer

from services.recorder import foxglove
from shared import codec
from shared.codec import NATIVE_ENCODING, Message

log = logging.getLogger(__name__)

CONFIG_METADATA = "sigmaslam.config"
PROFILE = "sigmaslam"
COMPRESSIONS = {"lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD, "none": CompressionType.NONE}


class RecordingError(RuntimeError):
    """The recording file cannot be written (bad path, bad settings)."""


class DirectFile:
    """Minimal binary file object for mcap's Writer that writes straight to the OS (no buffering)."""

    def __init__(self, path: str | Path) -> None:
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._pos = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data).cast("B")
        while view:
            n = os.write(self._fd, view)
            view = view[n:]
            self._pos += n
        return len(data)

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


def schema_description(cls: type[Message]) -> bytes:
    """JSON description of a message class's fields (the native channels' schema data)."""
    fields = [{"name": "header", "kind": "header", "doc": "stamp_ns [ns] int64, seq, frame_id"}]
    for f in dataclasses.fields(cls):
        if f.name == "header":
            continue
        entry = {"name": f.name, "doc": f.metadata.get("doc", "")}
        if "dtype" in f.metadata:
            entry.update(kind="array", dtype=f.metadata["dtype"].str, shape=list(f.metadata["shape"]))
        else:
            entry["kind"] = "scalar"
        fields.append(entry)
    return json.dumps({"type": cls.__name__, "type_id": cls.TYPE_ID, "codec_version": codec.VERSION,
                       "doc": (cls.__doc__ or "").strip(), "fields": fields}, indent=1).encode()


class RecordingWriter:
    """An open MCAP recording. Not thread-safe: one writer thread calls :meth:`write`."""

    def __init__(self, path: str | Path, *, chunk_size_bytes: int = 4 << 20, compression: str = "lz4",
                 foxglove_mirror: bool = True, config_yaml: str | None = None) -> None:
        if chunk_size_bytes < 1:
            raise RecordingError(f"recorder.chunk_size_bytes must be positive, got {chunk_size_bytes}")
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = DirectFile(self.path)
        except OSError as exc:
            raise RecordingError(f"cannot open {self.path} for writing: {exc}") from exc
        self._mcap = Writer(self._file, chunk_size=chunk_size_bytes, compression=COMPRESSIONS[compression])
        self._mcap.start(profile=PROFILE, library="sigmaslam-recorder")
        self._foxglove = foxglove_mirror
        self._schemas: dict[object, int] = {}
        self._channels: dict[tuple[str, object], int] = {}
        self.messages = 0
        self.mirror_messages = 0
        self.dropped_undecodable = 0
        self.mirror_errors = 0
        self.closed = False
        if config_yaml is not None:
            self._mcap.add_metadata(CONFIG_METADATA, {"yaml": config_yaml})

    def _channel(self, topic: str, schema_key: object, make_schema, encoding: str) -> int:
        cid = self._channels.get((topic, schema_key))
        if cid is None:
            sid = self._schemas.get(schema_key)
            if sid is None:
                name, schema_encoding, data = make_schema()
                sid = self._schemas[schema_key] = self._mcap.register_schema(name, schema_encoding, data)
            cid = self._channels[(topic, schema_key)] = self._mcap.register_channel(topic, encoding, sid)
        return cid

    def write(self, key: str, data: bytes, log_time_ns: int) -> bool:
        """Record the payload received on ``key``; returns False (counted, logged) if it does not decode."""
        try:
            msg = codec.decode(data)
        except codec.DecodeError as exc:
            self.dropped_undecodable += 1
            if self.dropped_undecodable == 1 or self.dropped_undecodable % 100 == 0:
                log.warning("%s: dropped an undecodable payload of %d B (%d so far): %s", key, len(data),
                            self.dropped_undecodable, exc)
            return False
        self.write_message(key, msg, log_time_ns, data)
        return True

    def write_message(self, key: str, msg: Message, log_time_ns: int | None = None, data: bytes | None = None) -> None:
        """Record a decoded message (``data``: its encoded bytes, if already at hand)."""
        cls = type(msg)
        log_time_ns = time.time_ns() if log_time_ns is None else log_time_ns
        cid = self._channel(key, cls, lambda: (cls.__name__, NATIVE_ENCODING, schema_description(cls)), NATIVE_ENCODING)
        h = msg.header
        self._mcap.add_message(cid, log_time=log_time_ns, data=codec.encode(msg) if data is None else data,
                               publish_time=max(int(h.stamp_ns), 0), sequence=int(h.seq) & 0xFFFFFFFF)
        self.messages += 1
        if self._foxglove:
            self._write_mirrors(key, msg, log_time_ns)

    def _write_mirrors(self, key: str, msg: Message, log_time_ns: int) -> None:
        try:
            mirrors = foxglove.mirror(key, msg)
        except (ValueError, TypeError) as exc:
            self.mirror_errors += 1
            if self.mirror_errors == 1 or self.mirror_errors % 100 == 0:
                log.warning("%s: no Foxglove mirror for a %s (%d errors so far): %s", key, type(msg).__name__,
                            self.mirror_errors, exc)
            return
        for topic, proto in mirrors:
            pcls = type(proto)
            cid = self._channel(topic, pcls, lambda: (pcls.DESCRIPTOR.full_name, foxglove.SCHEMA_ENCODING,
                                                      foxglove.file_descriptor_set(pcls)), foxglove.MESSAGE_ENCODING)
            self._mcap.add_message(cid, log_time=log_time_ns, data=proto.SerializeToString(),
                                   publish_time=max(int(msg.header.stamp_ns), 0), sequence=int(msg.header.seq) & 0xFFFFFFFF)
            self.mirror_messages += 1

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A named metadata record of string pairs (e.g. dataset calibration)."""
        self._mcap.add_metadata(name, data)

    def add_attachment(self, name: str, media_type: str, data: bytes, log_time_ns: int = 0) -> None:
        """A file stored in the recording (e.g. ground truth, a mesh)."""
        self._mcap.add_attachment(create_time=time.time_ns(), log_time=log_time_ns, name=name, media_type=media_type,
                                  data=data)

    def flush(self) -> None:
        """Close the chunk in progress and hand it to the OS (it survives a SIGKILL from now on)."""
        self._mcap.flush()

    def close(self) -> None:
        """Write the last chunk, the summary and the index; safe to call twice."""
        if self.closed:
            return
        self.closed = True
        try:
            self._mcap.finish()
        finally:
            self._file.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
