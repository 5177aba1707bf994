"""SceneDrawer against a real viser server (no browser): what is re-sent, moved, exported."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import viser

from helpers_zenoh import free_port
from services.viewer.config import ViewerConfig
from services.viewer.drawer import SceneDrawer
from services.viewer.scene_model import ViewerModel
from services.viewer.tracks import CHUNK
from tools.viewer_demo_publisher import demo_image, submap_messages
from test_viewer_model import pose, state
from shared import messages as m


@pytest.fixture
def drawer(tmp_path):
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    model = ViewerModel(ViewerConfig(image_rate_hz=1000.0))
    sent: list[str] = []
    d = SceneDrawer(server, model, publish_control=sent.append, export_dir=tmp_path)
    d.sent = sent
    try:
        yield d
    finally:
        server.stop()


def test_only_changed_submaps_are_sent_to_the_browser(drawer):
    model = drawer.model
    for msg in submap_messages(1):
        model.apply(msg)
    drawer.draw(model.take_update())
    assert drawer.drawn_meshes == 4 and drawer.moved_meshes == 0
    for msg in submap_messages(2):  # identical meshes and poses: nothing to send
        model.apply(msg)
    drawer.draw(model.take_update())
    assert drawer.drawn_meshes == 4
    for msg in submap_messages(3, shift_m=0.1):  # a loop closure moved every submap: move, don't re-send
        model.apply(msg)
    drawer.draw(model.take_update())
    assert drawer.drawn_meshes == 4 and drawer.moved_meshes == 4
    moved_T = submap_messages(0, 0.1)[0].T_WM
    np.testing.assert_allclose(drawer._meshes[0].position, moved_T[:3, 3], atol=1e-6)
    np.testing.assert_allclose(drawer._bbox[0].mean(0), moved_T[:3, 3], atol=1e-6)  # framing follows the move
    model.set_color_mode("uncertainty")  # vertex colours: the GLB path
    drawer.draw(model.take_update())
    assert drawer.drawn_meshes == 8
    emptied = submap_messages(4)[1]
    model.apply(m.SubmapMesh(header=emptied.header, submap_id=1, T_WM=emptied.T_WM, vertices_M=np.zeros((0, 3), np.float32),
                             faces=np.zeros((0, 3), np.int32), vertex_colors=np.zeros((0, 3), np.uint8)))
    drawer.draw(model.take_update())
    assert sorted(drawer._meshes) == [0, 2, 3] and 1 not in drawer._bbox


def test_export_trajectory_chunks_images_and_controls(drawer, tmp_path):
    model = drawer.model
    for msg in submap_messages(1):
        model.apply(msg)
    for i in range(2 * CHUNK + 5):
        model.apply(state(i + 1, pose(t=(0.01 * i, 0, 1))))
    img = demo_image(0)
    model.apply(m.MultiCameraFrame(header=m.Header(stamp_ns=1), images=(img,), camera_names=("cam0",),
                                   stamps_ns=np.array([1], np.int64)))
    drawer.draw(model.take_update())
    assert sorted(drawer._chunks) == [0, 1, 2]
    assert list(drawer._frusta) == ["cam0"] and drawer._frusta["cam0"].image is not None
    path = drawer.export_mesh()
    mesh = trimesh.load(path, process=False)
    assert len(mesh.vertices) == 2 * 642 + 2 * 8
    drawer._control("Pause")
    assert drawer.sent == ["pause"]


def test_the_occupancy_grid_is_drawn_once_per_new_grid(drawer):
    """map/grid: free and occupied cells as two square-point layers at the band's bottom; unknown ones not drawn."""
    from shared.codec import Header

    model = drawer.model
    cells = np.full((4, 5), 255, np.uint8)
    cells[0, :3], cells[2, 4] = 0, 100
    model.apply(m.OccupancyGrid2D(header=Header(stamp_ns=1, frame_id="W"), resolution_m=0.1,
                                  origin_xy_m=np.array([1.0, 2.0]), z_band_m=np.array([0.1, 1.5]), cells=cells))
    up = model.take_update()
    free, occupied, cell_m = up.grid_cells_W
    assert len(free) == 3 and len(occupied) == 1 and cell_m == 0.1
    np.testing.assert_allclose(occupied[0], [1.45, 2.25, 0.1], atol=1e-6)  # row 2, column 4: lowest y first
    drawer.draw(up)
    assert drawer.drawn_grids == 1
    drawer.draw(model.take_update())  # no new grid: nothing re-sent
    assert drawer.drawn_grids == 1
