"""Where sigmaslam finds the data that lives outside the repository.

The real EuRoC files (calibration, ground truth, IMU, image timestamps) are in ``../shared/data/euroc``
beside the checkout; ``SIGMASLAM_SHARED`` overrides the ``../shared`` folder. Generated data (replicas,
caches) goes under ``SIGMASLAM_DATA`` (default ``<repo>/data``, git-ignored).
"""
from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]

# short sequence names and the file stems of ../shared/data/euroc
EUROC_SEQUENCES = {
    "V1_02": {"groundtruth": "V1_02_medium", "imu": "V102", "images": "V102"},
    "V2_01": {"groundtruth": "V2_01_easy", "imu": "V201", "images": "V201"},
    "MH_04": {"groundtruth": "MH_04_difficult", "imu": "MH04", "images": "MH04_stereo"},
}


def shared_dir() -> Path:
    return Path(os.environ.get("SIGMASLAM_SHARED", REPO_ROOT.parent / "shared")).resolve()


def euroc_dir() -> Path:
    """``../shared/data/euroc`` (calib/, groundtruth/, imu/, image_timestamps/)."""
    d = shared_dir() / "data" / "euroc"
    if not d.is_dir():
        raise FileNotFoundError(f"{d}: EuRoC data folder not found (set SIGMASLAM_SHARED to the folder holding data/euroc)")
    return d


def euroc_files(sequence: str) -> dict[str, Path]:
    """Paths of the ground truth, real IMU and image timestamps of a sequence ('V1_02', 'V2_01', 'MH_04')."""
    if sequence not in EUROC_SEQUENCES:
        raise KeyError(f"unknown sequence {sequence!r}; known: {', '.join(EUROC_SEQUENCES)}")
    names, d = EUROC_SEQUENCES[sequence], euroc_dir()
    return {"groundtruth": d / "groundtruth" / f"{names['groundtruth']}.state_groundtruth_estimate0.csv.xz",
            "imu": d / "imu" / f"{names['imu']}.imu0_data.csv.xz",
            "image_timestamps": d / "image_timestamps" / f"{names['images']}.txt",
            "calib": d / "calib"}


def data_dir() -> Path:
    """Root of generated data (replicas, caches); created on demand."""
    d = Path(os.environ.get("SIGMASLAM_DATA", REPO_ROOT / "data"))
    d.mkdir(parents=True, exist_ok=True)
    return d
