"""A robot's sensor messages in ROS 2 (sensor_msgs Image, CompressedImage, Imu, CameraInfo), both ways.

In: images of the encodings robots send turned into the 8-bit grey images the pipeline tracks, header stamps into
int64 ns (ROS bags read by ``sigmaslam convert``/``run``, live topics read by ``sigmaslam ros2_input``). Out: what a
camera and IMU driver publish, built from a dataset's frames and samples (the player as a stand-in robot,
``sigmaslam player DATASET --as-ros2``). ``store`` is a rosbags type store (shared/ros2_wire.py: Jazzy).
"""

from __future__ import annotations

import cv2
import numpy as np

from shared.euroc_reader import DatasetError

IMAGE_TYPE, COMPRESSED_TYPE = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"
IMU_TYPE, CAMERA_INFO_TYPE = "sensor_msgs/msg/Imu", "sensor_msgs/msg/CameraInfo"
# ROS Bayer names -> OpenCV codes (OpenCV names the pattern by the second row's first two pixels)
BAYER = {"bayer_rggb8": cv2.COLOR_BayerBG2GRAY, "bayer_bggr8": cv2.COLOR_BayerRG2GRAY,
         "bayer_gbrg8": cv2.COLOR_BayerGR2GRAY, "bayer_grbg8": cv2.COLOR_BayerGB2GRAY}
COLOUR = {"bgr8": (3, cv2.COLOR_BGR2GRAY), "rgb8": (3, cv2.COLOR_RGB2GRAY), "bgra8": (4, cv2.COLOR_BGRA2GRAY),
          "rgba8": (4, cv2.COLOR_RGBA2GRAY)}


def image_type_of(topic: str) -> str:
    """The ROS 2 type of a camera topic: CompressedImage when its name ends in 'compressed' (image_transport's
    naming), else Image."""
    return COMPRESSED_TYPE if topic.rstrip("/").endswith("compressed") else IMAGE_TYPE


class UnreadableImage(DatasetError):
    """An image message whose encoding is not read or whose bytes do not hold the image it announces."""


def stamp_ns(msg) -> int:
    """The header stamp of a ROS message [ns]."""
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def image_to_grey(msg, msgtype: str) -> np.ndarray:
    """8-bit grey image of an Image or CompressedImage message; :class:`UnreadableImage` for an encoding it does not
    know or bytes that do not decode."""
    if msgtype.endswith("CompressedImage"):
        img = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise UnreadableImage(f"CompressedImage ({msg.format!r}) could not be decoded")
        if img.dtype == np.uint16:
            img = (img >> 8).astype(np.uint8)
        return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    enc, h, w, step = msg.encoding.lower(), int(msg.height), int(msg.width), int(msg.step)
    data = np.frombuffer(bytes(msg.data), np.uint8)
    if data.size < h * step:
        raise UnreadableImage(f"Image {w}x{h} ({enc}): {data.size} bytes, step {step} needs {h * step}")
    rows = data[: h * step].reshape(h, step)
    if enc in ("mono8", "8uc1"):
        return rows[:, :w].copy()
    if enc in ("mono16", "16uc1"):
        px = rows[:, : 2 * w].copy().view(">u2" if msg.is_bigendian else "<u2")
        return (px >> 8).astype(np.uint8)  # the top byte, as cv_bridge's mono16 -> mono8
    if enc in BAYER:
        return cv2.cvtColor(rows[:, :w].copy(), BAYER[enc])
    if enc in COLOUR:
        ch, code = COLOUR[enc]
        return cv2.cvtColor(rows[:, : ch * w].reshape(h, w, ch).copy(), code)
    raise UnreadableImage(f"image encoding {msg.encoding!r} not supported (mono8, mono16, bgr8, rgb8, bgra8, rgba8, "
                          f"bayer_rggb8/bggr8/gbrg8/grbg8, or CompressedImage)")


def _header(store, ns: int, frame: str):
    T = store.types
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=int(ns // 1_000_000_000),
                                                                            nanosec=int(ns % 1_000_000_000)),
                                    frame_id=frame)


def image_msg(store, ns: int, frame: str, grey: np.ndarray, encoding: str = "mono8"):
    """sensor_msgs/Image of a grey image as a driver sends it: ``mono8``, or colour (``bgr8``/``rgb8``)."""
    grey = np.ascontiguousarray(grey, np.uint8)
    h, w = grey.shape
    if encoding == "mono8":
        px = grey
    elif encoding in ("bgr8", "rgb8"):
        px = np.repeat(grey[:, :, None], 3, axis=2)
    else:
        raise ValueError(f"encoding {encoding!r}: mono8, bgr8 or rgb8")
    ch = 1 if px.ndim == 2 else px.shape[2]
    return store.types[IMAGE_TYPE](header=_header(store, ns, frame), height=h, width=w, encoding=encoding,
                                   is_bigendian=0, step=ch * w, data=px.reshape(-1))


def compressed_msg(store, ns: int, frame: str, grey: np.ndarray, fmt: str = "png"):
    """sensor_msgs/CompressedImage (PNG or JPEG) of a grey image."""
    ok, buf = cv2.imencode("." + fmt, np.asarray(grey, np.uint8))
    if not ok:
        raise ValueError(f"cannot encode a {fmt} image")
    return store.types[COMPRESSED_TYPE](header=_header(store, ns, frame), format=f"mono8; {fmt} compressed mono8",
                                        data=np.asarray(buf, np.uint8).reshape(-1))


def imu_msg(store, sample, frame: str):
    """sensor_msgs/Imu of an ImuSample (rates and specific force in the IMU frame; no orientation: its covariance's
    first element -1, as REP-145 asks)."""
    T = store.types
    v3 = T["geometry_msgs/msg/Vector3"]
    w, a = np.asarray(sample.omega_S, float), np.asarray(sample.acc_S, float)
    cov = np.zeros(9)
    return T[IMU_TYPE](header=_header(store, int(sample.header.stamp_ns), frame),
                       orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                       orientation_covariance=np.array([-1.0, 0, 0, 0, 0, 0, 0, 0, 0]),
                       angular_velocity=v3(x=w[0], y=w[1], z=w[2]), angular_velocity_covariance=cov,
                       linear_acceleration=v3(x=a[0], y=a[1], z=a[2]), linear_acceleration_covariance=cov)


def imu_values(msg) -> tuple[np.ndarray, np.ndarray]:
    """(omega_S [rad/s], acc_S [m/s^2]) of a sensor_msgs/Imu."""
    w, a = msg.angular_velocity, msg.linear_acceleration
    return np.array([w.x, w.y, w.z], float), np.array([a.x, a.y, a.z], float)


def camera_info_msg(store, ns: int, calib):
    """sensor_msgs/CameraInfo of a rig camera (shared.camera.CameraCalib): K, and D in ROS's model names."""
    cm = calib.camera
    K = np.array([[cm.fx, 0, cm.cx], [0, cm.fy, cm.cy], [0, 0, 1.0]])
    model = {"radtan": "plumb_bob", "equidistant": "equidistant", "none": "plumb_bob"}[cm.distortion]
    d = np.asarray(cm.dist_coeffs, float) if cm.dist_coeffs else np.zeros(5 if model == "plumb_bob" else 4)
    T = store.types
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return T[CAMERA_INFO_TYPE](header=_header(store, ns, calib.name), height=cm.height, width=cm.width,
                               distortion_model=model, d=d, k=K.ravel(), r=np.eye(3).ravel(),
                               p=np.hstack([K, np.zeros((3, 1))]).ravel(), binning_x=0, binning_y=0, roi=roi)
