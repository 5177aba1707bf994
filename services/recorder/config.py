"""Configuration of the MCAP recorder (``sigmaslam record``)."""

from __future__ import annotations

import dataclasses
from typing import Literal

from shared.config import param


@dataclasses.dataclass(frozen=True)
class RecorderConfig:
    """What the recorder subscribes to, how it queues and how it writes the MCAP file."""

    key_expr: str = param("", "Zenoh key expression to record ('' = everything under the namespace: '<namespace>/**')")
    output_dir: str = param("recordings", "folder for recordings when no --out is given (file named by UTC time and pid)")
    chunk_size_bytes: int = param(4 * 1024 * 1024, "uncompressed MCAP chunk size; a SIGKILL loses at most the chunk in progress", "B")
    flush_period_s: float = param(1.0, "a chunk in progress is closed and written at least this often (bounds the loss on SIGKILL)", "s")
    compression: Literal["lz4", "zstd", "none"] = param("lz4", "chunk compression")
    queue_depth: int = param(4096, "hard bound on messages waiting between the Zenoh callback and the writer (beyond: counted drops)")
    queue_max_bytes: int = param(512 * 1024 * 1024, "hard bound on the bytes waiting in that queue (beyond: counted drops)", "B")
    foxglove: bool = param(True, "also write Foxglove-viewable protobuf mirror channels (images, depth, poses, meshes)")
