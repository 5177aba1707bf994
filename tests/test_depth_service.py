"""The depth service as a real process on real Zenoh (loopback router): a rendered EuRoC stereo frame and
its estimator state in, depth/stereo and depth/fused out with the rectified camera's K and T_SC and
T_WC = T_WS T_SC, depth close to the ground truth; a malformed frame is dropped and counted without
stopping the service; a frame without a state goes out unposed; a burst faster than the rate is thinned
(drops counted in stats/depth); SIGTERM exits 0."""
from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import yaml

from services.depth.config import DepthConfig
from services.depth.pipeline import DepthPipeline
from shared import messages as m
from shared import topics
from shared.camera import camera_from_sensor_yaml, read_sensor_yaml_file
from shared.codec import Header
from shared.config import to_dict
from shared.paths import euroc_dir
from tests.helpers_zenoh import REPO, child_env, router, wait_for, wait_for_heartbeat
from tools.depth.scenes import random_camera, random_scene, render_pinhole, render_rays
from transport.pubsub import Publisher, Subscriber
from transport.session import open_session


@pytest.fixture(scope="module")
def frame_data():
    calib = euroc_dir() / "calib"
    cams = [camera_from_sensor_yaml(read_sensor_yaml_file(calib / f"cam{i}_sensor.yaml"), f"cam{i}") for i in (0, 1)]
    rng = np.random.default_rng(11)
    scene = random_scene(rng)
    T_WN0 = random_camera(scene, rng)
    ref = DepthPipeline(DepthConfig(method="sgbm"), *cams)
    T_WS = T_WN0 @ np.linalg.inv(ref.T_SC)
    images = []
    for cam in cams:
        img, _ = render_rays(scene, T_WS @ cam.T_SC, cam.camera.unproject(cam.camera.pixel_grid()))
        images.append(np.clip(img * 255, 0, 255).astype(np.uint8).reshape(cam.camera.height, cam.camera.width))
    _, gt = render_pinhole(scene, T_WN0, ref.K, (512, 384), supersample=1)
    return ref, T_WS, tuple(images), gt


def _frame(stamp, images, names=("cam0", "cam1")):
    return m.MultiCameraFrame(header=Header(stamp_ns=stamp, frame_id="rig"), images=images, camera_names=names,
                              stamps_ns=np.array([stamp] * len(images), np.int64))


def _state(stamp, T_WS):
    return m.EstimatorState(header=Header(stamp_ns=stamp, frame_id="W"), T_WS=T_WS, v_W=np.zeros(3),
                            gyro_bias=np.zeros(3), acc_bias=np.zeros(3), covariance=np.eye(15))


@pytest.mark.e2e
def test_depth_service_end_to_end(tmp_path, frame_data):
    ref, T_WS, images, gt = frame_data
    with router() as tcfg:
        cfg = {"transport": to_dict(tcfg) | {"stats_period_s": 0.2, "heartbeat_period_s": 0.2},
               "depth": {"method": "sgbm", "rate_hz": 4.0, "pose_wait_s": 0.3}}
        cfg_path = tmp_path / "system.yaml"
        cfg_path.write_text(yaml.safe_dump(cfg))
        proc = subprocess.Popen([sys.executable, "-m", "services.app.cli", "depth", str(cfg_path)], cwd=REPO,
                                env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        lines: list[str] = []
        threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True).start()
        try:
            ns = tcfg.namespace
            stereo, fused, stats = [], [], []
            with open_session(tcfg) as session:
                # up once it heartbeats (after warming its networks up)
                assert wait_for_heartbeat(session, tcfg, "depth", 60.0, proc), "".join(lines)
                subs = [Subscriber(session, f"{ns}/{topics.DEPTH_STEREO.key}", m.DepthFrame, "all", 64, handler=stereo.append),
                        Subscriber(session, f"{ns}/{topics.DEPTH_FUSED.key}", m.DepthFrame, "all", 64, handler=fused.append),
                        Subscriber(session, f"{ns}/stats/depth", m.ServiceStats, "all", 256, handler=stats.append)]
                p_frame = Publisher(session, f"{ns}/{topics.FRAME.key}", m.MultiCameraFrame, tcfg, block=True)
                p_state = Publisher(session, f"{ns}/{topics.STATE.key}", m.EstimatorState, tcfg, block=True)
                p_lm = Publisher(session, f"{ns}/{topics.LANDMARKS.key}", m.Landmarks, tcfg, block=True)
                assert p_frame.wait_for_subscribers(10.0) and p_state.wait_for_subscribers(10.0)
                assert p_lm.wait_for_subscribers(10.0)
                p_lm.publish(m.Landmarks(header=Header(stamp_ns=900, frame_id="W"), ids=np.arange(3, dtype=np.int64),
                                         p_W=np.ones((3, 3)), num_observations=np.full(3, 2, np.int32),
                                         last_seen_ns=np.full(3, 900, np.int64)))
                # 1. a posed frame
                p_state.publish(_state(1_000, T_WS))
                time.sleep(0.1)
                p_frame.publish(_frame(1_000, images))
                assert wait_for(lambda: len(stereo) >= 1 and len(fused) >= 1, 30.0), "".join(lines)
                d = stereo[0]
                assert d.header.stamp_ns == 1_000 and d.source == "stereo" and fused[0].source == "stereo"
                np.testing.assert_allclose(d.K, ref.K)
                np.testing.assert_allclose(d.T_SC, ref.T_SC)
                np.testing.assert_allclose(d.T_WC, T_WS @ ref.T_SC, atol=1e-12)
                ok = np.isfinite(d.depth)
                assert ok.mean() > 0.5
                assert np.median(np.abs(d.depth[ok] - gt[ok]) / gt[ok]) < 0.05
                # 2. a malformed frame (wrong size, then a missing camera) is dropped; the service goes on
                p_frame.publish(_frame(2_000, (images[0][:100], images[1][:100])))
                time.sleep(0.5)
                p_frame.publish(_frame(2_500, (images[0],), names=("cam0",)))
                time.sleep(0.5)
                # 3. a frame whose state never comes goes out with T_WC = identity
                p_frame.publish(_frame(3_000, images))
                assert wait_for(lambda: any(x.header.stamp_ns == 3_000 for x in stereo), 30.0), "".join(lines)
                assert np.array_equal([x for x in stereo if x.header.stamp_ns == 3_000][0].T_WC, np.eye(4))
                assert not any(x.header.stamp_ns in (2_000, 2_500) for x in stereo)
                # 4. a burst at 50 Hz is thinned to the service's rate; the replaced frames are counted
                n_before = len(stereo)
                for i in range(20):
                    p_frame.publish(_frame(10_000 + i, images))
                    time.sleep(0.02)
                time.sleep(2.0)

                def frame_drops() -> int:
                    s = stats[-1] if stats else None
                    if s is None or topics.FRAME.key not in s.queue_names:
                        return 0
                    return int(s.queue_dropped[list(s.queue_names).index(topics.FRAME.key)])
                assert wait_for(lambda: frame_drops() >= 5, 10.0), frame_drops()
                # the landmarks were received; the MVS prior counters are reported (no MVS with SGBM)
                q = dict(zip(stats[-1].queue_names, zip(stats[-1].queue_received, stats[-1].queue_dropped)))
                c = dict(zip(stats[-1].counter_names, stats[-1].counter_values))
                assert q[topics.LANDMARKS.key] == (1, 0) and "mvs_frames" not in q  # queues are queues
                assert c["mvs_frames"] == 0 and c["mvs_prior_points"] == 0 and c["uncertain_pixels"] == 0  # SGBM: no cap
                assert len(stereo) - n_before < 15
                proc.send_signal(signal.SIGTERM)
                proc.wait(timeout=30)
                for s in subs:
                    s.close()
        finally:
            proc.kill()
    assert proc.returncode == 0, "".join(lines)
    assert any("dropped" in ln for ln in lines), "".join(lines)
