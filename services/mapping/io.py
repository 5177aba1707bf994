"""Saving and loading a whole submap map (one .npz, written atomically) and writing PLY meshes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from shared.occupancy.blocks import BlockStore
from services.mapping.config import SensorModelConfig, SubmapConfig
from services.mapping.submaps import FROZEN, SubmapMapper
from shared.config import from_dict, to_dict
from shared.map_folder import atomic_write

FORMAT = "sigmaslam-occupancy-map/1"


class MapFileError(ValueError):
    """A map file that cannot be read."""


def save_map(mapper: SubmapMapper, path: str | Path) -> Path:
    """Write every submap (fields, poses, keyframe binding) and the configs to ``path`` (.npz)."""
    return write_map_arrays(map_arrays(mapper), path)


def map_arrays(mapper: SubmapMapper, reuse: dict | None = None) -> dict[str, np.ndarray]:
    """A copy of everything :func:`save_map` writes, as named arrays: the map may go on changing while another
    thread writes the copy (:func:`write_map_arrays`). ``reuse``: a dict kept between calls, in which the copy of
    each submap's fields is kept and given again while the submap is unchanged (not the current one, same frames,
    blocks and refined voxels): only the growing submap is copied, not the whole map."""
    meta = {"format": FORMAT, "sensor": to_dict(mapper.sensor), "submaps_cfg": to_dict(mapper.cfg), "submaps": []}
    arrays: dict[str, np.ndarray] = {}
    current = mapper.current
    for sm in mapper.submaps:
        meta["submaps"].append({"id": sm.id, "anchor_stamp_ns": sm.anchor_stamp_ns, "n_frames": sm.n_frames,
                                "keyframe_id": sm.keyframe_id, "keyframe_stamp_ns": sm.keyframe_stamp_ns})
        arrays[f"s{sm.id}/T_WM"] = np.array(sm.T_WM)
        arrays[f"s{sm.id}/T_KM"] = np.array(sm.T_KM)
        if sm.anchor_view is not None:
            for k, v in zip(("anchor_depth", "anchor_K", "anchor_T_MC"), sm.anchor_view):
                arrays[f"s{sm.id}/{k}"] = np.array(v)
        state = (sm is current, sm.n_frames, sm.store.n_blocks, sm.store.n_refined)
        if reuse is not None and sm.id in reuse and reuse[sm.id][0] == state:
            fields = reuse[sm.id][1]
        else:
            fields = sm.store.arrays()  # copies
            if reuse is not None:
                reuse[sm.id] = (state, fields)
        for k, v in fields.items():
            arrays[f"s{sm.id}/{k}"] = v
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    return arrays


def write_map_arrays(arrays: dict[str, np.ndarray], path: str | Path) -> Path:
    """Write :func:`map_arrays`'s snapshot to ``path`` (.npz) atomically."""
    return atomic_write(Path(path), lambda fh: np.savez(fh, **arrays))


def load_map(path: str | Path) -> SubmapMapper:
    """Read a map written by :func:`save_map`; meshes are rebuilt on the next ``remesh()``."""
    try:
        with np.load(path) as z:
            data = {k: z[k] for k in z.files}
        meta = json.loads(bytes(data.pop("meta")).decode())
    except (OSError, ValueError, KeyError) as exc:
        raise MapFileError(f"{path}: not a readable map file ({exc})") from exc
    if meta.get("format") != FORMAT:
        raise MapFileError(f"{path}: unknown format {meta.get('format')!r}")
    mapper = SubmapMapper(from_dict(SensorModelConfig, meta["sensor"]), from_dict(SubmapConfig, meta["submaps_cfg"]))
    for info in meta["submaps"]:
        p = f"s{info['id']}/"
        sub = {k[len(p):]: v for k, v in data.items() if k.startswith(p)}
        sm = mapper.new_submap(sub["T_WM"], info["anchor_stamp_ns"])
        sm.store = BlockStore.from_arrays(sub)
        sm.n_frames, sm.keyframe_id, sm.T_KM = info["n_frames"], info["keyframe_id"], sub["T_KM"]
        sm.keyframe_stamp_ns = int(info.get("keyframe_stamp_ns", -1))  # maps written before it: not known
        if "anchor_depth" in sub:
            sm.anchor_view = (sub["anchor_depth"], sub["anchor_K"], sub["anchor_T_MC"])
        sm.mesher.mark(sm.store, sm.store.refined_slots())
    return mapper


def append_submaps(dst: SubmapMapper, src: SubmapMapper, T: np.ndarray) -> int:
    """Add ``src``'s submaps to ``dst``, moved by ``T`` (``src``'s world frame in ``dst``'s), with new ids after
    ``dst``'s and frozen (they follow no keyframe of ``dst``'s run); returns how many. Both maps must have the same
    voxel size."""
    if abs(dst.sensor.voxel_size_m - src.sensor.voxel_size_m) > 1e-9:
        raise MapFileError(f"voxel sizes differ: {dst.sensor.voxel_size_m} m and {src.sensor.voxel_size_m} m")
    for sm in src.submaps:
        new = dst.new_submap(np.asarray(T, float) @ sm.T_WM, sm.anchor_stamp_ns)
        new.store, new.n_frames, new.T_KM, new.anchor_view = sm.store, sm.n_frames, sm.T_KM, sm.anchor_view
        new.keyframe_id = FROZEN
        new.mesher.mark(new.store, new.store.refined_slots())
    return len(src.submaps)


def write_ply(path: str | Path, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None,
              scalars: dict[str, np.ndarray] | None = None) -> Path:
    """Binary little-endian PLY of a triangle mesh (optional uint8 RGB and float32 named values per vertex; no faces:
    a point cloud), written atomically."""
    path = Path(path)
    v = np.asarray(vertices, np.float32).reshape(-1, 3)
    f = np.asarray(faces, np.int32).reshape(-1, 3)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(v)}",
              "property float x", "property float y", "property float z"]
    vdt = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None and len(colors):
        header += ["property uchar red", "property uchar green", "property uchar blue"]
        vdt += [("r", "u1"), ("g", "u1"), ("b", "u1")]
    for name in scalars or {}:
        header.append(f"property float {name}")
        vdt.append((name, "<f4"))
    header += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    vert = np.empty(len(v), vdt)
    vert["x"], vert["y"], vert["z"] = v.T
    if colors is not None and len(colors):
        c = np.asarray(colors, np.uint8).reshape(-1, 3)
        vert["r"], vert["g"], vert["b"] = c.T
    for name, values in (scalars or {}).items():
        vert[name] = np.asarray(values, np.float32).reshape(-1)
    face = np.empty(len(f), [("n", "u1"), ("i", "<i4", (3,))])
    face["n"], face["i"] = 3, f

    def write(fh) -> None:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vert.tobytes())
        fh.write(face.tobytes())

    atomic_write(path, write)
    return path
