"""Which camera rig the pipeline services use: a config section and its loader.

``rig.calibration`` names an EuRoC dataset folder (``mav0/cam*/sensor.yaml``) or a rig YAML file
(see :func:`shared.camera.load_rig`); empty means the real EuRoC rig: ``cam0_sensor.yaml``, ``cam1_sensor.yaml``
in ``calib/`` of :func:`shared.paths.euroc_dir` (``../shared/data/euroc``, else the copy bundled in ``data/euroc``). ``sigmaslam run DATASET`` sets it to DATASET.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from shared.camera import CalibrationError, CameraCalib, camera_from_sensor_yaml, load_rig, read_sensor_yaml_file
from shared.config import param


@dataclasses.dataclass(frozen=True)
class RigConfig:
    """Camera rig of the pipeline."""

    calibration: str = param("", "EuRoC dataset folder or rig YAML with the cameras; '' = the real EuRoC rig "
                             "(data/euroc/calib, or ../shared/data/euroc/calib when present)")
    cameras: tuple[str, ...] = param((), "names of the cameras to use, in this order (empty: all of the rig)")


def load_rig_config(cfg: RigConfig) -> list[CameraCalib]:
    """The cameras named by the config, in its order; CalibrationError names what is missing."""
    if cfg.calibration:
        rig = load_rig(cfg.calibration)
    else:
        from shared.paths import euroc_dir

        d = Path(euroc_dir()) / "calib"
        files = sorted(d.glob("cam*_sensor.yaml"))
        if not files:
            raise CalibrationError(f"{d}: no cam*_sensor.yaml")
        rig = [camera_from_sensor_yaml(read_sensor_yaml_file(f), f.name.split("_")[0], str(f)) for f in files]
    if not cfg.cameras:
        return rig
    by_name = {c.name: c for c in rig}
    missing = [n for n in cfg.cameras if n not in by_name]
    if missing:
        raise CalibrationError(f"rig.cameras: {missing} not in the rig ({sorted(by_name)})")
    return [by_name[n] for n in cfg.cameras]
