"""Turns :class:`~services.viewer.scene_model.SceneUpdate` into viser scene and GUI calls, and builds the
controls (layers, colouring, follow, pause/resume, mesh export, stats). Runs in the drawing thread only."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh
import viser

from services.viewer.scene_model import MeshData, SceneUpdate, ViewerModel
from services.viewer.submaps import COLOR_MODES, write_ply
from shared.geometry import R_to_quat_wxyz, transform_points

log = logging.getLogger("sigmaslam.viewer")

LAYERS = {"meshes": "/submaps", "causal trajectory": "/trajectory_causal", "keyframes": "/trajectory_keyframes",
          "body and cameras": "/body", "landmarks": "/landmarks", "ground truth": "/ground_truth"}
CAUSAL_RGB = (20, 20, 20)
KEYFRAME_RGB = (230, 60, 30)
GT_RGB = (40, 170, 60)
LANDMARK_RGB = (70, 110, 200)
GRID_FREE_RGB, GRID_OCCUPIED_RGB = (170, 220, 170), (150, 30, 30)  # the 2D occupancy grid's layer
PLACEHOLDER = np.zeros((48, 64, 3), np.uint8)
SRGB_TO_LINEAR = np.round(255.0 * (np.arange(256) / 255.0) ** 2.2).astype(np.uint8)  # approximate sRGB decoding
REFRAME_GROWTH = 1.3  # re-frame (untouched views) when the map diagonal grew by this factor


def _pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return R_to_quat_wxyz(T[:3, :3]), T[:3, 3].copy()


def _polyline(points: np.ndarray) -> np.ndarray:
    """(N,3) points -> (N-1,2,3) segments."""
    p = np.asarray(points, np.float32)
    return np.stack([p[:-1], p[1:]], axis=1)


def _world_bounds(T_WM: np.ndarray, bounds_M: np.ndarray) -> np.ndarray:
    """(2,3) axis-aligned min/max in W of the box ``bounds_M`` (min/max in M) posed at T_WM."""
    sel = np.array(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij")).reshape(3, -1).T
    corners_W = transform_points(T_WM, np.where(sel == 1, bounds_M[1], bounds_M[0]))
    return np.stack([corners_W.min(0), corners_W.max(0)])


class SceneDrawer:
    def __init__(self, server: viser.ViserServer, model: ViewerModel, *, publish_control: Callable[[str], None],
                 export_dir: str | Path, follow: bool = False, frustum_scale_m: float = 0.25) -> None:
        self.server = server
        self.model = model
        self.publish_control = publish_control
        self.export_dir = Path(export_dir)
        self.frustum_scale = frustum_scale_m
        self._meshes: dict[int, object] = {}
        self._chunks: dict[int, object] = {}
        self._frusta: dict[str, object] = {}
        self._bbox: dict[int, np.ndarray] = {}  # submap -> (2,3) world bbox, for framing the view
        self._bounds_M: dict[int, np.ndarray] = {}  # submap -> (2,3) robust min/max of its vertices in M
        self._framed = False
        self._framed_extent = 0.0  # map diagonal when the view was last framed [m]
        self._set_eye: dict[int, np.ndarray] = {}  # client -> camera position the viewer last set
        self._body_p: np.ndarray | None = None
        self.drawn_meshes = 0  # meshes sent to the browser (re-sends included)
        self.drawn_grids = 0  # 2D grids sent
        self.moved_meshes = 0
        server.scene.set_up_direction("+z")
        self._layers = {name: server.scene.add_frame(path, show_axes=False) for name, path in LAYERS.items()}
        self._body = server.scene.add_frame("/body/S", axes_length=0.3, axes_radius=0.015)
        self._build_gui(follow)
        self._to_frame: set[int] = set()  # clients to point at the scene once their camera has reported
        self._camera_known: set[int] = set()  # clients whose camera state has arrived (before: no camera access)
        server.on_client_connect(self._on_connect)

    def _on_connect(self, client) -> None:
        self._to_frame.add(client.client_id)
        client.camera.on_update(lambda _cam, cid=client.client_id: self._camera_known.add(cid))

    # ------------------------------------------------------------------ GUI

    def _build_gui(self, follow: bool) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="medium")
        with gui.add_folder("View"):
            self.status = gui.add_markdown("*waiting for data*")
            self.follow = gui.add_checkbox("Follow camera", initial_value=follow)
            color = gui.add_dropdown("Mesh colour", COLOR_MODES, initial_value=self.model.submaps.color_mode)
            color.on_update(lambda _: self.model.set_color_mode(color.value))
            frame = gui.add_button("Frame scene")  # done by the drawing thread at its next tick
            frame.on_click(lambda event: event.client is not None and self._to_frame.add(event.client.client_id))
        with gui.add_folder("Layers", expand_by_default=False):
            for name, handle in self._layers.items():
                box = gui.add_checkbox(name, initial_value=True)
                box.on_update(lambda _, h=handle, b=box: setattr(h, "visible", b.value))
        with gui.add_folder("Playback and export"):
            playback = gui.add_button_group("Player", ("Pause", "Resume"))
            playback.on_click(lambda event: self._control(event.target.value))
            gui.add_button("Export world mesh (PLY)").on_click(lambda _: self.export_mesh())
            self.export_note = gui.add_markdown("")
        with gui.add_folder("Images"):
            self.depth_label = gui.add_markdown("depth / sigma")
            self.depth_img = gui.add_image(PLACEHOLDER, label="depth", format="jpeg")
            self.sigma_img = gui.add_image(PLACEHOLDER, label="sigma", format="jpeg")
        with gui.add_folder("Stats", expand_by_default=False):
            self.stats = gui.add_markdown("*no stats received yet*")

    def _control(self, value: str) -> None:
        command = value.lower()
        self.publish_control(command)
        self.status.content = f"sent **{command}** to the player"

    def export_mesh(self) -> Path | None:
        vertices, faces, colors = self.model.world_mesh()
        if len(vertices) == 0:
            self.export_note.content = "no submap mesh to export yet"
            return None
        path = self.export_dir / f"world_mesh-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}.ply"
        try:
            write_ply(path, vertices, faces, colors)
        except OSError as exc:
            self.export_note.content = f"export failed: {exc}"
            log.warning("mesh export failed: %s", exc)
            return None
        self.export_note.content = f"wrote `{path}` ({len(vertices)} vertices, {len(faces)} faces)"
        log.info("exported the world mesh to %s", path)
        return path

    # ------------------------------------------------------------------ drawing

    def draw(self, up: SceneUpdate) -> None:
        for sid in up.removed_submaps:
            handle = self._meshes.pop(sid, None)
            self._bbox.pop(sid, None)
            if handle is not None:
                handle.remove()
        for sid, mesh in up.meshes.items():
            self._draw_mesh(sid, mesh)
        for sid, T_WM in up.poses.items():
            handle = self._meshes.get(sid)
            if handle is not None:
                handle.wxyz, handle.position = _pose(T_WM)
                self._bbox[sid] = _world_bounds(T_WM, self._bounds_M[sid])
                self.moved_meshes += 1
        self._draw_tracks(up)
        self._draw_grid(up)
        self._draw_body_and_images(up)
        if up.stats_md is not None:
            self.stats.content = up.stats_md
        if up.status_md is not None:
            self.status.content = up.status_md
        self._update_framing()

    def _draw_tracks(self, up: SceneUpdate) -> None:
        scene = self.server.scene
        for k in up.trajectory_removed:
            handle = self._chunks.pop(k, None)
            if handle is not None:
                handle.remove()
        for k, pts in up.trajectory_chunks.items():
            if len(pts) >= 2:
                self._chunks[k] = scene.add_line_segments(f"/trajectory_causal/c{k}", _polyline(pts), CAUSAL_RGB,
                                                          thickness=2.0, thickness_units="screen")
        if up.keyframes_W is not None and len(up.keyframes_W):
            kf = up.keyframes_W.astype(np.float32)
            if len(kf) >= 2:
                scene.add_line_segments("/trajectory_keyframes/line", _polyline(kf), KEYFRAME_RGB, thickness=2.0,
                                        thickness_units="screen")
            scene.add_point_cloud("/trajectory_keyframes/points", kf, KEYFRAME_RGB, point_size=0.02, point_shape="circle")
        if up.ground_truth_W is not None and len(up.ground_truth_W) >= 2:
            scene.add_line_segments("/ground_truth/line", _polyline(up.ground_truth_W), GT_RGB, thickness=2.0,
                                    thickness_units="screen")
        if up.landmarks_W is not None and len(up.landmarks_W):
            scene.add_point_cloud("/landmarks/points", up.landmarks_W.astype(np.float32), LANDMARK_RGB,
                                  point_size=0.02, point_shape="circle")

    def _draw_grid(self, up: SceneUpdate) -> None:
        """The newest 2D occupancy grid (map/grid) as square points at the bottom of its height band: free cells pale
        green, occupied ones dark red, unknown ones not drawn."""
        if up.grid_cells_W is None:
            return
        free, occupied, cell_m = up.grid_cells_W
        for name, pts, rgb in (("free", free, GRID_FREE_RGB), ("occupied", occupied, GRID_OCCUPIED_RGB)):
            self.server.scene.add_point_cloud(f"/grid/{name}", pts if len(pts) else np.zeros((1, 3), np.float32), rgb,
                                              point_size=cell_m, point_shape="square", visible=bool(len(pts)))
        self.drawn_grids += 1

    def _draw_body_and_images(self, up: SceneUpdate) -> None:
        if up.T_WS is not None:
            self._body.wxyz, self._body.position = _pose(up.T_WS)
            self._body_p = up.T_WS[:3, 3].copy()
            for fr in up.frusta:
                self._draw_frustum(fr)
            if self.follow.value:
                self._follow()
        if up.live_image is not None and self._frusta:
            frustum = self._frusta.get(up.live_camera) or next(iter(self._frusta.values()))
            frustum.image = up.live_image
        if up.depth_rgb is not None:
            self.depth_img.image = up.depth_rgb
            self.sigma_img.image = up.sigma_rgb
            self.depth_label.content = f"depth / sigma (**{up.depth_source}**)"

    def _update_framing(self) -> None:
        clients = self.server.get_clients()
        if self._bbox and not self.follow.value:
            lo, hi = self._map_bounds()
            if not self._framed:
                self._to_frame.update(clients)
            elif np.linalg.norm(hi - lo) > REFRAME_GROWTH * self._framed_extent:
                # the map outgrew the view: re-frame the clients whose camera the user has not moved since
                self._to_frame.update(cid for cid, c in clients.items() if cid in self._set_eye and cid in self._camera_known
                                      and np.allclose(c.camera.position, self._set_eye[cid], atol=0.05))
        ready = [c for cid, c in clients.items() if cid in self._to_frame and cid in self._camera_known]
        if ready and (self._bbox or self._body_p is not None):
            self._frame_view(ready)
            self._to_frame.difference_update(c.client_id for c in ready)
        self._to_frame.intersection_update(clients)  # forget disconnected clients
        self._camera_known.intersection_update(clients)
        for cid in set(self._set_eye) - set(clients):
            del self._set_eye[cid]

    def _draw_mesh(self, sid: int, mesh: MeshData) -> None:
        wxyz, pos = _pose(mesh.T_WM)
        name = f"/submaps/m{sid}"
        if len(mesh.faces) == 0:  # an emptied submap: nothing to draw
            old = self._meshes.pop(sid, None)
            self._bbox.pop(sid, None)
            if old is not None:
                old.remove()
            return
        if np.all(mesh.colors == mesh.colors[0]):  # one colour: the cheap path, no GLB encoding
            handle = self.server.scene.add_mesh_simple(name, mesh.vertices_M, mesh.faces, color=tuple(int(c) for c in mesh.colors[0]),
                                                       side="double", wxyz=wxyz, position=pos)
        else:
            # glTF vertex colours are linear; the browser shows them as sRGB: convert so they look as computed
            tm = trimesh.Trimesh(mesh.vertices_M, mesh.faces, vertex_colors=SRGB_TO_LINEAR[mesh.colors], process=False)
            handle = self.server.scene.add_mesh_trimesh(name, tm, wxyz=wxyz, position=pos)
        self._meshes[sid] = handle  # same name: viser replaced the previous node
        # robust extent (2nd-98th percentile): a few stray fragments must not shrink the framed view
        self._bounds_M[sid] = np.percentile(mesh.vertices_M, [2.0, 98.0], axis=0).astype(np.float64)
        self._bbox[sid] = _world_bounds(mesh.T_WM, self._bounds_M[sid])
        self.drawn_meshes += 1

    def _draw_frustum(self, fr) -> None:
        wxyz, pos = _pose(fr.T_WC)
        handle = self._frusta.get(fr.name)
        if handle is None:
            handle = self.server.scene.add_camera_frustum(f"/body/{fr.name}", fov=fr.fov_y_rad, aspect=fr.aspect,
                                                          scale=self.frustum_scale, color=(40, 40, 40),
                                                          wxyz=wxyz, position=pos)
            self._frusta[fr.name] = handle
        else:
            handle.wxyz, handle.position = wxyz, pos

    def _follow(self) -> None:
        if self._body_p is None:
            return
        for cid, client in self.server.get_clients().items():
            if cid not in self._camera_known:
                continue
            offset = np.asarray(client.camera.position) - np.asarray(client.camera.look_at)
            if np.linalg.norm(offset) < 1e-3 or np.linalg.norm(offset) > 20.0:
                offset = np.array([-3.0, -3.0, 2.5])
            with client.atomic():
                client.camera.position = self._body_p + offset
                client.camera.look_at = self._body_p

    def _map_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        boxes = np.stack(list(self._bbox.values()))
        return boxes[:, 0].min(0), boxes[:, 1].max(0)

    def _frame_view(self, clients: list) -> None:
        """Point the given clients' cameras at the map (or the body) from above and aside."""
        if self._bbox:
            lo, hi = self._map_bounds()
        elif self._body_p is not None:
            lo, hi = self._body_p - 1.0, self._body_p + 1.0
        else:
            return
        center = (lo + hi) / 2.0
        radius = max(float(np.linalg.norm(hi - lo)) / 2.0, 0.5)
        back = np.array([-0.9, -0.9, 0.8]) / np.linalg.norm([-0.9, -0.9, 0.8])  # from the map towards the eye
        right = np.cross(-back, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        # look a little right of the map so that it sits left of the control panel
        center = center + 0.3 * radius * right
        eye = center + 1.6 * radius * back
        for client in clients:
            with client.atomic():  # position first: setting it shifts look_at along
                client.camera.position = eye
                client.camera.look_at = center
            self._set_eye[client.client_id] = eye
        if self._bbox:
            self._framed = True
            self._framed_extent = float(np.linalg.norm(hi - lo))
