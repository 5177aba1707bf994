"""Data the tests read, found through ``shared.paths`` (never a hard-coded ``../shared``), and skips that say what
is missing and where it was looked for.

EuRoC files: the shared folder (``$SIGMASLAM_SHARED/data/euroc``, default ``../shared`` beside the checkout) first,
then the files bundled in ``data/euroc`` (the rig calibration, V1_02, V2_01). Real images (``data/real``) are only
in the shared folder. Fixtures built on these are in tests/conftest.py (``euroc_calib``, ``real_data``).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from shared import paths


def _missing_sequence(sequence: str) -> str:
    return (f"EuRoC {sequence} files not found in {paths.shared_dir() / 'data' / 'euroc'} nor bundled in "
            f"{paths.BUNDLED_EUROC}: set SIGMASLAM_SHARED to the folder holding data/euroc (../shared beside the "
            "checkout)")


def needs_sequence(sequence: str) -> pytest.MarkDecorator:
    """Mark for a test (or a parameter) that needs every file of a EuRoC sequence."""
    return pytest.mark.skipif(not paths.has_sequence(sequence), reason=_missing_sequence(sequence))


def require_sequence(sequence: str) -> dict[str, Path]:
    """``shared.paths.euroc_files(sequence)``, or skip the calling test saying which files are missing where."""
    if not paths.has_sequence(sequence):
        pytest.skip(_missing_sequence(sequence))
    return paths.euroc_files(sequence)


def require_real_data(name: str, inside: str = "") -> Path:
    """``shared.paths.real_data_dir(name)`` (real images kept outside the repository), or skip the calling test
    saying where they were looked for. ``inside``: a path within it that must exist too (e.g. ``mav0``)."""
    try:
        d = paths.real_data_dir(name)
    except paths.DataNotFound:
        d = None
    if d is None or (inside and not (d / inside).exists()):
        pytest.skip(f"{paths.shared_dir() / 'data' / 'real' / name / inside}: real data not found (set "
                    "SIGMASLAM_SHARED to the folder holding data/real; ../shared beside the checkout)")
    return d
