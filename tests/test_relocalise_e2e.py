"""Localising in the saved map of another flight, with the product's replicas (not the test box room): the default
replica (25 s of V1_02 in the room 'vicon-a') is mapped, then 12 s of V2_01, a different flight through the same room,
localise in that map (``sigmaslam eval relocalise``: both runs in one process, lockstep, reproducible).

Until replicas of a site were rendered in one scene whatever their trajectory (services/app/synth/scene.py), every
map candidate of the second flight failed PnP: the two replicas showed the same room with other textures."""

from __future__ import annotations

import pytest


@pytest.mark.e2e
def test_another_flight_through_the_room_localises_in_the_default_replicas_map(tmp_path):
    from services.app.synth.api import ensure_replica
    from services.app.eval.relocalise import evaluate

    a = ensure_replica("V1_02", "vicon-a", imu="real", duration_s=25.0)  # the demo's, cached by the first test using it
    b = ensure_replica("V2_01", "vicon-a", imu="real", start_s=56.0, duration_s=12.0)  # passes where a looked
    rep = evaluate(str(a), str(b), tmp_path)
    counts = rep["loop_counts"]
    assert rep["time_to_relocalise_s"] is not None and rep["time_to_relocalise_s"] < 8.0, (rep, counts)
    assert rep["localised_fraction"] > 0.4, rep
    assert counts.get("verified", 0) >= 3 and counts["verified"] > 0.1 * counts["proposed"], counts
    assert rep["ate_map_frame_causal_m"] < 0.08, rep  # the first run's alignment to the truth only
