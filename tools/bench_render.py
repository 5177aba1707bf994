"""Render throughput on this machine: ``python -m tools.bench_render [--scene vicon-a] [--frames 20]``.

Prints the median time of one camera image (752x480, real distortion), of its GT depth, and the stereo
frame rate (two images + one depth), along V1_02's trajectory.
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="vicon-a")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--supersample", type=int, default=1)
    a = ap.parse_args()
    from shared.euroc import read_euroc_csv
    from shared.paths import euroc_files
    from services.app.synth.trajectory import Trajectory
    from services.app.synth.render import RenderConfig, Renderer
    from services.app.synth.replica import load_calibration
    from services.app.synth.scene import build_scene

    t = time.perf_counter()
    scene = build_scene(a.scene)
    t_scene = time.perf_counter() - t
    cams = load_calibration(euroc_files("V1_02")["calib"])[0]
    r = Renderer(scene, cams, RenderConfig(supersample=a.supersample))
    traj = Trajectory(read_euroc_csv(euroc_files("V1_02")["groundtruth"]))
    stamps = np.linspace(traj.t0_ns + 5e9, traj.t_end_ns - 5e9, a.frames).astype(np.int64)
    rng = np.random.default_rng(0)
    img_t, dep_t, rig_t = [], [], []
    for s in stamps:
        T_WC = traj.pose(s) @ cams[0].T_SC
        t = time.perf_counter()
        r.image([T_WC], 0, 0.0, rng)
        img_t.append(time.perf_counter() - t)
        r._last_hit = None  # time a depth cast of its own
        t = time.perf_counter()
        r.depth(T_WC, 0)
        dep_t.append(time.perf_counter() - t)
        t = time.perf_counter()
        r.render_rig(traj.pose(s), 0.0, rng)
        rig_t.append(time.perf_counter() - t)
    print(f"scene {a.scene}: {len(scene.triangles)} triangles, atlas {scene.atlas.shape}, built in {t_scene:.1f} s")
    print(f"one image 752x480 (supersample {a.supersample}): median {np.median(img_t) * 1e3:.0f} ms; "
          f"GT depth: median {np.median(dep_t) * 1e3:.0f} ms; "
          f"stereo frame (2 images + depth): median {np.median(rig_t) * 1e3:.0f} ms = {1 / np.median(rig_t):.2f} frames/s")


if __name__ == "__main__":
    main()
