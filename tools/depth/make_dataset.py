"""Render the depth networks' training/validation/test sets from procedural scenes (tools/depth/scenes.py).

Per scene: a short camera walk of ``frames`` rectified stereo pairs (left, right, left z-depth) with the
EuRoC rectified intrinsics at 512x384 and the EuRoC baseline; stereo samples are single frames, MVS samples
are a frame plus others of the same walk. Splits use disjoint scene seeds: train 1000+, val 2000+,
test (an unseen scene family for the calibration check) 3000+.

    .venv/bin/python -m tools.depth.make_dataset --out data/depth_train --train 30 --val 5 --test 5
"""
from __future__ import annotations

import argparse
import json
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np

from tools.depth.scenes import _inside_object, look_at, random_camera, random_scene, render_pinhole

# rectified EuRoC cam0/cam1 at 512x384 (shared.camera.stereo_rectification, fov_scale 1)
K_RECT = np.array([[312.275, 0.0, 255.5], [0.0, 312.275, 191.5], [0.0, 0.0, 1.0]])
BASELINE_M = 0.110078
SIZE = (512, 384)
SPLIT_SEED0 = {"train": 1000, "val": 2000, "test": 3000}


def camera_walk(scene, rng: np.random.Generator, frames: int) -> np.ndarray:
    """(frames, 4, 4) T_WC along a straight-ish walk of 4-10 cm steps, looking at a slowly moving target."""
    for _ in range(100):
        T0 = random_camera(scene, rng)
        step = rng.uniform(0.04, 0.10)
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        target = T0[:3, 3] + 2.0 * T0[:3, 2]
        drift = rng.normal(0, 0.05, 3)
        poses = []
        for i in range(frames):
            pos = T0[:3, 3] + i * step * direction + rng.normal(0, 0.005, 3)
            if _inside_object(scene, pos, 0.25) or not ((pos > scene.box_lo[0] + 0.3) & (pos < scene.box_hi[0] - 0.3)).all():
                break
            poses.append(look_at(pos, target + i * drift, rng.normal(0, 0.05)))
        if len(poses) == frames:
            return np.stack(poses)
    raise RuntimeError("no valid camera walk found in 100 tries")


def render_scene(args: tuple[str, int, int, str]) -> str:
    split, seed, frames, out = args
    path = Path(out) / split / f"scene_{seed:05d}.npz"
    if path.exists():  # deterministic per seed: an existing scene is the same scene
        return str(path) + " (kept)"
    rng = np.random.default_rng(seed)
    scene = random_scene(rng, n_boxes=int(rng.integers(3, 9)), n_spheres=int(rng.integers(1, 5)))
    T_WC = camera_walk(scene, rng, frames)
    T_C0C1 = np.eye(4)
    T_C0C1[0, 3] = BASELINE_M
    left, right, depth = [], [], []
    for T in T_WC:
        noise = rng.uniform(0.5, 3.0)
        img0, d0 = render_pinhole(scene, T, K_RECT, SIZE, supersample=1, noise_std=noise, rng=rng)
        img1, _ = render_pinhole(scene, T @ T_C0C1, K_RECT, SIZE, supersample=1, noise_std=noise, rng=rng)
        left.append(img0)
        right.append(img1)
        depth.append(d0)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.npz")  # rename at the end: a killed render leaves no half file
    np.savez_compressed(tmp, left=np.stack(left), right=np.stack(right), depth=np.stack(depth), T_WC=T_WC,
                        K=K_RECT, baseline_m=BASELINE_M)
    tmp.replace(path)
    return str(path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="data/depth_train")
    p.add_argument("--train", type=int, default=30, help="training scenes")
    p.add_argument("--val", type=int, default=5, help="validation scenes (calibration split)")
    p.add_argument("--test", type=int, default=5, help="unseen test scenes")
    p.add_argument("--frames", type=int, default=12, help="frames per scene walk")
    p.add_argument("--workers", type=int, default=2)
    a = p.parse_args(argv)
    jobs = [(split, SPLIT_SEED0[split] + i, a.frames, a.out)
            for split, n in (("train", a.train), ("val", a.val), ("test", a.test)) for i in range(n)]
    t0 = time.time()
    with Pool(a.workers) as pool:
        for i, path in enumerate(pool.imap_unordered(render_scene, jobs)):
            print(f"[{i + 1}/{len(jobs)}] {path} ({time.time() - t0:.0f} s)", flush=True)
    Path(a.out).mkdir(parents=True, exist_ok=True)
    (Path(a.out) / "dataset.json").write_text(json.dumps({
        "command": "python -m tools.depth.make_dataset " + " ".join(argv or __import__("sys").argv[1:]),
        "generator": "tools/depth/scenes.py", "split_seed0": SPLIT_SEED0, "frames": a.frames,
        "K": K_RECT.tolist(), "baseline_m": BASELINE_M, "size": SIZE,
        "scenes": {split: f"seeds {SPLIT_SEED0[split]}-{SPLIT_SEED0[split] + n - 1}" if n else "none"
                   for split, n in (("train", a.train), ("val", a.val), ("test", a.test))}}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
