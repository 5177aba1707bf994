"""Rebuilding a complete, indexed MCAP file from one cut short (SIGKILL, power loss, full disk).

A recording killed without closing has its data section up to the last chunk written, then maybe a
partial chunk, and no summary, index or footer. :func:`recover` reads it front to back with mcap's
non-seeking stream reader (every record length checked against the bytes actually present, chunk
CRCs checked), stops cleanly at the first truncated or corrupt record, and writes every schema,
channel, metadata record, attachment and message it read before that point into a new file with a
summary and index. Messages of the partial last chunk are lost; nothing before it is.
"""

from __future__ import annotations

import dataclasses
import logging
import struct
import zlib
from pathlib import Path

from mcap.exceptions import EndOfFile, McapError
from mcap.records import Attachment, Channel, DataEnd, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import CRCValidationError, StreamReader
from mcap.writer import CompressionType, Writer

log = logging.getLogger(__name__)


class RecoveryError(RuntimeError):
    """The input is not an MCAP file at all (bad magic) or cannot be read."""


@dataclasses.dataclass
class RecoveryReport:
    messages: int = 0
    channels: int = 0
    schemas: int = 0
    metadata: int = 0
    attachments: int = 0
    complete: bool = False  # the input had its data end / footer (nothing was cut off)
    stopped_at_byte: int = 0  # bytes of the input read before the truncated/corrupt tail
    input_bytes: int = 0
    reason: str = ""  # why reading stopped early ('' when complete)


class _Strict:
    """File wrapper whose ``read(n)`` raises EndOfFile instead of returning fewer than n bytes."""

    def __init__(self, f) -> None:
        self._f = f
        self.pos = 0

    def read(self, n: int = -1) -> bytes:
        data = self._f.read(n)
        if n is not None and n >= 0 and len(data) < n:
            raise EndOfFile(f"wanted {n} bytes at offset {self.pos}, only {len(data)} left")
        self.pos += len(data)
        return data


def recover(path_in: str | Path, path_out: str | Path, *, chunk_size_bytes: int = 4 << 20) -> RecoveryReport:
    """Copy everything readable from ``path_in`` (possibly truncated) into a complete indexed ``path_out``."""
    path_in, path_out = Path(path_in), Path(path_out)
    if path_in.resolve() == path_out.resolve():
        raise RecoveryError("recover: the output must be a different file than the input")
    report = RecoveryReport(input_bytes=path_in.stat().st_size)
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    with open(path_in, "rb") as f_in:
        strict = _Strict(f_in)
        if f_in.read(8) != b"\x89MCAP0\r\n":
            raise RecoveryError(f"{path_in}: not an MCAP file (bad magic)")
        strict.pos = 8
        out = Writer(str(path_out), chunk_size=chunk_size_bytes, compression=CompressionType.LZ4)
        started = False
        records = StreamReader(strict, skip_magic=True, validate_crcs=True).records
        try:
            for record in records:
                report.stopped_at_byte = strict.pos
                if isinstance(record, Header):
                    out.start(profile=record.profile, library=record.library)
                    started = True
                    continue
                if not started:
                    out.start()
                    started = True
                if isinstance(record, Schema) and record.id not in schema_ids:
                    schema_ids[record.id] = out.register_schema(record.name, record.encoding, record.data)
                    report.schemas += 1
                elif isinstance(record, Channel) and record.id not in channel_ids:
                    if record.schema_id != 0 and record.schema_id not in schema_ids:
                        log.warning("%s: channel %r refers to unknown schema %d; skipped", path_in, record.topic, record.schema_id)
                        continue
                    channel_ids[record.id] = out.register_channel(record.topic, record.message_encoding,
                                                                  schema_ids.get(record.schema_id, 0), dict(record.metadata))
                    report.channels += 1
                elif isinstance(record, Message):
                    cid = channel_ids.get(record.channel_id)
                    if cid is None:
                        continue
                    out.add_message(cid, log_time=record.log_time, data=record.data,
                                    publish_time=record.publish_time, sequence=record.sequence)
                    report.messages += 1
                elif isinstance(record, Metadata):
                    out.add_metadata(record.name, dict(record.metadata))
                    report.metadata += 1
                elif isinstance(record, Attachment):
                    out.add_attachment(record.create_time, record.log_time, record.name, record.media_type, record.data)
                    report.attachments += 1
                elif isinstance(record, (DataEnd, Footer)):
                    report.complete = True
                    break
        except (EndOfFile, McapError, CRCValidationError, struct.error, zlib.error, ValueError, RuntimeError) as exc:
            # the truncated / corrupt tail (lz4 and zstd raise RuntimeError/ValueError subclasses)
            report.reason = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        finally:
            if not started:
                out.start()
            out.finish()
    if not report.complete:
        log.info("%s: read %d of %d bytes (%s); recovered %d messages on %d channels into %s", path_in,
                 report.stopped_at_byte, report.input_bytes, report.reason or "end of file", report.messages,
                 report.channels, path_out)
    return report
