"""The mapping's map on disk: what a mapping node starts from and where its map goes.

:class:`MapStore` of an output folder (``None``: nothing is read back or written):

- :meth:`MapStore.initial_map`: after a supervisor restart, the last checkpoint ``<out>/map/dense.npz`` (same
  submaps, ids continue); else the dense submaps of a saved map (``mapping.prior_map``, frozen in its frame); else an
  empty map. A checkpoint or saved map that cannot be read starts an empty map (logged).
- :meth:`MapStore.checkpoint`: writes a snapshot of the map in a thread of its own (atomic rename), skipping one
  that falls due while the previous is still being written.
- :meth:`MapStore.write`: ``mesh.ply`` (world), ``submaps/submap_NNN.ply`` (each in its frame M), ``map/dense.npz``
  and ``mapping.json`` (counts, integration times, per-submap sizes and poses).
"""

from __future__ import annotations

import json
import logging
import threading
from pathlib import Path

import numpy as np

from services.mapping.config import MappingConfig
from services.mapping.io import MapFileError, load_map, map_arrays, save_map, write_map_arrays, write_ply
from services.mapping.submaps import SubmapMapper, meshes_in_world
from shared.map_folder import DENSE_FILE, dense_path, remove_stale_temps, run_map_dir

log = logging.getLogger("sigmaslam.mapping")


class MapStore:
    """The map folder of one mapping process (``out_dir``; None: in memory only); ``restarts``: how often the
    supervisor restarted this process (a restart resumes from the checkpoint)."""

    def __init__(self, out_dir: str | None, restarts: int = 0) -> None:
        self.out_dir = out_dir or None
        self.restarts = restarts
        self._writer: threading.Thread | None = None  # the checkpoint being written
        self._unchanged: dict = {}  # the last copies of the submaps' fields (map_arrays' reuse)

    def initial_map(self, cfg: MappingConfig) -> tuple[SubmapMapper, dict[str, int]]:
        """(the map to start from, counts that say where it came from: ``resumed`` 1 or 0 after a restart,
        ``prior_submaps`` from a saved map; none for an empty map)."""
        counts: dict[str, int] = {}
        if self.out_dir:
            for tmp in remove_stale_temps(run_map_dir(self.out_dir)):
                log.warning("removed %s, left by a save that was killed", tmp)
        if self.restarts > 0 and self.out_dir:
            path = run_map_dir(self.out_dir) / DENSE_FILE
            try:
                mapper = load_map(path)
            except (MapFileError, FileNotFoundError) as exc:
                log.warning("mapping restarted without a usable checkpoint (%s): starting an empty map", exc)
                counts["resumed"] = 0
            else:
                log.warning("mapping restarted: resumed %d submaps from %s", len(mapper.submaps), path)
                print(f"mapping: resumed {len(mapper.submaps)} submaps from {path}", flush=True)
                return mapper, {"resumed": 1}
        if cfg.prior_map:
            # the saved map's submaps stay where they are, in its frame (frozen: the keyframes they followed belong
            # to the run that made them); new depth goes into new submaps, which follow this run's keyframes
            path = dense_path(cfg.prior_map)
            try:
                mapper = load_map(path)
            except (MapFileError, FileNotFoundError) as exc:
                log.warning("mapping: no dense submaps from the saved map (%s): starting an empty map", exc)
            else:
                mapper.estimator_reset()  # freeze them; the next depth frame starts a new submap
                print(f"mapping: {len(mapper.submaps)} submaps of the saved map {path}", flush=True)
                return mapper, {**counts, "prior_submaps": len(mapper.submaps)}
        return SubmapMapper(cfg.sensor, cfg.submaps), counts

    @property
    def writing(self) -> bool:
        """A checkpoint is being written."""
        return self._writer is not None and self._writer.is_alive()

    def snapshot(self, mapper: SubmapMapper) -> dict[str, np.ndarray]:
        """A copy of the map to write (closed submaps' copies are kept from the last snapshot)."""
        return map_arrays(mapper, self._unchanged)

    def checkpoint(self, arrays: dict[str, np.ndarray], counts: dict) -> None:
        """Write a :meth:`snapshot` to map/dense.npz in a thread of its own: a large map takes seconds to write
        (1.8 s median at 34 submaps), during which depth frames would pile up; a failed write is counted in
        ``counts['checkpoints_failed']``."""
        self._writer = threading.Thread(target=self._write_checkpoint, name="mapping-checkpoint", daemon=True,
                                        args=(arrays, run_map_dir(self.out_dir) / DENSE_FILE, counts))
        self._writer.start()

    def _write_checkpoint(self, arrays: dict[str, np.ndarray], path: Path, counts: dict) -> None:
        try:
            write_map_arrays(arrays, path)
        except OSError as exc:  # a full disk: the run goes on, the last complete checkpoint stays
            counts["checkpoints_failed"] += 1
            log.warning("checkpoint %s not written: %s", path, exc)

    def wait(self) -> None:
        """Let a checkpoint being written finish (before the final map is written to the same file)."""
        if self._writer is not None:
            self._writer.join()
            self._writer = None

    def write(self, mapper: SubmapMapper, counts: dict, integrate_ms: list[float], report_only: bool = False) -> None:
        """The map (mesh.ply, submaps/, map/dense.npz) and mapping.json; with ``report_only`` only mapping.json."""
        out_dir = Path(self.out_dir)
        self.wait()
        out_dir.mkdir(parents=True, exist_ok=True)
        if not report_only:
            parts = [(sm.T_WM, *mapper.mesh(sm)[:2]) for sm in mapper.submaps]  # each submap meshed once
            write_ply(out_dir / "mesh.ply", *meshes_in_world(parts))
            for sm, (_, sv, sf) in zip(mapper.submaps, parts):
                write_ply(out_dir / "submaps" / f"submap_{sm.id:03d}.ply", sv, sf)
            save_map(mapper, run_map_dir(out_dir) / DENSE_FILE)
        ms = np.array(integrate_ms) if integrate_ms else np.array([np.nan])
        report = {"counts": dict(counts), "integrate_ms_p50": float(np.median(ms)),
                  "integrate_ms_p90": float(np.percentile(ms, 90)), "map_bytes": mapper.nbytes(),
                  "submaps": [{"id": sm.id, "bytes": sm.store.nbytes(), "blocks": sm.store.n_blocks,
                               "refined_blocks": sm.store.n_refined - len(sm.store.free_rows), "frames": sm.n_frames,
                               "T_WM": sm.T_WM.tolist(), "keyframe_id": sm.keyframe_id} for sm in mapper.submaps]}
        (out_dir / "mapping.json").write_text(json.dumps(report, indent=1))
