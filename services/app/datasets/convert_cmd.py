"""``sigmaslam convert SRC DST``: EuRoC ASL folder <-> sigmaslam MCAP recording; ROS bag -> EuRoC folder.

ROS bags (ROS 2 MCAP or sqlite3, ROS 1) become EuRoC folders with services/app/datasets/bag_input.py (``--calib`` Kalibr
camchain-imucam.yaml + ``--imu-calib`` imu.yaml, or an EuRoC folder; ``--cam``/``--imu`` topics when ambiguous).

EuRoC -> MCAP: IMU samples and multi-camera frames become native ``sensors/imu`` / ``sensors/frame``
messages (log time = sensor stamp) under ``--namespace``; every other file of ``mav0`` (sensor.yaml
files, ground truth, GT depth, scene mesh) and ``replica.yaml`` is stored as an MCAP attachment under its
relative path, so the reverse conversion restores the folder exactly. MCAP -> EuRoC: messages are written
back with :func:`services.app.datasets.euroc_writer.write_euroc`, attachments to their paths. A plain recording without
attachments needs ``--calib`` (a folder with ``camN_sensor.yaml`` [+ ``imu0_sensor.yaml``]).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from shared import topics
from shared.euroc_reader import DatasetError, EurocDataset, read_sensor_yaml
from shared.messages import ImuSample, MultiCameraFrame

MESSAGE_FILES = ("cam*/data/*", "cam*/data.csv", "imu0/data.csv")


def _is_message_file(rel: Path) -> bool:
    return any(rel.match(p) for p in MESSAGE_FILES)


def euroc_to_mcap(src: str | Path, dst: str | Path, namespace: str = "sigmaslam/robot0", foxglove: bool = False) -> dict:
    from services.recorder.mcap_writer import RecordingWriter

    ds = EurocDataset(src)
    keys = {ImuSample: topics.IMU.key_expr(namespace), MultiCameraFrame: topics.FRAME.key_expr(namespace)}
    counts = {"imu": 0, "frames": 0, "attachments": 0}
    with RecordingWriter(dst, foxglove_mirror=foxglove) as w:
        for msg in ds.messages():
            w.write_message(keys[type(msg)], msg, log_time_ns=int(msg.header.stamp_ns))
            counts["imu" if isinstance(msg, ImuSample) else "frames"] += 1
        base = ds.root.parent
        files = [f for f in sorted(ds.root.rglob("*")) if f.is_file() and not _is_message_file(f.relative_to(ds.root))]
        files += [f for f in (base / "replica.yaml",) if f.is_file()]
        for f in files:
            w.add_attachment(str(f.relative_to(base)), "application/octet-stream", f.read_bytes())
            counts["attachments"] += 1
    counts.update({f"skipped_{k}": v for k, v in ds.stats.items() if v})
    return counts


def mcap_to_euroc(src: str | Path, dst: str | Path, calib: str | Path | None = None) -> dict:
    from mcap.reader import make_reader

    from services.player.source import McapSource
    from services.app.datasets.euroc_writer import write_euroc

    dst = Path(dst)
    if (dst / "mav0").exists():
        raise FileExistsError(f"{dst}: already holds a dataset (mav0/)")
    with open(src, "rb") as f:
        attachments = {a.name: a.data for a in make_reader(f).iter_attachments()}
    source = McapSource(src)
    imu_rows, frames = [], []
    for msg in source.messages():
        if isinstance(msg, ImuSample):
            imu_rows.append([msg.header.stamp_ns, *msg.omega_S, *msg.acc_S])
        else:
            frames.append(msg)
    if not frames:
        raise DatasetError(f"{src}: no sensors/frame messages")
    names = list(frames[0].camera_names)
    cam_yaml, imu_yaml = {}, None
    tmp = dst / ".calib"
    for name in names:
        rel = f"mav0/{name}/sensor.yaml"
        if rel in attachments:
            tmp.mkdir(parents=True, exist_ok=True)
            (tmp / f"{name}.yaml").write_bytes(attachments[rel])
            cam_yaml[name] = read_sensor_yaml(tmp / f"{name}.yaml")
        elif calib is not None:
            cam_yaml[name] = read_sensor_yaml(Path(calib) / f"{name}_sensor.yaml", ("T_BS", "intrinsics", "resolution"))
        else:
            raise DatasetError(f"{src}: no calibration for {name} in the recording; pass --calib FOLDER")
    if "mav0/imu0/sensor.yaml" in attachments:
        (tmp / "imu0.yaml").write_bytes(attachments["mav0/imu0/sensor.yaml"])
        imu_yaml = read_sensor_yaml(tmp / "imu0.yaml")
    elif calib is not None and (Path(calib) / "imu0_sensor.yaml").is_file():
        imu_yaml = read_sensor_yaml(Path(calib) / "imu0_sensor.yaml")
    else:
        imu_yaml = {"sensor_type": "imu", "rate_hz": 200}
    frames_iter = ((m.header.stamp_ns, [m.images[m.camera_names.index(n)] for n in names]) for m in frames)
    write_euroc(dst, cam_yaml, frames_iter, np.asarray(imu_rows, dtype=np.float64).reshape(-1, 7), imu_yaml,
                imu_stamps_ns=np.array([r[0] for r in imu_rows], dtype=np.int64))
    for name, data in attachments.items():
        out = dst / name
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(data)
    for f in tmp.glob("*"):
        f.unlink()
    if tmp.exists():
        tmp.rmdir()
    return {"imu": len(imu_rows), "frames": len(frames), "attachments": len(attachments), **source.stats}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("src", help="EuRoC folder (mav0 or its parent), sigmaslam .mcap recording, or ROS bag (ROS 2 "
                   "folder or .mcap/.db3, ROS 1 .bag)")
    p.add_argument("dst", help=".mcap file (from a folder) or folder (from a .mcap or a bag)")
    p.add_argument("--namespace", default="sigmaslam/robot0", help="key prefix of the topics written to MCAP")
    p.add_argument("--to", choices=["euroc", "ros2"], default="euroc", help="from a sigmaslam recording: an EuRoC "
                   "folder of its sensor data (euroc), or a ROS 2 bag of its results (ros2: odometry, tf, path, "
                   "submap clouds and meshes, depth; services/app/datasets/ros2_export.py)")
    p.add_argument("--foxglove", action="store_true", help="also write Foxglove image mirrors (doubles the size)")
    p.add_argument("--calib", help="MCAP -> EuRoC: calibration folder when the recording carries none; bag -> EuRoC: "
                   "Kalibr camchain-imucam.yaml or an EuRoC folder")
    from services.app.datasets.bag_input import add_bag_arguments

    add_bag_arguments(p, calib=False)


def main(args: argparse.Namespace) -> int:
    from services.app.datasets.ros_bag import is_ros_bag

    try:
        if is_ros_bag(args.src):
            from services.app.datasets.bag_input import bag_to_euroc

            counts = bag_to_euroc(args.src, args.dst, args.calib, args.imu_calib, args.cam, args.imu,
                                  args.sync_tolerance_ms)
        elif str(args.src).endswith(".mcap") and args.to == "ros2":
            from services.app.datasets.ros2_export import recording_to_ros2

            counts = recording_to_ros2(args.src, args.dst)
        elif str(args.src).endswith(".mcap"):
            counts = mcap_to_euroc(args.src, args.dst, args.calib)
        else:
            counts = euroc_to_mcap(args.src, args.dst, args.namespace, args.foxglove)
    except (DatasetError, FileNotFoundError, FileExistsError, OSError) as exc:
        print(f"sigmaslam convert: {exc}", file=sys.stderr)
        return 1
    print(f"converted {args.src} -> {args.dst}: " + ", ".join(f"{k} {v}" for k, v in counts.items()))
    return 0
