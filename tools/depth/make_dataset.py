"""Render the depth networks' training/validation/test sets from procedural scenes (tools/depth/scenes.py).

Per scene: a short camera walk of ``frames`` rectified stereo pairs (left, right, left z-depth) with the
EuRoC rectified intrinsics at 512x384 and the EuRoC baseline; stereo samples are single frames, MVS samples
are a frame plus others of the same walk. Splits use disjoint scene seeds: train 1000+, val 2000+,
test (an unseen scene family for the calibration check) 3000+.

    .venv/bin/python -m tools.depth.make_dataset --out data/depth_train --train 30 --val 5 --test 5

``--dressed`` renders the multi-view set of issue 18 (the MVS network's "world-like" data): the same rooms with
material images on every object (tools/depth/materials.py: photographs, procedural patterns, combinations;
``--real DIR`` adds the unlabelled real ETH3D/EuRoC images as pictures), thin bars and objects close to the camera
walk, a random ambient level, focal lengths of 230-420 px, 4x supersampling, and per frame the camera effects of
the layered stereo set (blur, exposure, gamma, vignetting, noise, JPEG; tools/depth/layered_stereo.py).
``--left-only`` skips the right views (the MVS network reads only left images). Middlebury is never read.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from contextlib import nullcontext
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from tools.depth.layered_stereo import camera_effects
from tools.depth.scenes import (_inside_object, add_objects, dress, look_at, random_bars, random_camera, random_scene,
                                render_pinhole, render_radiance)

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


def near_objects(scene, rng, T_WC: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Up to n spheres 0.4-1.5 m in front of the walk's first camera, none closer than 0.2 m to any walk pose."""
    centres, radii = [], []
    for _ in range(n):
        r = rng.uniform(0.04, 0.3)
        c = T_WC[0, :3, 3] + T_WC[0, :3, :3] @ np.array([*rng.uniform(-0.6, 0.6, 2), rng.uniform(0.4, 1.5)])
        if np.linalg.norm(T_WC[:, :3, 3] - c, axis=1).min() > r + 0.2:
            centres.append(c)
            radii.append(r)
    return np.array(centres).reshape(-1, 3), np.array(radii)


def _dressed_scene(rng, frames: int, real_dir: str | None):
    """A room with bars, a camera walk, objects near the walk, material images; (scene, T_WC, K)."""
    from tools.depth.materials import cached_photos

    scene = random_scene(rng, n_boxes=int(rng.integers(3, 12)), n_spheres=int(rng.integers(1, 6)))
    scene = add_objects(scene, rng, *random_bars(scene, rng, int(rng.integers(0, 8))))
    T_WC = camera_walk(scene, rng, frames)
    centres, radii = near_objects(scene, rng, T_WC, int(rng.integers(0, 4)))
    scene = add_objects(scene, rng, sph_c=centres, sph_r=radii)
    scene = dress(scene, rng, cached_photos(real_dir))
    f = float(np.exp(rng.uniform(np.log(230.0), np.log(420.0))))
    K = np.array([[f, 0.0, 255.5 + rng.uniform(-8, 8)], [0.0, f, 191.5 + rng.uniform(-8, 8)], [0.0, 0.0, 1.0]])
    return scene, T_WC, K


def render_scene(args: tuple[str, int, int, str, bool, bool, str | None]) -> str:
    split, seed, frames, out, dressed, left_only, real_dir = args
    path = Path(out) / split / f"scene_{seed:05d}.npz"
    if path.exists():  # deterministic per seed: an existing scene is the same scene
        return str(path) + " (kept)"
    rng = np.random.default_rng(seed)
    if dressed:
        scene, T_WC, K = _dressed_scene(rng, frames, real_dir)
    else:
        scene = random_scene(rng, n_boxes=int(rng.integers(3, 9)), n_spheres=int(rng.integers(1, 5)))
        T_WC, K = camera_walk(scene, rng, frames), K_RECT
    T_C0C1 = np.eye(4)
    T_C0C1[0, 3] = BASELINE_M
    left, right, depth = [], [], []
    for T in T_WC:
        if dressed:
            rad0, d0 = render_radiance(scene, T, K, SIZE, supersample=2)
            rad1 = None if left_only else render_radiance(scene, T @ T_C0C1, K, SIZE, supersample=2)[0]
            img0, img1, _ = camera_effects(rng, rad0.astype(np.float32),
                                           None if rad1 is None else rad1.astype(np.float32))
        else:
            noise = rng.uniform(0.5, 3.0)
            img0, d0 = render_pinhole(scene, T, K, SIZE, supersample=1, noise_std=noise, rng=rng)
            img1 = render_pinhole(scene, T @ T_C0C1, K, SIZE, supersample=1, noise_std=noise, rng=rng)[0]
        left.append(img0)
        depth.append(d0)
        if img1 is not None:
            right.append(img1)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.npz")  # rename at the end: a killed render leaves no half file
    views = {"left": np.stack(left)} | ({"right": np.stack(right)} if right else {})
    np.savez_compressed(tmp, **views, depth=np.stack(depth), T_WC=T_WC, K=K, baseline_m=BASELINE_M)
    tmp.replace(path)
    return str(path)


def _one_thread() -> None:
    """Each render process on one core (the parallelism is the pool's)."""
    import cv2

    cv2.setNumThreads(1)


def _write_provenance(a, argv) -> None:
    """dataset.json of the set: generator, camera, and per split the seeds and the command that rendered them
    (several commands may fill one set, e.g. its validation split first)."""
    path = Path(a.out) / "dataset.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    old = json.loads(path.read_text()) if path.is_file() else {}
    command = "python -m tools.depth.make_dataset " + " ".join(argv if argv is not None else sys.argv[1:])
    scenes = old.get("scenes", {}) if isinstance(old.get("scenes"), dict) else {}
    for split, n in (("train", a.train), ("val", a.val), ("test", a.test)):
        if n or split not in scenes:
            scenes[split] = f"seeds {SPLIT_SEED0[split]}-{SPLIT_SEED0[split] + n - 1} ({command})" if n else "none"
    path.write_text(json.dumps({
        "generator": "tools/depth/scenes.py" + (" (dressed)" if a.dressed else ""), "split_seed0": SPLIT_SEED0,
        "frames": a.frames, "K": "per scene, f 230-420 px" if a.dressed else K_RECT.tolist(),
        "baseline_m": BASELINE_M, "size": SIZE, "right_views": not a.left_only, "real": a.real,
        "scenes": scenes}, indent=1))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="data/depth_train")
    p.add_argument("--train", type=int, default=30, help="training scenes")
    p.add_argument("--val", type=int, default=5, help="validation scenes (calibration split)")
    p.add_argument("--test", type=int, default=5, help="unseen test scenes")
    p.add_argument("--frames", type=int, default=12, help="frames per scene walk")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--dressed", action="store_true", help="material images, bars, near objects, varied focal "
                   "length and camera effects (the MVS network's world-like set)")
    p.add_argument("--left-only", action="store_true", help="no right views (enough for the MVS network)")
    p.add_argument("--real", default=None, help="--dressed: folder of unlabelled real images used as pictures "
                   "(the layout of $SIGMASLAM_SHARED/data/real: eth3d_two_view/, euroc_V1_01_micro/)")
    a = p.parse_args(argv)
    if (a.left_only or a.real) and not a.dressed:
        raise SystemExit("make_dataset: --left-only and --real go with --dressed")
    jobs = [(split, SPLIT_SEED0[split] + i, a.frames, a.out, a.dressed, a.left_only, a.real)
            for split, n in (("train", a.train), ("val", a.val), ("test", a.test)) for i in range(n)]
    _write_provenance(a, argv)  # first: a render stopped half way still says what it was
    t0 = time.time()
    # fresh worker processes (spawn): a forked child of a process that already ran OpenCV's thread pool can hang
    with get_context("spawn").Pool(a.workers, initializer=_one_thread) if a.workers > 1 else nullcontext() as pool:
        results = pool.imap_unordered(render_scene, jobs) if pool else map(render_scene, jobs)
        for i, path in enumerate(results):
            print(f"[{i + 1}/{len(jobs)}] {path} ({time.time() - t0:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
