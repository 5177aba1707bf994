"""EuRoC ASL dataset folder reader (``mav0`` or its parent; cam0..camN, imu0, optional ground truth).

Frames are synchronised across cameras by exact timestamp; a stamp missing in some camera is counted
(``stats['frames_missing_camera']``) and skipped. Backward/duplicate timestamps are counted and skipped
with a warning. Missing or unreadable images skip their frame (all cameras) and count in
``stats['unreadable_images']``: image files that a ``data.csv`` row names but that do not exist (real
downloads have such rows) are found when the folder is opened, so ``frame_stamps_ns`` holds only frames
whose files all exist, with one warning per camera; a file that does not decode is found when loaded.
Missing sensor files/keys -> DatasetError.
"""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import yaml

from shared.codec import Header
from shared.messages import ImuSample, MultiCameraFrame

log = logging.getLogger(__name__)


class DatasetError(RuntimeError):
    """Missing/malformed dataset file or key; the message names the path."""


def _read_text(path: Path) -> str:
    try:
        return path.read_text()
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{path}: not a text file ({exc})") from None


def read_sensor_yaml(path: Path, keys: tuple[str, ...] = ()) -> dict:
    if not path.is_file():
        raise DatasetError(f"{path}: sensor.yaml not found")
    text = _read_text(path)
    if text.startswith("%YAML"):  # OpenCV's YAML 1.0 directive line, which PyYAML does not take
        text = text.partition("\n")[2]
    try:
        d = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise DatasetError(f"{path}: not valid YAML ({exc})") from None
    if not isinstance(d, dict):
        raise DatasetError(f"{path}: expected a mapping of keys, got {type(d).__name__}")
    for k in keys:
        if k not in d:
            raise DatasetError(f"{path}: missing key {k!r}")
    return d


class EurocDataset:
    def __init__(self, path: str | Path):
        p = Path(path)
        root = p / "mav0" if (p / "mav0").is_dir() else p
        if not root.is_dir():
            raise DatasetError(f"{p}: dataset folder not found")
        self.root = root
        self.stats = {"frames_missing_camera": 0, "backwards_stamps": 0, "unreadable_images": 0, "nonfinite_imu": 0,
                      "imu_outside_frames": 0}
        self.camera_names = sorted((d.name for d in root.glob("cam*") if d.is_dir()), key=lambda n: int(n[3:]))
        if not self.camera_names:
            raise DatasetError(f"{root}: no cam* folder")
        self.camera_yaml = {c: read_sensor_yaml(root / c / "sensor.yaml", ("T_BS", "intrinsics", "resolution"))
                            for c in self.camera_names}
        self._cams = {c: self._read_cam(c) for c in self.camera_names}
        self.imu_yaml = read_sensor_yaml(root / "imu0" / "sensor.yaml", ("rate_hz",))
        self.imu_stamps_ns, self.imu_values = self._read_imu()
        common = set.intersection(*(set(self._cams[c]) for c in self.camera_names))
        union = set.union(*(set(self._cams[c]) for c in self.camera_names))
        self.stats["frames_missing_camera"] = len(union - common)
        no_file = set().union(*(self._missing_files(c, common) for c in self.camera_names))
        self.stats["unreadable_images"] = len(no_file)
        self.frame_stamps_ns = np.array(sorted(common - no_file), dtype=np.int64)
        gt = root / "state_groundtruth_estimate0" / "data.csv"
        self.groundtruth_path = gt if gt.is_file() else None

    def _csv(self, path: Path) -> list[list[str]]:
        if not path.is_file():
            raise DatasetError(f"{path}: data.csv not found")
        return [[x.strip() for x in ln.split(",")] for ln in _read_text(path).splitlines()
                if ln.strip() and not ln.startswith("#")]

    def _monotonic(self, path: Path, stamps: list[int]) -> np.ndarray:
        bad = next((t for t in stamps if not 0 <= t < 2**63), None)
        if bad is not None:
            raise DatasetError(f"{path}: timestamp {bad} is not a non-negative int64 [ns]")
        keep, last = [], None
        for i, t in enumerate(stamps):
            if last is not None and t <= last:
                self.stats["backwards_stamps"] += 1
                log.warning("%s: data row %d timestamp %d not after %d; skipped", path, i, t, last)
                continue
            keep.append(i)
            last = t
        return np.asarray(keep, dtype=np.int64)

    def _read_cam(self, cam: str) -> dict[int, Path]:
        path = self.root / cam / "data.csv"
        rows = self._csv(path)
        try:
            stamps = [int(r[0]) for r in rows]
        except (ValueError, IndexError) as e:
            raise DatasetError(f"{path}: bad row ({e})") from None
        short = next((i for i, r in enumerate(rows) if len(r) < 2 or not r[1]), None)
        if short is not None:
            raise DatasetError(f"{path}: data row {short} has no file name")
        return {stamps[i]: self.root / cam / "data" / rows[i][1] for i in self._monotonic(path, stamps)}

    def _missing_files(self, cam: str, stamps: set[int]) -> set[int]:
        """Stamps (of ``stamps``) whose image file of ``cam`` does not exist; one warning for all of them."""
        missing = {t for t in stamps if not self._cams[cam][t].is_file()}
        if missing:
            log.warning("%s: %d data.csv rows name image files that do not exist (first at %d); those frames are "
                        "skipped", self.root / cam / "data.csv", len(missing), min(missing))
        return missing

    def frame_span_ns(self) -> tuple[int, int] | None:
        """First and last frame stamp [ns], or None without frames."""
        f = self.frame_stamps_ns
        return (int(f[0]), int(f[-1])) if len(f) else None

    def _read_imu(self):
        path = self.root / "imu0" / "data.csv"
        rows = self._csv(path)
        if any(len(r) != 7 for r in rows):
            raise DatasetError(f"{path}: expected 7 columns")
        try:
            stamps = [int(r[0]) for r in rows]
            vals = np.array([[float(x) for x in r[1:]] for r in rows]).reshape(-1, 6)
        except ValueError as e:
            raise DatasetError(f"{path}: bad row ({e})") from None
        finite = np.isfinite(vals).all(axis=1)
        if not finite.all():  # NaN/inf samples are skipped (an IMU gap the estimator bridges or reports)
            self.stats["nonfinite_imu"] = int((~finite).sum())
            log.warning("%s: %d rows with NaN/inf values skipped", path, self.stats["nonfinite_imu"])
        keep = self._monotonic(path, [t for t, ok in zip(stamps, finite) if ok])
        return np.asarray(stamps, dtype=np.int64)[finite][keep], vals[finite][keep]

    def load_frame(self, stamp_ns: int) -> list[np.ndarray] | None:
        imgs = []
        for c in self.camera_names:
            f = self._cams[c][int(stamp_ns)]
            img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) if f.is_file() else None
            if img is None:
                self.stats["unreadable_images"] += 1
                log.warning("%s: missing or unreadable image; frame %d skipped", f, stamp_ns)
                return None
            imgs.append(img)
        return imgs

    def messages(self, imu_margin_ns: int | None = None, start_ns: int = 0):
        """Yield ImuSample and MultiCameraFrame in time order (IMU first on ties).

        ``imu_margin_ns``: yield only the IMU samples from this long before the first frame to this long after
        the last (the rest is counted in ``stats['imu_outside_frames']``); None: every sample. ``start_ns`` > 0:
        begin that long after the first frame, as if the sensors were switched on there (mid-flight): earlier
        frames are left out, and earlier IMU samples too, but for the margin (they count as outside the frames). Each frame's images are
        read right after the frame before it is yielded, so that a player at sensor rate does not decode them when
        they fall due (two 752x480 PNGs cost ~5 ms).
        """
        i = j = seq_i = seq_f = 0
        ahead, ahead_j = None, -1  # the next frame's images, read as soon as the frame before it was yielded
        ti, tf = self.imu_stamps_ns, self.frame_stamps_ns
        values = self.imu_values
        if start_ns < 0:
            raise ValueError(f"start_ns must be >= 0, got {start_ns}")
        if start_ns > 0 and len(tf):
            tf = tf[tf >= tf[0] + start_ns]
            if not len(tf):
                raise DatasetError(f"{self.root}: no frame {start_ns * 1e-9:.1f} s or more after the first; the "
                                   f"sequence spans {(self.frame_stamps_ns[-1] - self.frame_stamps_ns[0]) * 1e-9:.1f} s")
            if imu_margin_ns is None:  # every sample from the start on
                ti, values = ti[ti >= tf[0]], values[ti >= tf[0]]
        span = (int(tf[0]), int(tf[-1])) if len(tf) else None
        if imu_margin_ns is not None and span is not None:
            keep = (ti >= span[0] - imu_margin_ns) & (ti <= span[1] + imu_margin_ns)
            self.stats["imu_outside_frames"] = int((~keep).sum())
            if not keep.all():
                log.info("%s: %d of %d IMU samples lie more than %.2f s outside the frames' span; not played",
                         self.root / "imu0" / "data.csv", int((~keep).sum()), len(ti), imu_margin_ns * 1e-9)
            ti, values = ti[keep], values[keep]
        while i < len(ti) or j < len(tf):
            if j >= len(tf) or (i < len(ti) and ti[i] <= tf[j]):
                v = values[i]
                yield ImuSample(header=Header(stamp_ns=int(ti[i]), seq=seq_i, frame_id="S"),
                                omega_S=v[:3].copy(), acc_S=v[3:].copy())
                i += 1
                seq_i += 1
            else:
                imgs = ahead if ahead_j == j else self.load_frame(tf[j])
                if imgs is not None:
                    yield MultiCameraFrame(header=Header(stamp_ns=int(tf[j]), seq=seq_f, frame_id="rig"),
                                           images=tuple(imgs), camera_names=tuple(self.camera_names),
                                           stamps_ns=np.full(len(imgs), tf[j], dtype=np.int64))
                    seq_f += 1
                j += 1
                if j < len(tf):  # decode the next frame now, not when it falls due (a player publishes it on time)
                    ahead, ahead_j = self.load_frame(tf[j]), j
