"""Test helpers: ROS bags and Kalibr files written from an EuRoC folder with ``rosbags`` (no ROS), as a robot's
``ros2 bag record`` and Kalibr would produce them."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml

from shared.camera import load_rig
from shared.euroc_reader import EurocDataset


def _stamp(ts, ns: int):
    return ts.types["builtin_interfaces/msg/Time"](sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def _header(ts, stamp_ns: int, frame: str):
    H = ts.types["std_msgs/msg/Header"]
    extra = {"seq": 0} if "seq" in H.__dataclass_fields__ else {}  # ROS 1 headers have a sequence number
    return H(stamp=_stamp(ts, stamp_ns), frame_id=frame, **extra)


def image_msg(ts, img: np.ndarray, stamp_ns: int, frame: str, encoding: str = "mono8"):
    """A sensor_msgs/Image (mono8, mono16, bgr8, rgb8, bayer_rggb8) or, with 'png'/'jpeg', a CompressedImage."""
    header = _header(ts, stamp_ns, frame)
    if encoding in ("png", "jpeg"):
        ok, buf = cv2.imencode(".png" if encoding == "png" else ".jpg", img)
        return ts.types["sensor_msgs/msg/CompressedImage"](header=header, format=encoding, data=buf.ravel())
    h, w = img.shape[:2]
    if encoding == "mono16":
        data = (img.astype(np.uint16) << 8).astype("<u2").view(np.uint8).ravel()
        step = 2 * w
    elif encoding in ("bgr8", "rgb8"):
        data = np.repeat(img[..., None], 3, axis=2).ravel()
        step = 3 * w
    elif encoding == "bayer_rggb8":  # a grey scene seen through an RGGB mosaic: every site has the grey value
        data, step = img.ravel(), w
    else:
        data, step = img.ravel(), w
    return ts.types["sensor_msgs/msg/Image"](header=header, height=h, width=w, encoding=encoding, is_bigendian=0,
                                               step=step, data=np.ascontiguousarray(data, np.uint8))


def imu_msg(ts, stamp_ns: int, w: np.ndarray, a: np.ndarray):
    T = ts.types
    v3 = lambda x: T["geometry_msgs/msg/Vector3"](x=float(x[0]), y=float(x[1]), z=float(x[2]))
    return T["sensor_msgs/msg/Imu"](
        header=_header(ts, stamp_ns, "imu0"),
        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=np.zeros(9),
        angular_velocity=v3(w), angular_velocity_covariance=np.zeros(9), linear_acceleration=v3(a),
        linear_acceleration_covariance=np.zeros(9))


def write_bag(euroc: Path, out: Path, kind: str = "mcap", encodings=("mono8", "png"), max_frames: int | None = None,
              topics=("/cam0/image_raw", "/cam1/image_raw"), imu_topic: str = "/imu0", cam_delay_ns=(0, 0)) -> Path:
    """A bag of the EuRoC folder's frames and IMU: kind 'mcap' or 'sqlite3' (ROS 2) or 'ros1'. Messages are
    written in receive-time order (images 3 ms after their stamp); ``cam_delay_ns`` adds to each camera's stamp."""
    from rosbags.typesys import Stores, get_typestore

    ds = EurocDataset(euroc)
    stamps = ds.frame_stamps_ns[:max_frames] if max_frames else ds.frame_stamps_ns
    lo, hi = stamps[0] - 1_000_000_000, stamps[-1] + 1_000_000_000  # the player's default IMU margin
    keep = (ds.imu_stamps_ns >= lo) & (ds.imu_stamps_ns <= hi)
    events = [(int(t), 0, i) for i, t in zip(np.flatnonzero(keep), ds.imu_stamps_ns[keep])]
    events += [(int(t) + 3_000_000, 1, int(t)) for t in stamps]
    events.sort()
    if kind == "ros1":
        from rosbags.rosbag1 import Writer

        ts = get_typestore(Stores.ROS1_NOETIC)
        writer = Writer(out)
        ser = ts.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        ts = get_typestore(Stores.ROS2_HUMBLE)
        writer = Writer(out, version=9, storage_plugin=StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3)
        ser = ts.serialize_cdr
    with writer as w:
        conns = []
        for topic, enc in zip(topics, encodings):
            mt = "sensor_msgs/msg/CompressedImage" if enc in ("png", "jpeg") else "sensor_msgs/msg/Image"
            conns.append(w.add_connection(topic, mt, typestore=ts))
        c_imu = w.add_connection(imu_topic, "sensor_msgs/msg/Imu", typestore=ts)
        for t_rx, kind_ev, ref in events:
            if kind_ev == 0:
                v = ds.imu_values[ref]
                w.write(c_imu, t_rx, ser(imu_msg(ts, int(ds.imu_stamps_ns[ref]), v[:3], v[3:]), "sensor_msgs/msg/Imu"))
                continue
            imgs = ds.load_frame(ref)
            for k, (conn, enc) in enumerate(zip(conns, encodings)):
                msg = image_msg(ts, imgs[k], ref + cam_delay_ns[k], f"cam{k}", enc)
                w.write(conn, t_rx, ser(msg, conn.msgtype))
    return out


def write_kalibr(euroc: Path, out_dir: Path, timeshift_s: float = 0.0, topics=("/cam0/image_raw", "/cam1/image_raw")
                 ) -> tuple[Path, Path]:
    """camchain-imucam.yaml and imu.yaml of the EuRoC folder's rig, in Kalibr's layout."""
    cams = load_rig(euroc)
    chain = {}
    for i, c in enumerate(cams):
        m = c.camera
        entry = {"camera_model": "pinhole", "intrinsics": [m.fx, m.fy, m.cx, m.cy],
                 "distortion_model": "radtan" if m.distortion in ("radtan", "radial-tangential") else m.distortion,
                 "distortion_coeffs": [float(x) for x in m.dist_coeffs], "resolution": [m.width, m.height],
                 "rostopic": topics[i], "T_cam_imu": np.linalg.inv(c.T_SC).tolist(), "timeshift_cam_imu": timeshift_s}
        if i:
            entry["T_cn_cnm1"] = (np.linalg.inv(c.T_SC) @ cams[i - 1].T_SC).tolist()
        chain[f"cam{i}"] = entry
    imu = yaml.safe_load((EurocDataset(euroc).root / "imu0" / "sensor.yaml").read_text().split("\n", 1)[1])
    imu_out = {"imu0": {k: imu[k] for k in ("gyroscope_noise_density", "gyroscope_random_walk",
                                             "accelerometer_noise_density", "accelerometer_random_walk")}
               | {"update_rate": imu.get("rate_hz", 200), "rostopic": "/imu0", "model": "calibrated"}}
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "camchain-imucam.yaml").write_text(yaml.safe_dump(chain))
    (out_dir / "imu.yaml").write_text(yaml.safe_dump(imu_out))
    return out_dir / "camchain-imucam.yaml", out_dir / "imu.yaml"
