"""Reading a sigmaslam recording back into typed messages.

::

    for key, log_time_ns, msg in read_recording("run.mcap", topics=["sigmaslam/robot0/estimator/state"]):
        ...
    cfg = from_dict(SystemConfig, read_metadata("run.mcap"))

Only the native channels (message encoding ``sigmaslam-codec-v1``) are returned; the Foxglove
mirror channels are skipped. Works on files written by the recorder and on files rebuilt by
:func:`services.recorder.recovery.recover` (a file cut short must be recovered first).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable, Iterator

import yaml
from mcap.reader import make_reader

from services.recorder.mcap_writer import CONFIG_METADATA, NATIVE_ENCODING
from shared import codec
from shared.codec import Message


def read_recording(path: str | Path, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, Message]]:
    """Yield ``(key expression, log_time_ns, message)`` of the native channels in log-time order.

    ``topics``: full key expressions to keep (None: all). A payload that does not decode raises
    :class:`shared.codec.DecodeError` naming the key and time.
    """
    wanted = None if topics is None else list(topics)
    with open(path, "rb") as f:
        reader = make_reader(f)
        for _schema, channel, message in reader.iter_messages(topics=wanted):
            if channel.message_encoding != NATIVE_ENCODING:
                continue
            try:
                msg = codec.decode(message.data)
            except codec.DecodeError as exc:
                raise codec.DecodeError(f"{path}: {channel.topic} at log time {message.log_time}: {exc}") from exc
            yield channel.topic, message.log_time, msg


def read_metadata(path: str | Path) -> dict:
    """The resolved system config stored in the recording (plain data, as ``sigmaslam config`` prints it).

    Raises LookupError if the file has no ``sigmaslam.config`` metadata.
    """
    with open(path, "rb") as f:
        for record in make_reader(f).iter_metadata():
            if record.name == CONFIG_METADATA:
                return yaml.safe_load(record.metadata["yaml"]) or {}
    raise LookupError(f"{path}: no '{CONFIG_METADATA}' metadata in this recording")
