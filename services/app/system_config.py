"""The whole-system config: one section per component, loaded from one YAML file.

Components add their section here as they land. ``sigmaslam config --defaults`` prints every field
with its default, unit and docstring.

It belongs to the application: the ``sigmaslam`` commands load it and hand each process its system config (a process
package reads its own section and those it shares, never this module: tests/test_layers.py).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from shared.config import from_dict, load_yaml, merge, param, parse_override
from services.app.config import SupervisorConfig
from services.backend.config import BackendConfig
from services.backend.o2p.config import O2PConfig
from services.depth.config import DepthConfig
from services.frontend.config import FrontendConfig
from services.backend.loop.config import LoopConfig
from services.mapping.config import MappingConfig
from services.player.config import PlayerConfig
from services.recorder.config import RecorderConfig
from services.ros2.config import Ros2Config
from services.viewer.config import ViewerConfig
from shared.rig import RigConfig
from transport.config import TransportConfig


@dataclasses.dataclass(frozen=True)
class SystemConfig:
    """Resolved configuration of a sigmaslam deployment."""

    transport: TransportConfig = param(TransportConfig(), "Zenoh session, namespace and queueing")
    recorder: RecorderConfig = param(RecorderConfig(), "MCAP recorder (sigmaslam record)")
    supervisor: SupervisorConfig = param(SupervisorConfig(), "processes started by sigmaslam up")
    viewer: ViewerConfig = param(ViewerConfig(), "viser web viewer (sigmaslam viewer)")
    rig: RigConfig = param(RigConfig(), "camera rig calibration used by the pipeline services")
    frontend: FrontendConfig = param(FrontendConfig(), "multi-camera feature tracker (sigmaslam frontend)")
    backend: BackendConfig = param(BackendConfig(), "visual-inertial estimator (sigmaslam backend)")
    loop: LoopConfig = param(LoopConfig(), "loop closure, pose graph, relocalisation, final BA (in sigmaslam backend)")
    o2p: O2PConfig = param(O2PConfig(), "occupancy-to-point factors, frame-to-map and map-to-map (in sigmaslam backend; off by default)")
    depth: DepthConfig = param(DepthConfig(), "stereo/MVS depth with learned uncertainty (sigmaslam depth)")
    mapping: MappingConfig = param(MappingConfig(), "occupancy submapping (sigmaslam mapping)")
    player: PlayerConfig = param(PlayerConfig(), "dataset player: pacing of sensors/imu and sensors/frame (sigmaslam player)")
    ros2: Ros2Config = param(Ros2Config(), "ROS 2 on Zenoh (rmw_zenoh wire format): the outputs as ROS 2 topics "
                             "(sigmaslam ros2), a robot's sensors as input (sigmaslam ros2_input); off by default")


def load_system_config(path: str | Path | None = None, overrides: list[str] | None = None) -> SystemConfig:
    """Load the system config from YAML (defaults if ``path`` is None), then apply ``key.path=value`` overrides."""
    extra: dict = {}
    for text in overrides or []:
        extra = merge(extra, parse_override(text))
    if path is None:
        return from_dict(SystemConfig, extra)
    return load_yaml(SystemConfig, path, extra)
