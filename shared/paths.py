"""Where sigmaslam finds its data.

Real EuRoC files (calibration, ground truth, IMU, image timestamps) are looked up file by file in two places, in
this order:

1. ``$SIGMASLAM_SHARED/data/euroc`` (default ``../shared/data/euroc`` beside the checkout): all eight sequences
   the project uses, when that folder is there;
2. ``<repo>/data/euroc``: the files bundled with the repository (CC BY-NC-SA 3.0, data/euroc/README.md): the rig
   calibration and V1_02 and V2_01, enough for the default replica, so a fresh clone runs on its own.

Other shared data (real images under ``data/real``) is only in the first place: :func:`real_data_dir`.
Generated data (replicas, caches) goes under ``SIGMASLAM_DATA`` (default ``<repo>/data``, git-ignored but for
``data/euroc``).
"""
from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
BUNDLED_EUROC = REPO_ROOT / "data" / "euroc"

# short sequence names -> the files of data/euroc: ground truth (17-column EuRoC CSV or TUM, xz), real imu0 data
# (None: the sequence has none here; replicas simulate it), cam0 image stamps (the stereo list where cam1 misses frames)
EUROC_SEQUENCES = {
    "MH_01": {"groundtruth": "MH_01_easy.groundtruth_tum.txt", "imu": None, "images": "MH01"},
    "MH_02": {"groundtruth": "MH_02_easy.groundtruth_tum.txt", "imu": None, "images": "MH02"},
    "MH_03": {"groundtruth": "MH_03_medium.groundtruth_tum.txt", "imu": "MH03", "images": "MH03"},
    "MH_04": {"groundtruth": "MH_04_difficult.state_groundtruth_estimate0.csv", "imu": "MH04", "images": "MH04_stereo"},
    # V1_01: OpenVINS' vicon2gt re-estimate (the original's orientation is known to be off, and the replica pairs
    # the ground truth with the real IMU)
    "V1_01": {"groundtruth": "V1_01_easy.vicon2gt_openvins.csv", "imu": "V101", "images": "V101"},
    "V1_02": {"groundtruth": "V1_02_medium.state_groundtruth_estimate0.csv", "imu": "V102", "images": "V102"},
    "V2_01": {"groundtruth": "V2_01_easy.state_groundtruth_estimate0.csv", "imu": "V201", "images": "V201"},
    "V2_03": {"groundtruth": "V2_03_difficult.state_groundtruth_estimate0.csv", "imu": "V203", "images": "V203_stereo"},
}


class DataNotFound(FileNotFoundError):
    """A data file that is neither in the shared data folder nor bundled with the repository."""


def shared_dir() -> Path:
    """The folder of data kept outside the repository (``$SIGMASLAM_SHARED``, default ``../shared``)."""
    return Path(os.environ.get("SIGMASLAM_SHARED", REPO_ROOT.parent / "shared")).resolve()


def euroc_roots() -> list[Path]:
    """The EuRoC folders searched, in order: the shared one (if present), then the bundled one."""
    shared = shared_dir() / "data" / "euroc"
    return [r for r in (shared, BUNDLED_EUROC) if r.is_dir()]


def euroc_file(relative: str) -> Path:
    """``relative`` (e.g. ``calib/cam0_sensor.yaml``) from the first EuRoC folder that has it."""
    for root in euroc_roots():
        if (root / relative).exists():
            return root / relative
    raise DataNotFound(f"{relative}: not in {shared_dir() / 'data' / 'euroc'} nor bundled in {BUNDLED_EUROC}; "
                       "set SIGMASLAM_SHARED to a folder holding data/euroc/ with it")


def euroc_dir() -> Path:
    """The EuRoC folder holding the rig calibration (``calib/``): the shared one if present, else the bundled one."""
    return euroc_file("calib").parent


def euroc_files(sequence: str) -> dict[str, Path]:
    """Paths of the ground truth, real IMU, image timestamps and rig calibration of a known sequence.

    Each file comes from the first folder of :func:`euroc_roots` that has it; a file that no folder has raises
    :class:`DataNotFound` naming it (e.g. MH_04 on a fresh clone without ``../shared``)."""
    if sequence not in EUROC_SEQUENCES:
        raise KeyError(f"unknown sequence {sequence!r}; known: {', '.join(EUROC_SEQUENCES)}")
    names = EUROC_SEQUENCES[sequence]
    files = {"groundtruth": euroc_file(f"groundtruth/{names['groundtruth']}.xz"),
             "image_timestamps": euroc_file(f"image_timestamps/{names['images']}.txt"),
             "calib": euroc_file("calib")}
    if names["imu"]:
        files["imu"] = euroc_file(f"imu/{names['imu']}.imu0_data.csv.xz")
    return files


def has_real_imu(sequence: str) -> bool:
    """Whether the recorded imu0 data of ``sequence`` exists (else replicas of it need ``imu='sim'``)."""
    try:
        return "imu" in euroc_files(sequence)
    except DataNotFound:
        return False


def has_sequence(sequence: str) -> bool:
    """Whether every file of ``sequence`` can be found (for tests that skip without it)."""
    try:
        euroc_files(sequence)
    except DataNotFound:
        return False
    return True


def real_data_dir(name: str = "") -> Path:
    """``$SIGMASLAM_SHARED/data/real[/name]``: real images kept outside the repository (licences forbid copying
    them in). Raises :class:`DataNotFound` when absent."""
    d = shared_dir() / "data" / "real" / name
    if not d.exists():
        raise DataNotFound(f"{d}: real image data not found (set SIGMASLAM_SHARED to the folder holding data/real)")
    return d


def data_dir() -> Path:
    """Root of generated data (replicas, caches); created on demand."""
    d = Path(os.environ.get("SIGMASLAM_DATA", REPO_ROOT / "data"))
    d.mkdir(parents=True, exist_ok=True)
    return d
