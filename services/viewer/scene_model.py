"""What the viewer draws, kept without viser or Zenoh: messages in (:meth:`ViewerModel.apply`, any thread),
:class:`SceneUpdate` out (:meth:`ViewerModel.take_update`, the drawing thread). Receiving only stores the
latest data; colour mapping, image throttling and change tracking happen when an update is taken, so
a slow browser only makes updates coarser, never the receiving slower."""

from __future__ import annotations

import dataclasses
import math
import threading
import time

import cv2
import numpy as np

from services.viewer.colors import depth_image, gray_to_rgb, sigma_image
from services.viewer.config import ViewerConfig
from services.viewer.stats_panel import stats_markdown
from services.viewer.submaps import SubmapChanges, SubmapStore
from services.viewer.tracks import ChunkedTrajectory, GroundTruthOverlay, KeyframeTrack, LandmarkBuffer
from shared import messages as m
from shared.camera import CameraCalib
from shared.euroc import PoseSeries

LIVE_IMAGE_MAX_WIDTH = 376  # [px] the live image on the frustum is downscaled to this width
DEPTH_SOURCE_TIMEOUT_S = 2.0  # fused depth is shown unless none arrived for this long (then stereo)


@dataclasses.dataclass(frozen=True)
class Frustum:
    name: str
    T_WC: np.ndarray  # (4,4)
    fov_y_rad: float
    aspect: float  # width / height


@dataclasses.dataclass(frozen=True)
class MeshData:
    T_WM: np.ndarray
    vertices_M: np.ndarray  # (V,3) float32
    faces: np.ndarray  # (F,3) int32
    colors: np.ndarray  # (V,3) uint8


@dataclasses.dataclass
class SceneUpdate:
    """Changes since the previous update; None/empty fields mean 'unchanged'."""

    meshes: dict[int, MeshData] = dataclasses.field(default_factory=dict)  # re-send these submaps
    poses: dict[int, np.ndarray] = dataclasses.field(default_factory=dict)  # only move these (T_WM)
    removed_submaps: tuple[int, ...] = ()
    trajectory_chunks: dict[int, np.ndarray] = dataclasses.field(default_factory=dict)  # chunk -> (n,3) p_W
    trajectory_removed: tuple[int, ...] = ()
    keyframes_W: np.ndarray | None = None  # (K,3)
    T_WS: np.ndarray | None = None  # latest body pose
    frusta: tuple[Frustum, ...] = ()
    live_image: np.ndarray | None = None  # (H,W,3) uint8 for the frustum of live_camera
    live_camera: str = ""  # name of the camera of live_image (the frame's first camera)
    depth_rgb: np.ndarray | None = None
    sigma_rgb: np.ndarray | None = None
    depth_source: str = ""
    landmarks_W: np.ndarray | None = None  # (L,3)
    ground_truth_W: np.ndarray | None = None  # (N,3)
    stats_md: str | None = None
    status_md: str | None = None
    grid_cells_W: tuple[np.ndarray, np.ndarray, float] | None = None  # (free (F,3), occupied (O,3) cell centres, cell m)


def grid_cells(g: m.OccupancyGrid2D) -> tuple[np.ndarray, np.ndarray, float]:
    """Centres in W of a 2D grid's free and occupied cells, drawn at the bottom of its height band."""
    rows, cols = np.nonzero(g.cells != 255)
    xy = np.asarray(g.origin_xy_m) + (np.column_stack([cols, rows]) + 0.5) * g.resolution_m
    p = np.column_stack([xy, np.full(len(xy), float(g.z_band_m[0]))]).astype(np.float32)
    occupied = g.cells[rows, cols] >= 50
    return p[~occupied], p[occupied], float(g.resolution_m)


class ViewerModel:
    """Thread-safe store of the latest data to draw, with change tracking."""

    def __init__(self, cfg: ViewerConfig | None = None, cameras: list[CameraCalib] | None = None,
                 ground_truth: PoseSeries | None = None) -> None:
        self.cfg = cfg or ViewerConfig()
        self._lock = threading.Lock()
        self.submaps = SubmapStore(self.cfg.mesh_color, tuple(self.cfg.height_range_m))
        self.trajectory = ChunkedTrajectory(self.cfg.max_trajectory_points)
        self.keyframes = KeyframeTrack()
        self.landmarks = LandmarkBuffer(self.cfg.max_landmarks)
        self.ground_truth = (GroundTruthOverlay(ground_truth, self.cfg.align_ground_truth)
                             if ground_truth is not None and len(ground_truth) else None)
        self._cameras: dict[str, tuple[np.ndarray, float, float]] = {}  # name -> (T_SC, fov_y, aspect)
        self._camera_order: list[str] = []
        for c in cameras or []:
            self._set_camera(c.name, c.T_SC, c.camera.fy, c.camera.width, c.camera.height)
        self._rig_given = bool(cameras)
        self.T_WS: np.ndarray | None = None
        self.state_status = ""
        self._body_changed = False
        self._frame: m.MultiCameraFrame | None = None
        self._frame_new = False
        self._depth: dict[str, tuple[m.DepthFrame, float]] = {}
        self._depth_new = False
        self._stats: dict[str, tuple[m.ServiceStats, float]] = {}
        self._stream_ended: m.StreamEnd | None = None
        self._last_image_s = -math.inf
        self._last_depth_s = -math.inf
        self._last_stats_s = -math.inf
        self._last_gt_s = -math.inf
        self.counts = {"state": 0, "keyframes": 0, "submap": 0, "frame": 0, "depth": 0, "landmarks": 0, "stats": 0,
                       "grid": 0}
        self.grid: m.OccupancyGrid2D | None = None  # the newest 2D occupancy grid (map/grid)
        self._grid_new = False
        self._status_dirty = True

    # ------------------------------------------------------------------ receiving (any thread, cheap)

    def apply(self, msg: m.Message, now_s: float | None = None) -> None:
        handler = self._HANDLERS.get(type(msg))
        if handler is None:
            raise TypeError(f"the viewer does not show {type(msg).__name__} messages")
        with self._lock:
            handler(self, msg, time.monotonic() if now_s is None else now_s)
            self._status_dirty = True

    def _on_state(self, msg: m.EstimatorState, now_s: float) -> None:
        T = np.asarray(msg.T_WS, np.float64)
        if not np.isfinite(T).all():
            raise ValueError("EstimatorState with non-finite T_WS")
        self.counts["state"] += 1
        self.trajectory.append(msg.header.stamp_ns, T[:3, 3])
        self.T_WS = T.copy()
        self.state_status = msg.status
        self._body_changed = True

    def _on_keyframes(self, msg: m.Keyframes, now_s: float) -> None:
        self.counts["keyframes"] += 1
        self.keyframes.update(msg.ids, msg.stamps_ns, msg.T_WS)

    def _on_submap(self, msg: m.SubmapMesh, now_s: float) -> None:
        self.counts["submap"] += 1
        self.submaps.apply(msg)

    def _on_frame(self, msg: m.MultiCameraFrame, now_s: float) -> None:
        self.counts["frame"] += 1
        self._frame, self._frame_new = msg, True

    def _on_depth(self, msg: m.DepthFrame, now_s: float) -> None:
        self.counts["depth"] += 1
        self._depth[msg.source] = (msg, now_s)
        self._depth_new = True
        name = msg.header.frame_id or "depth"
        if not self._rig_given and name not in self._cameras:
            h, w = msg.depth.shape
            self._set_camera(name, msg.T_SC, float(msg.K[1, 1]), w, h)
            self._body_changed = True

    def _on_landmarks(self, msg: m.Landmarks, now_s: float) -> None:
        self.counts["landmarks"] += 1
        self.landmarks.add(msg.ids, msg.p_W)

    def _on_stats(self, msg: m.ServiceStats, now_s: float) -> None:
        self.counts["stats"] += 1
        self._stats[msg.service] = (msg, now_s)

    def _on_grid(self, msg: m.OccupancyGrid2D, now_s: float) -> None:
        if msg.resolution_m <= 0 or not np.isfinite(msg.origin_xy_m).all():
            raise ValueError("OccupancyGrid2D with a non-positive resolution or a non-finite origin")
        self.counts["grid"] += 1
        self.grid, self._grid_new = msg, True

    def _on_end(self, msg: m.StreamEnd, now_s: float) -> None:
        self._stream_ended = msg

    _HANDLERS = {m.EstimatorState: _on_state, m.Keyframes: _on_keyframes, m.SubmapMesh: _on_submap,
                 m.MultiCameraFrame: _on_frame, m.DepthFrame: _on_depth, m.Landmarks: _on_landmarks,
                 m.ServiceStats: _on_stats, m.StreamEnd: _on_end, m.OccupancyGrid2D: _on_grid}

    def _set_camera(self, name: str, T_SC: np.ndarray, fy: float, width: int, height: int) -> None:
        if name not in self._cameras:
            self._camera_order.append(name)
        self._cameras[name] = (np.asarray(T_SC, np.float64).copy(), 2.0 * math.atan2(height / 2.0, fy), width / height)

    # ------------------------------------------------------------------ controls

    def set_color_mode(self, mode: str) -> None:
        with self._lock:
            self.submaps.set_color_mode(mode)

    def world_mesh(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        with self._lock:
            return self.submaps.world_mesh()

    # ------------------------------------------------------------------ drawing thread

    def take_update(self, now_s: float | None = None, with_images: bool = True) -> SceneUpdate:
        """Everything that changed since the last call; images at most at cfg.image_rate_hz."""
        now = time.monotonic() if now_s is None else now_s
        with self._lock:
            up = SceneUpdate()
            self._take_submaps(up, self.submaps.take_changes())
            up.trajectory_chunks, up.trajectory_removed = self.trajectory.take_changes()
            up.keyframes_W = self.keyframes.take()
            up.landmarks_W = self.landmarks.take()
            if self._grid_new and self.grid is not None:
                self._grid_new = False
                up.grid_cells_W = grid_cells(self.grid)
            if self._body_changed and self.T_WS is not None:
                up.T_WS = self.T_WS.copy()
                up.frusta = tuple(self._frusta(self.T_WS))
                self._body_changed = False
            if self.ground_truth is not None:
                if now - self._last_gt_s >= 1.0 and len(self.trajectory) >= GroundTruthOverlay.MIN_MATCHES:
                    self._last_gt_s = now
                    self.ground_truth.realign(*self.trajectory.all_points())
                up.ground_truth_W = self.ground_truth.take()
            period = 1.0 / max(self.cfg.image_rate_hz, 1e-3)
            frame = self._frame if with_images and self._frame_new and now - self._last_image_s >= period else None
            if frame is not None:
                self._frame_new, self._last_image_s = False, now
            depth = None
            if with_images and self._depth_new and now - self._last_depth_s >= period:
                self._depth_new, self._last_depth_s = False, now
                depth = self._pick_depth(now)
            if now - self._last_stats_s >= 1.0 / max(self.cfg.stats_rate_hz, 1e-3):
                self._last_stats_s = now
                up.stats_md = stats_markdown(self._stats, now)
            if self._status_dirty:
                self._status_dirty = False
                up.status_md = self._status()
        # colour mapping outside the lock: receiving never waits for it
        if frame is not None and frame.images:
            up.live_image = _downscale(gray_to_rgb(frame.images[0]), LIVE_IMAGE_MAX_WIDTH)
            up.live_camera = frame.camera_names[0] if frame.camera_names else ""
        if depth is not None:
            up.depth_rgb = depth_image(depth.depth, tuple(self.cfg.depth_range_m))
            up.sigma_rgb = sigma_image(depth.sigma, tuple(self.cfg.sigma_range_m))
            up.depth_source = depth.source
        return up

    def _take_submaps(self, up: SceneUpdate, ch: SubmapChanges) -> None:
        for sid in ch.meshes:
            e = self.submaps.entries[sid]
            up.meshes[sid] = MeshData(e.T_WM.copy(), e.vertices_M, e.faces, self.submaps.colors(e))
        for sid in ch.poses:
            up.poses[sid] = self.submaps.entries[sid].T_WM.copy()
        up.removed_submaps = ch.removed

    def _frusta(self, T_WS: np.ndarray) -> list[Frustum]:
        names = self._camera_order or ["cam0"]
        out = []
        for name in names:
            T_SC, fov, aspect = self._cameras.get(name, (np.eye(4), math.radians(60.0), 4.0 / 3.0))
            out.append(Frustum(name, T_WS @ T_SC, fov, aspect))
        return out

    def _pick_depth(self, now: float) -> m.DepthFrame | None:
        fused = self._depth.get("fused")
        if fused is not None and now - fused[1] <= DEPTH_SOURCE_TIMEOUT_S:
            return fused[0]
        newest = max(self._depth.values(), key=lambda d: d[1], default=None)
        return None if newest is None else newest[0]

    def _status(self) -> str:
        c = self.counts
        n_v = sum(len(e.vertices_M) for e in self.submaps.entries.values())
        lines = [f"**states** {c['state']} ({self.state_status or '–'}) · **keyframes msgs** {c['keyframes']}",
                 f"**submaps** {len(self.submaps.entries)} ({n_v} vertices; {self.submaps.mesh_updates} mesh, "
                 f"{self.submaps.pose_updates} pose-only updates)",
                 f"**frames** {c['frame']} · **depth** {c['depth']} · **landmarks** {len(self.landmarks.positions())}"]
        if self._stream_ended is not None:
            lines.append(f"**stream ended**: {self._stream_ended.source} after {self._stream_ended.frames_sent} frames")
        return "  \n".join(lines)


def _downscale(image: np.ndarray, max_width: int) -> np.ndarray:
    h, w = image.shape[:2]
    if w <= max_width:
        return np.ascontiguousarray(image)
    return cv2.resize(image, (max_width, max(1, round(h * max_width / w))), interpolation=cv2.INTER_AREA)
