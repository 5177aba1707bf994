"""Track error against the ground truth (tools/eval/track_error.py): its geometry on constructed input, and the
whole measurement on a short replica, where a wrong pose lookup must show."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tools.eval.track_error import AGE_BINS, depth_at, measure, pose_lookup, summarise


def test_pose_lookup_interpolates_position_and_rotation():
    t = np.array([0, 1_000_000_000, 2_000_000_000], np.int64) + 10**18
    p = np.array([[0.0, 0, 0], [1, 2, 0], [1, 2, 4]])
    q = Rotation.from_euler("z", [[0], [40], [80]], degrees=True).as_quat()[:, [3, 0, 1, 2]]
    T_WS = pose_lookup(t, p, q)
    T = T_WS(t[0] + 250_000_000)
    np.testing.assert_allclose(T[:3, 3], [0.25, 0.5, 0.0], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], Rotation.from_euler("z", 10, degrees=True).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(T_WS(t[2])[:3, 3], p[2], atol=1e-12)
    with pytest.raises(ValueError, match="outside"):
        T_WS(t[2] + 1)


def test_depth_at_skips_edges_and_holes():
    d = np.full((20, 20), 2.0)
    d[:, 10:] = 3.0  # a step: pixels next to column 10 sit on an edge
    d[5, 5] = 0.0  # no depth
    got = depth_at(d, np.array([[3.2, 3.4], [9.0, 12.0], [10.4, 12.0], [15.0, 15.0], [5.0, 4.0], [0.0, 5.0]]))
    np.testing.assert_allclose(got[[0, 3]], [2.0, 3.0])
    assert np.isnan(got[[1, 2, 4, 5]]).all()  # on the step, on the step, beside the hole, on the border


def test_summarise_bins_by_age():
    ages = np.array([1, 2, 3, 7, 50, 200])
    errs = np.array([0.1, 0.3, 1.0, 2.0, 3.0, 4.0])
    s = summarise(errs, ages)
    assert s["all"]["n"] == 6 and s["all"]["median_px"] == pytest.approx(1.5)
    assert s["1-2"]["n"] == 2 and s["1-2"]["median_px"] == pytest.approx(0.2)
    assert s[">=81"]["n"] == 1 and s["11-20"]["n"] == 0 and np.isnan(s["11-20"]["median_px"])
    assert len(s) == len(AGE_BINS) + 1


@pytest.mark.e2e
def test_tracks_on_a_replica_sit_where_the_ground_truth_puts_them(cached_replica):
    folder = cached_replica("V1_02", duration_s=1.5)  # shared with test_mapping_replica's reduced form
    res = measure(folder, frames=30)
    young = res["errors"]["1-2"]
    assert res["tracks"] > 50 and young["n"] > 100
    assert young["median_px"] < 0.2, res["errors"]  # a clean replica: a fraction of a pixel after one frame
    # the same tracks scored against poses 200 ms late (the drone starts slowly): the camera's motion must show
    late = measure(folder, frames=30, shift_ms=200.0)
    assert late["errors"]["1-2"]["median_px"] > 2 * young["median_px"], late["errors"]


@pytest.mark.e2e
def test_affine_refinement_stops_the_drift_with_age(cached_replica):
    """Translation-only KLT drifts as the tracks age (exposure changes, the patches' scale and shape); refined
    against their first patch (frontend.klt_affine) the old tracks stay near the young ones' error."""
    folder = cached_replica("V1_02", duration_s=1.5)
    plain = measure(folder, frames=30, overrides=["frontend.klt_affine=false"])["errors"]
    affine = measure(folder, frames=30, overrides=["frontend.klt_affine=true"])["errors"]
    assert plain["21-40"]["median_px"] > 2 * plain["1-2"]["median_px"]  # the drift is there to stop
    assert affine["21-40"]["median_px"] < 0.6 * plain["21-40"]["median_px"], (plain, affine)
    assert affine["21-40"]["n"] > 0.8 * plain["21-40"]["n"]  # and the old tracks are kept
