"""ROS bag (ROS 2 MCAP/sqlite3, ROS 1) -> EuRoC ASL folder with the rig's calibration, without ROS installed.

    sigmaslam convert BAG DIR --calib camchain-imucam.yaml --imu-calib imu.yaml [--cam T --cam T] [--imu T]
    sigmaslam convert BAG DIR --calib EUROC_FOLDER

The calibration is a Kalibr ``camchain-imucam.yaml`` (services/app/datasets/kalibr.py: pinhole radtan/equidistant, T_cam_imu,
timeshift_cam_imu applied to the image stamps) with ``imu.yaml`` for the IMU noise, or an EuRoC folder whose
``mav0/cam*/sensor.yaml`` and ``imu0/sensor.yaml`` are copied. Camera topics: ``--cam`` in rig order, else the
Kalibr file's ``rostopic`` entries when the bag has them, else picked automatically (services/app/datasets/ros_bag.py). Stereo
frames are matched by header stamp within ``--sync-tolerance-ms``; unmatched images are counted and reported.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from shared.camera import CameraCalib, camera_to_sensor_yaml, load_rig, read_sensor_yaml_file
from services.app.datasets.euroc_writer import write_euroc
from services.app.datasets.ros_bag import BagError, bag_topics, choose_topics, iter_frames, scan_bag


def rig_calibration(calib: str | Path, imu_calib: str | Path | None) -> tuple[list[CameraCalib], dict,
                                                                            list[str | None], list[int], str | None]:
    """(cameras, IMU sensor.yaml fields, camera topics or None, time shifts [ns], IMU topic or None)."""
    c = Path(calib)
    if c.is_dir():
        cams = load_rig(c)
        root = c / "mav0" if (c / "mav0").is_dir() else c
        imu_file = Path(imu_calib) if imu_calib else root / "imu0" / "sensor.yaml"
        imu = read_sensor_yaml_file(imu_file) if imu_file.is_file() else {}
        return cams, imu, [None] * len(cams), [0] * len(cams), None
    from services.app.datasets.kalibr import read_kalibr

    rig = read_kalibr(c, imu_calib)
    return rig.cameras, rig.imu_yaml, rig.topics, rig.timeshift_ns, rig.imu_topic


def bag_to_euroc(bag: str | Path, dst: str | Path, calib: str | Path | None, imu_calib: str | Path | None = None,
                 cams: list[str] | None = None, imu: str | None = None, sync_tolerance_ms: float = 2.0,
                 progress: bool = True) -> dict:
    """Write DST/mav0 from the bag; returns the counts (frames, IMU samples, drops) and the topics used."""
    bag, dst = Path(bag), Path(dst)
    if calib is None:
        raise BagError(f"{bag}: a bag carries no calibration: pass --calib camchain-imucam.yaml (Kalibr, with "
                       f"--imu-calib imu.yaml) or --calib EUROC_FOLDER")
    if (dst / "mav0").exists():
        raise FileExistsError(f"{dst}: already holds a dataset (mav0/)")
    rig, imu_yaml, calib_topics, shifts, calib_imu = rig_calibration(calib, imu_calib)
    if not imu_yaml:
        raise BagError(f"{calib}: no IMU noise parameters: pass --imu-calib imu.yaml (Kalibr) or an EuRoC folder with "
                       f"imu0/sensor.yaml")
    topics = bag_topics(bag)
    if not cams and all(t in topics for t in calib_topics if t) and all(calib_topics):
        cams = list(calib_topics)
    if imu is None and calib_imu in topics:
        imu = calib_imu
    cams, imu = choose_topics(topics, cams, imu, str(bag))
    if len(cams) != len(rig):
        raise BagError(f"{bag}: {len(cams)} camera topics ({', '.join(cams)}) but the calibration has {len(rig)} "
                       f"cameras: name them with --cam, in the calibration's order")
    content, arrs, pairs = scan_bag(bag, cams, imu, shifts, int(sync_tolerance_ms * 1e6))
    if len(pairs) == 0:
        raise BagError(f"{bag}: no stereo frame matched within {sync_tolerance_ms} ms ({content.stats})")
    rate = 1e9 / float(np.median(np.diff(content.frame_stamps_ns))) if len(pairs) > 1 else 20.0
    cam_yaml = {}
    for c in rig:
        y = camera_to_sensor_yaml(c)
        y["rate_hz"] = round(rate, 3)
        cam_yaml[c.name] = y
    stats = dict(content.stats)
    written = [0]

    def frames():
        for stamp, imgs in iter_frames(bag, cams, arrs, pairs, shifts, progress, stats):
            for c, im in zip(rig, imgs):
                if im.shape != (c.camera.height, c.camera.width):
                    raise BagError(f"{bag}: {c.name} image {im.shape[1]}x{im.shape[0]}, calibration says "
                                   f"{c.camera.width}x{c.camera.height}")
            written[0] += 1
            yield stamp, imgs

    imu_rows = np.column_stack([content.imu_stamps_ns.astype(np.float64), content.imu])
    write_euroc(dst, cam_yaml, frames(), imu_rows, imu_yaml, imu_stamps_ns=content.imu_stamps_ns)
    return {"frames": written[0], "imu": len(content.imu_stamps_ns), **{k: v for k, v in stats.items() if v},
            "cameras": ",".join(cams), "imu_topic": imu}


def add_bag_arguments(p: argparse.ArgumentParser, calib: bool = True) -> None:
    """The options of a ROS bag input (``convert`` and ``run``)."""
    if calib:
        p.add_argument("--calib", help="ROS bag input: Kalibr camchain-imucam.yaml or an EuRoC folder")
    p.add_argument("--imu-calib", help="ROS bag input: Kalibr imu.yaml (IMU noise densities and random walks)")
    p.add_argument("--cam", action="append", default=None, metavar="TOPIC",
                   help="ROS bag input: camera topic, repeated in rig order (default: picked when unambiguous)")
    p.add_argument("--imu", default=None, metavar="TOPIC", help="ROS bag input: IMU topic (default: the only one)")
    p.add_argument("--sync-tolerance-ms", type=float, default=2.0,
                   help="ROS bag input: stereo images further apart than this are not a frame (counted)")
