"""Ground-truth depth images of replicas: 16-bit PNG, depth along the optical axis in fixed steps.

``value = round(depth_m / scale_m)`` stored as uint16 PNG; 0 means "no depth" (no surface, or beyond
``65535 * scale_m``). The scale is in the folder's ``sensor.yaml`` (``depth_scale_m``), 0.2 mm for
rooms whose diagonal fits 13.1 m, else 0.5 mm (up to 32.7 m). The quantisation error is at most half a
step. Depth images share the geometry (distorted pixels, resolution) of the camera named in
``sensor.yaml`` (``camera``).

Folder layout (EuRoC-like): ``mav0/depth<i>/{sensor.yaml, data.csv, data/<stamp_ns>.png}``.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml

MAX_VALUE = 65535


def choose_scale(max_range_m: float) -> float:
    """Finest of 0.2 mm / 0.5 mm / 1 mm steps that represents ``max_range_m``."""
    for s in (0.0002, 0.0005, 0.001):
        if max_range_m <= MAX_VALUE * s:
            return s
    raise ValueError(f"depth range {max_range_m:.1f} m too large for 16-bit depth at 1 mm")


def encode_depth(depth_m: np.ndarray, scale_m: float) -> tuple[np.ndarray, int]:
    """float depth [m] (NaN/<=0 invalid) -> (uint16 image, number of valid pixels beyond range set to 0)."""
    d = np.asarray(depth_m, np.float64)
    q = np.round(np.where(np.isfinite(d) & (d > 0), d, 0.0) / scale_m)
    over = q > MAX_VALUE
    q[over] = 0
    return q.astype(np.uint16), int(over.sum())


def decode_depth(img: np.ndarray, scale_m: float) -> np.ndarray:
    """uint16 image -> float32 depth [m], NaN where 0."""
    d = img.astype(np.float32) * np.float32(scale_m)
    d[img == 0] = np.nan
    return d


def write_depth_png(path: str | Path, depth_m: np.ndarray, scale_m: float) -> int:
    """Write one depth image; returns the count of pixels dropped for being out of range."""
    img, over = encode_depth(depth_m, scale_m)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"{path}: could not write depth PNG")
    return over


def read_depth_png(path: str | Path, scale_m: float) -> np.ndarray:
    """(H, W) float32 depth [m] (NaN = none) from a 16-bit PNG; clear error if missing or not 16-bit."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FileNotFoundError(f"{path}: missing or unreadable depth image")
    if img.dtype != np.uint16 or img.ndim != 2:
        raise ValueError(f"{path}: expected a single-channel 16-bit PNG, got {img.dtype} {img.shape}")
    return decode_depth(img, scale_m)


class DepthFolder:
    """Reader of ``mav0/depth<i>``: ``stamps_ns``, ``camera``, ``scale_m``, ``read(stamp_ns)`` -> float32 [m]."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        meta = self.path / "sensor.yaml"
        if not meta.is_file():
            raise FileNotFoundError(f"{meta}: depth sensor.yaml not found")
        d = yaml.safe_load(meta.read_text().split("\n", 1)[1] if meta.read_text().startswith("%YAML") else meta.read_text())
        for k in ("camera", "depth_scale_m"):
            if k not in (d or {}):
                raise KeyError(f"{meta}: missing key {k!r}")
        self.camera, self.scale_m = str(d["camera"]), float(d["depth_scale_m"])
        csv = self.path / "data.csv"
        if not csv.is_file():
            raise FileNotFoundError(f"{csv}: not found")
        rows = [ln.split(",") for ln in csv.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
        self._files = {int(r[0]): self.path / "data" / r[1].strip() for r in rows}
        self.stamps_ns = np.array(sorted(self._files), dtype=np.int64)

    def read(self, stamp_ns: int) -> np.ndarray:
        if int(stamp_ns) not in self._files:
            raise KeyError(f"{self.path}: no depth at {stamp_ns}")
        return read_depth_png(self._files[int(stamp_ns)], self.scale_m)


def write_depth_sensor_yaml(folder: Path, camera: str, scale_m: float) -> None:
    (folder / "data").mkdir(parents=True, exist_ok=True)
    (folder / "sensor.yaml").write_text("%YAML:1.0\n" + yaml.safe_dump({
        "sensor_type": "depth", "comment": "ground-truth depth along the optical axis of the camera, uint16 PNG",
        "camera": camera, "depth_scale_m": scale_m, "invalid_value": 0}, sort_keys=False))
