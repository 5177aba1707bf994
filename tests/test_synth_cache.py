"""Replicas in the cache (services/app/synth/api.py): generated once under concurrency, a named profile gets its own,
a time shift moves the images."""

from __future__ import annotations

import numpy as np
import pytest

from services.app.synth.depth_io import DepthFolder
from services.app.synth.render import RenderConfig
from services.app.synth.replica import ReplicaSpec, generate, plan
from shared.euroc import read_euroc_csv


def test_ensure_replica_generates_once_under_concurrency(tmp_path, monkeypatch):
    """Two threads ask for the same replica at once: one generates (into .partial, renamed when done), the other
    waits on the lock and gets the same folder; a later call finds it cached. Generation itself is stubbed (what it
    writes: test_replica_layout_and_reader); the stub keeps the lock held a while so that the threads overlap."""
    import threading
    import time

    from services.app.synth import api

    calls, errors, paths = [], [], []

    def fake_generate(spec, out, progress=True):
        calls.append(spec)
        time.sleep(0.2)  # the other thread reaches the lock meanwhile
        out.mkdir(parents=True)
        (out / "replica.yaml").write_text(f"generator_version: {api.GENERATOR_VERSION}\nframes: {len(plan(spec)['frames'])}\n")
        return out

    monkeypatch.setattr(api, "generate", fake_generate)

    def get():
        return api.ensure_replica("V1_02", "vicon-b", imu="sim", duration_s=0.3, start_s=5.0, root=tmp_path,
                                  progress=False)

    def call():
        try:
            paths.append(get())
        except Exception as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=call) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(paths) == 2 and paths[0] == paths[1]
    assert len(calls) == 1  # generated once, the other caller waited for it
    assert (paths[0] / "replica.yaml").is_file() and not list(tmp_path.glob("*.partial"))
    assert get() == paths[0] and len(calls) == 1  # cached: not generated again
    assert (paths[0] / "replica.yaml").read_text().endswith("frames: 7\n")  # 0.3 s at 20 Hz, both ends included
    # a replica of an older generator is made again, in the same place
    (paths[0] / "replica.yaml").write_text("generator_version: 1\nframes: 7\n")
    assert get() == paths[0] and len(calls) == 2 and api._current(paths[0])


@pytest.mark.e2e
def test_replica_time_shift_moves_the_images(tmp_path):
    """timeshift_cam_imu_s: the image stamped t shows the scene at t + shift; the ground truth stays on the IMU."""
    base = dict(scene="vicon-a", sequence="V1_02", imu="sim", imu_noise=False, start_s=20.0, duration_s=0.15,
                depth_cameras=[0])
    a = generate(ReplicaSpec(**base), tmp_path / "a", progress=False)
    b = generate(ReplicaSpec(**base, timeshift_cam_imu_s=0.05), tmp_path / "b", progress=False)
    da, db = DepthFolder(a / "mav0" / "depth0"), DepthFolder(b / "mav0" / "depth0")
    sa, sb = da.stamps_ns, db.stamps_ns
    np.testing.assert_array_equal(sa, sb)
    # b's frame k is a's frame k + 1 (50 ms = one frame later at 20 Hz)
    assert np.nanmean(np.abs(db.read(sb[0]) - da.read(sa[1]))) < 0.3 * np.nanmean(np.abs(da.read(sa[0]) - da.read(sa[1])))
    ga = read_euroc_csv(a / "mav0" / "state_groundtruth_estimate0" / "data.csv")
    gb = read_euroc_csv(b / "mav0" / "state_groundtruth_estimate0" / "data.csv")
    np.testing.assert_allclose(ga.p_WS, gb.p_WS)


def test_named_profile_gets_its_own_cached_replica(tmp_path, monkeypatch):
    """``profile='hard'``: the spec handed to the generator carries the profile's blur, exposure jumps and clock
    offset, the folder name says so, and other non-default settings are refused (they would be cached under a
    default name)."""
    import dataclasses

    from services.app.synth import api
    from services.app.synth.profiles import PROFILES, apply_profile

    specs = []

    def fake_generate(spec, out, progress=True):
        specs.append(spec)
        out.mkdir(parents=True)
        (out / "replica.yaml").write_text(f"generator_version: {api.GENERATOR_VERSION}\nframes: 1\n")
        return out

    monkeypatch.setattr(api, "generate", fake_generate)
    hard = api.ensure_replica("V1_02", "vicon-a", imu="sim", duration_s=0.3, root=tmp_path, progress=False,
                              profile="hard")
    plain = api.ensure_replica("V1_02", "vicon-a", imu="sim", duration_s=0.3, root=tmp_path, progress=False)
    assert hard.name == plain.name + "-hard" and len(specs) == 2
    r = specs[0].render
    assert r.motion_blur_samples == PROFILES["hard"]["render"]["motion_blur_samples"] > 1
    assert r.motion_blur_mode == "flow" and r.exposure_jump_rate_hz > 0
    assert specs[0].timeshift_cam_imu_s == PROFILES["hard"]["timeshift_cam_imu_s"] and specs[1].render == RenderConfig()
    with pytest.raises(ValueError, match="unknown replica profile"):
        apply_profile(specs[1], "blurry")
    odd = dataclasses.replace(specs[1], render=dataclasses.replace(RenderConfig(), read_noise_dn=9.0))
    with pytest.raises(ValueError, match="default render settings or a named profile"):
        api.ensure_spec(odd, tmp_path)
