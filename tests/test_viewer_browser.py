"""The web viewer in a real browser: a `sigmaslam viewer` process, a separate publisher process sending
submap meshes, states, keyframes, images, depth and landmarks (estimator/landmarks) over real Zenoh (loopback router), and
headless Chromium (the system's /usr/bin/chromium, driven by Playwright) on the viser page.

Checks: the meshes are drawn (strongly coloured pixels in the 3D view that vanish when the 'meshes'
layer is switched off), the Pause button publishes Control('pause') on `control` (seen by this test
and by the publisher process), the export button writes the world mesh PLY with every submap, the
stats panel lists the publisher's and the viewer's stages, a malformed mesh is counted as a drop
(nothing else is dropped, the viewer keeps running), and the page logged no errors. The screenshot is
kept in out/viewer/browser_test.png.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from helpers_zenoh import REPO, child_env, free_port, router, wait_for
from services.app.system_config import SystemConfig
from services.viewer.config import ViewerConfig
from shared import messages as m, topics
from shared.config import to_yaml
from transport.pubsub import Publisher, Subscriber
from tools.viewer_screenshot import CHROMIUM, CHROMIUM_ARGS, VIEWPORT
from transport.session import open_session

PANEL_X = VIEWPORT["width"] - 420  # the control panel is right of this; the 3D view is checked left of it
FULL = os.environ.get("SIGMASLAM_E2E") == "full"
SHOT = REPO / "out" / "viewer" / "browser_test.png"
# the demo scene: 2 icospheres (642 vertices, 1280 faces) and 2 boxes (8 vertices, 12 faces)
DEMO_VERTICES, DEMO_FACES = 2 * 642 + 2 * 8, 2 * 1280 + 2 * 12

pytestmark = pytest.mark.e2e


class Proc:
    """A child process whose stdout lines are collected by a thread."""

    def __init__(self, argv: list[str]) -> None:
        self.p = subprocess.Popen([sys.executable, *argv], cwd=REPO, env=child_env(), stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.p.stdout:
            self.lines.append(line.rstrip())

    def has(self, text: str) -> bool:
        return any(text in line for line in self.lines)

    def stop(self) -> int:
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGTERM)
            try:
                self.p.wait(10)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait(5)
        return self.p.returncode


def coloured_pixels(png: bytes) -> int:
    """Saturated or dark pixels in the 3D view: meshes in any colouring, not the white background or the
    light grid (thin lines and dots add a little)."""
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[:, :PANEL_X]
    img[:160, :330] = 255  # the top-left corner holds viser's 'software WebGL' notice
    img[-80:, :80] = 255  # ... and the bottom-left the orientation axes
    hi = img.max(axis=2).astype(int)
    return int(((hi - img.min(axis=2) > 80) | (hi < 120)).sum())


@pytest.fixture
def stack(tmp_path):
    pytest.importorskip("playwright.sync_api")
    if not Path(CHROMIUM).exists():
        pytest.skip(f"{CHROMIUM} not installed (make system-deps)")
    with router() as tcfg:
        port = free_port()
        cfg = SystemConfig(transport=tcfg, viewer=ViewerConfig(port=port, export_dir=str(tmp_path / "export")))
        path = tmp_path / "config.yaml"
        path.write_text(to_yaml(cfg))
        with open_session(tcfg) as session:
            ns = tcfg.namespace
            control = Subscriber(session, f"{ns}/{topics.CONTROL.key}", m.Control, "all", 64)
            stats = Subscriber(session, f"{ns}/stats/viewer", m.ServiceStats, "latest", 1)
            bad_pub = Publisher(session, f"{ns}/{topics.SUBMAP.key}", m.SubmapMesh, tcfg, prepare_shm=False)
            viewer = Proc(["-m", "services.app.cli", "viewer", str(path)])
            procs = [viewer]
            try:
                assert wait_for(lambda: viewer.has("viewer: http"), 30), "\n".join(viewer.lines)
                duration = 90 if FULL else 45
                pub = Proc(["-m", "tools.viewer_demo_publisher", str(path), "--duration", str(duration)])
                procs.append(pub)
                assert wait_for(lambda: pub.has("demo: publishing"), 30), "\n".join(pub.lines)
                yield dict(url=f"http://127.0.0.1:{port}/", viewer=viewer, pub=pub, control=control, stats=stats,
                           bad_pub=bad_pub, export=tmp_path / "export")
            finally:
                codes = [p.stop() for p in reversed(procs)]
                control.close()
                stats.close()
                bad_pub.close()
        assert codes[-1] == 0, "viewer did not exit cleanly on SIGTERM:\n" + "\n".join(viewer.lines[-30:])


def test_viewer_page_draws_meshes_and_controls_work(stack):
    from playwright.sync_api import sync_playwright

    errors: list[str] = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport=VIEWPORT)
            page.on("console", lambda msg: msg.type == "error" and errors.append(msg.text))
            page.on("pageerror", lambda exc: errors.append(f"pageerror: {exc}"))
            page.goto(stack["url"])
            page.get_by_text("Connected").or_(page.get_by_text("sigmaslam")).first.wait_for(timeout=30_000)

            shots: list[bytes] = []

            def mesh_visible() -> bool:
                shots.append(page.screenshot())
                return coloured_pixels(shots[-1]) > 0.02 * PANEL_X * VIEWPORT["height"]

            assert wait_for(mesh_visible, 60, 1.0), f"no mesh in view: {coloured_pixels(shots[-1])} coloured pixels"
            page.wait_for_timeout(1500)  # one more image/stats round before the kept screenshot
            SHOT.parent.mkdir(parents=True, exist_ok=True)
            png = page.screenshot(path=str(SHOT))
            with_meshes = coloured_pixels(png)

            # layer toggle: without the meshes layer the coloured area (almost) disappears
            page.get_by_text("Layers", exact=True).click()
            page.get_by_label("meshes", exact=True).click()
            assert wait_for(lambda: coloured_pixels(page.screenshot()) < 0.2 * with_meshes, 15, 0.5)
            page.get_by_label("meshes", exact=True).click()
            assert wait_for(lambda: coloured_pixels(page.screenshot()) > 0.8 * with_meshes, 15, 0.5)

            if FULL:  # the other colourings (vertex colours: the GLB path) also draw
                for mode in ("height", "uncertainty", "submap"):
                    page.get_by_role("textbox", name="Mesh colour").or_(page.get_by_label("Mesh colour")).first.click()
                    page.get_by_role("option", name=mode, exact=True).click()
                    assert wait_for(lambda: coloured_pixels(page.screenshot()) > 0.5 * with_meshes, 20, 0.5), mode

            # pause button -> Control on `control` for the player
            page.get_by_role("button", name="Pause").click()
            assert wait_for(lambda: len(stack["control"].queue) > 0, 10)
            ctrl = stack["control"].get_nowait()
            assert (ctrl.command, ctrl.target) == ("pause", "player")
            assert wait_for(lambda: stack["pub"].has("control: pause -> player"), 10)

            # mesh export -> world PLY with every submap
            page.get_by_role("button", name="Export world mesh (PLY)").click()
            assert wait_for(lambda: any(stack["export"].glob("world_mesh-*.ply")), 15)
            ply = next(stack["export"].glob("world_mesh-*.ply"))
            mesh = trimesh.load(ply, process=False)
            assert (len(mesh.vertices), len(mesh.faces)) == (DEMO_VERTICES, DEMO_FACES)
            page.get_by_text("world_mesh-").wait_for(timeout=10_000)  # the page reports the written file

            # stats panel: rows of the publisher process (stage 'publish') and of the viewer itself ('draw')
            page.get_by_text("Stats", exact=True).click()
            page.get_by_role("cell", name="publish", exact=True).wait_for(timeout=10_000)
            page.get_by_role("cell", name="draw", exact=True).wait_for(timeout=10_000)
        finally:
            browser.close()

    # a mesh with a face index past its vertices: counted as a drop of map/submap, the viewer carries on
    bad = m.SubmapMesh(header=m.Header(stamp_ns=1), submap_id=99, T_WM=np.eye(4),
                       vertices_M=np.zeros((3, 3), np.float32), faces=np.array([[0, 1, 7]], np.int32),
                       vertex_colors=np.zeros((0, 3), np.uint8))
    stack["bad_pub"].publish(bad)

    def viewer_queues() -> dict:
        st = stack["stats"].get(timeout=5)
        assert "draw" in st.stage_names
        return dict(zip(st.queue_names, zip(st.queue_received.tolist(), st.queue_dropped.tolist())))

    assert wait_for(lambda: viewer_queues()[topics.SUBMAP.key][1] == 1, 10, 0.2), viewer_queues()
    q = viewer_queues()
    assert q[topics.SUBMAP.key][0] >= 5 and q[topics.STATE.key][0] > 20 and q[topics.LANDMARKS.key][0] >= 2, q
    # images come through keep-latest queues (the page shows the newest one): on a loaded machine older ones are
    # skipped and counted, by design; every other input must arrive whole
    images = {topics.SUBMAP.key, topics.FRAME.key, topics.DEPTH_STEREO.key, topics.DEPTH_FUSED.key}
    assert all(dropped == 0 for key, (_, dropped) in q.items() if key not in images), q
    assert stack["viewer"].p.poll() is None
    assert not errors, errors
