"""frontend.match_gain_cross on real photographs: on the real EuRoC V1_01 frames camera 0 is ~11 % brighter than
camera 1, and the camera-to-camera KLT finds many more of camera 0's features in camera 1 on gain-matched images
(tools/eval/cross_matches.py)."""
from __future__ import annotations

import pytest

from tools.eval.cross_matches import cross_match_shares

pytestmark = pytest.mark.e2e  # tracks 60 real stereo pairs twice (~10 s)


def test_gain_matching_finds_more_stereo_matches_on_real_frames(real_data):
    r = cross_match_shares(str(real_data("euroc_V1_01_micro", "mav0")))
    assert r["frames"] == 60 and r["brightness_ratio"] > 1.05  # the cameras' exposures do differ
    (n_off, off), (n_on, on) = r["off"], r["on"]
    assert on > off + 0.1
    assert abs(n_on - n_off) < 0.1 * n_off  # as many features in camera 0; more of them matched
