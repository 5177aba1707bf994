"""Configuration of the web viewer (``sigmaslam viewer``)."""

from __future__ import annotations

import dataclasses
from typing import Literal

from shared.config import param


@dataclasses.dataclass(frozen=True)
class ViewerConfig:
    """Where the viser page is served, what it shows and how often it redraws."""

    host: str = param("127.0.0.1", "address the viser HTTP/websocket server binds to ('0.0.0.0' exposes it to the network)")
    port: int = param(8080, "TCP port of the viser page")
    draw_rate_hz: float = param(10.0, "how often the drawing thread pushes scene changes to the browser", "Hz")
    image_rate_hz: float = param(5.0, "at most this many live/depth/sigma image updates per second", "Hz")
    stats_rate_hz: float = param(1.0, "refresh rate of the stats panel", "Hz")
    mesh_color: Literal["submap", "height", "uncertainty"] = param("submap", "initial mesh colouring: 'submap' (one colour per submap), 'height' (z in W) or 'uncertainty' (the mesh's vertex colours)")
    height_range_m: tuple[float, float] = param((-1.0, 3.0), "z range in W mapped onto the height colour map", "m")
    max_trajectory_points: int = param(20000, "causal trajectory points kept (oldest dropped beyond)")
    max_landmarks: int = param(20000, "sparse landmark observations kept (oldest dropped beyond)")
    depth_range_m: tuple[float, float] = param((0.3, 8.0), "depth mapped onto the depth colour map", "m")
    sigma_range_m: tuple[float, float] = param((0.0, 0.5), "depth sigma mapped onto the sigma colour map", "m")
    frustum_scale_m: float = param(0.25, "drawn size of the camera frusta", "m")
    rig: str = param("", "rig calibration (EuRoC folder or rig YAML) for the camera frusta; '' = use T_SC and K of the depth frames")
    ground_truth: str = param("", "ground-truth trajectory (EuRoC CSV, .csv.xz or TUM) to overlay; '' = none")
    align_ground_truth: Literal["se3", "posyaw", "none"] = param("se3", "how the overlay is aligned to the causal trajectory")
    follow: bool = param(False, "initially move the browser camera with the body")
    export_dir: str = param("out/viewer", "folder the mesh-export button writes world_mesh-<UTC>.ply into")
    player_target: str = param("player", "service name the pause/resume buttons address (Control.target)")
