"""A saved map on disk: the folder layout, atomic writes, and where a run's map lives.

A saved map is a folder ``DIR/map/`` (``DIR``: a run's output folder) holding

- ``sparse.npz``: what localisation needs, written by the back end (services/backend/loop/saved_map.py):
  keyframes with their poses, features, descriptors and landmark positions, the pose graph's edges;
- ``dense.npz``: the occupancy submaps, written by the mapping service (services/mapping/io.py).

Each file carries its own format tag and is written atomically (a temporary file beside it, fsynced, then renamed
over the old one), so a process killed mid-save leaves the previous complete file. The two files are written by two
processes at their own times; each is complete on its own. Nothing here imports the transport.
"""

from __future__ import annotations

import os
from pathlib import Path

# header.frame_id of states a run localising in a saved map publishes before it has relocalised: a temporary frame
# of its own, not the map's ("W" from then on, as in every other run)
UNALIGNED_FRAME = "odom"

MAP_DIR = "map"
SPARSE_FILE = "sparse.npz"
DENSE_FILE = "dense.npz"


def map_dir(path: str | Path) -> Path:
    """The map folder of ``path``: ``path`` itself when it holds a map file or is named ``map``, else
    ``path/map`` (a run's output folder)."""
    p = Path(path)
    if p.name == MAP_DIR or (p / SPARSE_FILE).exists() or (p / DENSE_FILE).exists():
        return p
    return p / MAP_DIR


def run_map_dir(out_dir: str | Path) -> Path:
    """Where a run writing to ``out_dir`` keeps its map: always ``out_dir/map`` (writers use this; readers,
    given a folder by a user, :func:`map_dir`)."""
    return Path(out_dir) / MAP_DIR


def sparse_path(path: str | Path) -> Path:
    return map_dir(path) / SPARSE_FILE


def dense_path(path: str | Path) -> Path:
    return map_dir(path) / DENSE_FILE


def atomic_write(path: str | Path, write) -> Path:
    """Call ``write(fh)`` on a temporary file beside ``path``, fsync it and rename it to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def remove_stale_temps(folder: str | Path) -> list[Path]:
    """Delete ``.<name>.<pid>.tmp`` files of :func:`atomic_write` left by processes that no longer run
    (killed mid-save); returns what was removed. The completed files beside them are untouched."""
    removed = []
    for tmp in Path(folder).glob(".*.tmp") if Path(folder).is_dir() else []:
        pid = tmp.name.rsplit(".", 2)[-2]
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)
            continue  # its writer is alive
        except ProcessLookupError:
            pass
        except PermissionError:
            continue
        tmp.unlink(missing_ok=True)
        removed.append(tmp)
    return removed
