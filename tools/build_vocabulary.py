"""Build the ORB bag-of-words vocabulary of loop closure from rendered imagery.

    python -m tools.build_vocabulary [--out services/backend/loop/data/orb_vocabulary.npz] [--images-per-scene 60]
                                     [--seed-offset 100] [--k1 16 --k2 64]

Images are rendered by services/app/synth with the real EuRoC cam0 calibration in every scene style of
``services.app.synth.scene.SCENES`` built with seeds ``seed-offset + i`` (the evaluation replicas use seed 0, so
the training scenes have other layouts, textures and light), from random positions of the site's
ground-truth region looking in random horizontal directions. Features are those of the frontend (FAST
corners spread over a grid, ORB descriptors at them). The command, scenes, seeds and counts are stored
in the vocabulary file (``provenance``) and printed.
"""

from __future__ import annotations

import argparse
import sys
import time

import cv2
import numpy as np

from services.frontend.config import FrontendConfig
from services.frontend.detection import detect_spread
from services.backend.loop.vocabulary import DEFAULT_PATH, train


def frontend_descriptors(image: np.ndarray, cfg: FrontendConfig, orb) -> tuple[np.ndarray, np.ndarray]:
    """(uv (K,2) float32, ORB descriptors (K,32) uint8) at the corners the frontend would detect."""
    uv = detect_spread(image, np.zeros((0, 2), np.float32), cfg.max_features_per_camera, cfg.grid_cols,
                       cfg.grid_rows, cfg.min_distance_px, cfg.fast_threshold, cfg.border_px)
    kps = [cv2.KeyPoint(float(u), float(v), 31.0) for u, v in uv]
    kps, desc = orb.compute(image, kps)
    if desc is None or not kps:
        return np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8)
    return cv2.KeyPoint_convert(kps).reshape(-1, 2), desc


def look_pose(p_W: np.ndarray, yaw: float, pitch: float) -> np.ndarray:
    """T_WC of a camera (OpenCV axes) at p_W looking along yaw (about +z of W) tilted down by pitch."""
    f = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), -np.sin(pitch)])
    x = np.cross(f, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(f, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, f], axis=1)
    T[:3, 3] = p_W
    return T


def render_descriptors(scene_name: str, seed: int, n_images: int, rng: np.random.Generator) -> list[np.ndarray]:
    from shared.paths import euroc_files
    from services.app.synth.render import Renderer
    from services.app.synth.replica import load_calibration
    from services.app.synth.scene import SCENES, build_scene, site_positions

    cams = load_calibration(euroc_files("V1_02")["calib"])[0][:1]
    scene = build_scene(scene_name, seed)
    renderer = Renderer(scene, cams)
    pts = site_positions(SCENES[scene_name][0])
    cfg, orb = FrontendConfig(), cv2.ORB_create(nfeatures=1, edgeThreshold=19, patchSize=31)
    out = []
    for _ in range(n_images):
        T_WC = look_pose(pts[rng.integers(len(pts))], rng.uniform(0, 2 * np.pi), rng.uniform(-0.2, 0.5))
        img = renderer.image([T_WC], 0, float(rng.uniform(0, 100)), rng)
        out.append(frontend_descriptors(img, cfg, orb)[1])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(DEFAULT_PATH))
    ap.add_argument("--images-per-scene", type=int, default=60)
    ap.add_argument("--seed-offset", type=int, default=100, help="scene seeds (evaluation replicas use 0)")
    ap.add_argument("--k1", type=int, default=16)
    ap.add_argument("--k2", type=int, default=64)
    a = ap.parse_args(argv)
    from services.app.synth.scene import SCENES

    rng = np.random.default_rng(a.seed_offset)
    t0 = time.perf_counter()
    sets, scenes = [], []
    for i, name in enumerate(SCENES):
        seed = a.seed_offset + i
        d = render_descriptors(name, seed, a.images_per_scene, rng)
        sets += d
        scenes.append({"scene": name, "seed": seed, "images": len(d), "descriptors": int(sum(len(x) for x in d))})
        print(f"{name} seed {seed}: {len(d)} images, {scenes[-1]['descriptors']} descriptors "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    prov = {"command": "python -m tools.build_vocabulary " + " ".join(argv if argv is not None else sys.argv[1:]),
            "data": "services/app/synth renders, EuRoC cam0 calibration, random poses in the site region",
            "scenes": scenes, "k1": a.k1, "k2": a.k2, "cluster_seed": a.seed_offset,
            "features": "frontend FAST grid + ORB (31 px patch)", "built": time.strftime("%Y-%m-%d")}
    voc = train(sets, a.k1, a.k2, a.seed_offset, prov)
    voc.save(a.out)
    used = int((voc.idf > 0).sum())
    print(f"vocabulary {voc.size} words ({used} informative) from {len(sets)} images in "
          f"{time.perf_counter() - t0:.0f} s -> {a.out}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
