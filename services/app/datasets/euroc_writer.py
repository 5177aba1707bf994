"""Write the EuRoC ASL layout (mav0/camN, imu0, state_groundtruth_estimate0)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml

from shared.euroc import PoseSeries, write_euroc_csv


def _yaml(path: Path, d: dict) -> None:
    path.write_text("%YAML:1.0\n" + yaml.safe_dump(d, sort_keys=False))


def write_euroc(path: str | Path, camera_yaml: dict[str, dict], frames_iter, imu_array: np.ndarray,
                imu_yaml: dict, groundtruth: PoseSeries | None = None, imu_stamps_ns: np.ndarray | None = None) -> Path:
    """frames_iter yields (stamp_ns, [img per camera]); imu_array (N, 7): t_ns, w xyz, a xyz. Returns mav0.

    ``imu_stamps_ns`` (N,) int64, when given, replaces column 0 (float64 cannot hold every ns stamp)."""
    root = Path(path) / "mav0"
    names = list(camera_yaml)
    files = {}
    for c in names:
        (root / c / "data").mkdir(parents=True, exist_ok=True)
        _yaml(root / c / "sensor.yaml", camera_yaml[c])
        files[c] = open(root / c / "data.csv", "w")
        files[c].write("#timestamp [ns],filename\n")
    try:
        for stamp, imgs in frames_iter:
            for c, img in zip(names, imgs):
                cv2.imwrite(str(root / c / "data" / f"{int(stamp)}.png"), img)
                files[c].write(f"{int(stamp)},{int(stamp)}.png\n")
    finally:
        for f in files.values():
            f.close()
    (root / "imu0").mkdir(parents=True, exist_ok=True)
    _yaml(root / "imu0" / "sensor.yaml", imu_yaml)
    with open(root / "imu0" / "data.csv", "w") as f:
        f.write("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
                "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n")
        rows = np.asarray(imu_array)
        stamps = np.asarray(imu_stamps_ns, dtype=np.int64) if imu_stamps_ns is not None else rows[:, 0] if len(rows) else []
        for t, r in zip(stamps, rows):
            f.write(f"{int(t)}," + ",".join(repr(float(x)) for x in r[1:]) + "\n")
    if groundtruth is not None:
        (root / "state_groundtruth_estimate0").mkdir(parents=True, exist_ok=True)
        write_euroc_csv(root / "state_groundtruth_estimate0" / "data.csv", groundtruth)
    return root
