"""Submap meshes as the viewer keeps them: latest mesh and pose per submap, which ones changed since
the last draw, their colours, and the world mesh (all submaps in W) for export. No viser, no Zenoh."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from services.viewer.colors import height_colors, submap_color
from shared.geometry import transform_points
from shared.messages import SubmapMesh

COLOR_MODES = ("submap", "height", "uncertainty")
# in 'height' mode a pose update recolours the mesh only when some bounding-box corner moved this much in z
HEIGHT_RECOLOR_TOL_M = 0.05


@dataclasses.dataclass
class SubmapEntry:
    submap_id: int
    T_WM: np.ndarray  # (4,4) float64, current pose
    vertices_M: np.ndarray  # (V,3) float32
    faces: np.ndarray  # (F,3) int32
    vertex_colors: np.ndarray  # (V,3) uint8 or (0,3)
    stamp_ns: int
    T_WM_colored: np.ndarray  # pose the drawn colours were computed at (height mode)
    corners_M: np.ndarray  # (8,3) bounding-box corners in M

    @property
    def has_vertex_colors(self) -> bool:
        return len(self.vertex_colors) == len(self.vertices_M) and len(self.vertices_M) > 0


@dataclasses.dataclass(frozen=True)
class SubmapChanges:
    """What the drawer must do: re-send these meshes, move these, delete these."""

    meshes: tuple[int, ...] = ()
    poses: tuple[int, ...] = ()
    removed: tuple[int, ...] = ()

    def __bool__(self) -> bool:
        return bool(self.meshes or self.poses or self.removed)


def _bbox_corners(v: np.ndarray) -> np.ndarray:
    if len(v) == 0:
        return np.zeros((8, 3))
    lo, hi = v.min(0).astype(np.float64), v.max(0).astype(np.float64)
    sel = np.array(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij")).reshape(3, -1).T
    return np.where(sel == 1, hi, lo)


class SubmapStore:
    """Latest mesh and pose per submap with change tracking (callers serialise access)."""

    def __init__(self, color_mode: str = "submap", height_range_m: tuple[float, float] = (-1.0, 3.0)) -> None:
        self.entries: dict[int, SubmapEntry] = {}
        self.height_range_m = height_range_m
        self._mesh_dirty: set[int] = set()
        self._pose_dirty: set[int] = set()
        self._removed: set[int] = set()
        self.color_mode = "submap"
        self.set_color_mode(color_mode)
        self.mesh_updates = 0  # meshes that changed geometry or colour (counted per message)
        self.pose_updates = 0  # messages that only moved a submap
        self.unchanged = 0  # messages identical to what is held

    def set_color_mode(self, mode: str) -> None:
        if mode not in COLOR_MODES:
            raise ValueError(f"colour mode must be one of {COLOR_MODES}, got {mode!r}")
        if mode != self.color_mode:
            self.color_mode = mode
            self._mesh_dirty.update(self.entries)

    def apply(self, msg: SubmapMesh) -> str:
        """Take one SubmapMesh; returns 'mesh', 'pose' or 'unchanged' (what the drawer will have to do)."""
        sid = int(msg.submap_id)
        old = self.entries.get(sid)
        T = np.asarray(msg.T_WM, np.float64)
        _check_mesh(msg)
        if old is not None and _same_mesh(old, msg):
            if np.array_equal(old.T_WM, T):
                self.unchanged += 1
                return "unchanged"
            old.T_WM = T.copy()
            old.stamp_ns = msg.header.stamp_ns
            if self.color_mode == "height" and self._height_stale(old):
                self._mark_mesh(old)
                return "mesh"
            self._pose_dirty.add(sid)
            self.pose_updates += 1
            return "pose"
        v = np.ascontiguousarray(msg.vertices_M, np.float32)
        entry = SubmapEntry(sid, T.copy(), v, np.ascontiguousarray(msg.faces, np.int32),
                            np.ascontiguousarray(msg.vertex_colors, np.uint8), msg.header.stamp_ns, T.copy(),
                            _bbox_corners(v))
        self.entries[sid] = entry
        self._removed.discard(sid)
        self._mark_mesh(entry)
        return "mesh"

    def remove(self, submap_id: int) -> None:
        if self.entries.pop(submap_id, None) is not None:
            self._mesh_dirty.discard(submap_id)
            self._pose_dirty.discard(submap_id)
            self._removed.add(submap_id)

    def _mark_mesh(self, entry: SubmapEntry) -> None:
        self._mesh_dirty.add(entry.submap_id)
        self._pose_dirty.discard(entry.submap_id)
        self.mesh_updates += 1

    def _height_stale(self, e: SubmapEntry) -> bool:
        z_now = transform_points(e.T_WM, e.corners_M)[:, 2]
        z_then = transform_points(e.T_WM_colored, e.corners_M)[:, 2]
        return bool(np.max(np.abs(z_now - z_then)) > HEIGHT_RECOLOR_TOL_M)

    def take_changes(self) -> SubmapChanges:
        """Submaps changed since the last call (then forgotten)."""
        ch = SubmapChanges(tuple(sorted(self._mesh_dirty)), tuple(sorted(self._pose_dirty - self._mesh_dirty)),
                           tuple(sorted(self._removed)))
        self._mesh_dirty.clear()
        self._pose_dirty.clear()
        self._removed.clear()
        return ch

    def colors(self, entry: SubmapEntry) -> np.ndarray:
        """(V,3) uint8 vertex colours of ``entry`` in the current mode (records the pose used for height)."""
        n = len(entry.vertices_M)
        if self.color_mode == "height":
            entry.T_WM_colored = entry.T_WM.copy()
            z_W = transform_points(entry.T_WM, entry.vertices_M.astype(np.float64))[:, 2]
            return height_colors(z_W, self.height_range_m)
        if self.color_mode == "uncertainty" and entry.has_vertex_colors:
            return entry.vertex_colors
        return np.broadcast_to(submap_color(entry.submap_id), (n, 3)).copy()

    def world_mesh(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All submaps in W: vertices (V,3) float64, faces (F,3) int64, colours (V,3) uint8 (current mode)."""
        verts, faces, cols = [], [], []
        offset = 0
        for sid in sorted(self.entries):
            e = self.entries[sid]
            verts.append(transform_points(e.T_WM, e.vertices_M.astype(np.float64)))
            faces.append(e.faces.astype(np.int64) + offset)
            cols.append(self.colors(e))
            offset += len(e.vertices_M)
        if not verts:
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.uint8)
        return np.concatenate(verts), np.concatenate(faces), np.concatenate(cols)


def _check_mesh(msg: SubmapMesh) -> None:
    """Reject what the browser could not draw (ValueError: the caller counts and logs the drop)."""
    if not np.isfinite(msg.T_WM).all() or not np.allclose(msg.T_WM[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"submap {msg.submap_id}: T_WM is not a finite homogeneous transform")
    if not np.isfinite(msg.vertices_M).all():
        raise ValueError(f"submap {msg.submap_id}: non-finite vertices")
    if len(msg.faces) and (msg.faces.min() < 0 or msg.faces.max() >= len(msg.vertices_M)):
        raise ValueError(f"submap {msg.submap_id}: face index outside 0..{len(msg.vertices_M) - 1}")


def _same_mesh(e: SubmapEntry, msg: SubmapMesh) -> bool:
    return (np.array_equal(e.vertices_M, msg.vertices_M) and np.array_equal(e.faces, msg.faces)
            and np.array_equal(e.vertex_colors, msg.vertex_colors))


def write_ply(path: str | Path, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None) -> Path:
    """Binary little-endian PLY with float32 vertices, optional uchar RGB and int32 triangle faces."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"write_ply needs (V,3) vertices and (F,3) faces, got {v.shape} and {f.shape}")
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError("write_ply: face index out of range")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vrec = np.empty(len(v), dtype=fields)
    vrec["x"], vrec["y"], vrec["z"] = v[:, 0], v[:, 1], v[:, 2]
    if colors is not None:
        c = np.asarray(colors, np.uint8)
        vrec["red"], vrec["green"], vrec["blue"] = c[:, 0], c[:, 1], c[:, 2]
    frec = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    frec["n"] = 3
    frec["i"] = f
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(v)}",
              "property float x", "property float y", "property float z"]
    if colors is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vrec.tobytes())
        fh.write(frec.tobytes())
    return path
