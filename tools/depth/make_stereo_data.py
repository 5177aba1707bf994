"""Render the stereo training set of layered real-looking pairs (tools/depth/layered_stereo.py), with OpenCV
SGBM's disparity of every pair precomputed (the input of the SGBM-guided network, services/depth/refine_net.py).

    .venv/bin/python -m tools.depth.make_stereo_data --out data/stereo_train --train 4096 --val 256 --seed 0

Frames are written in shards of ``--shard`` frames of one size (sizes vary between shards: 256-352 x 320-512 px),
each shard a folder of .npy arrays (memory-mapped by training): ``left``, ``right`` (N,H,W) uint8; ``disparity``
(N,H,W) uint16 in 1/256 px; ``nonocc`` (N,H,W) uint8; ``sgbm`` (N,H,W) uint16 in 1/16 px, 0 = no match;
``u_max`` (N,) float32 (the frame's disparity range [px]); ``sgbm_range`` (N,) int16 (SGBM's search range: the
depth service's 96 px or the frame's range rounded up to 16, at random). A shard is a function of (seed, split,
index): existing shards are kept, a shard is written to a temporary folder and renamed when complete.
``dataset.json`` records the command, seeds, counts, sizes and the photographs used as materials.

``--rooms DIR`` adds the training scenes of a procedural room set (``tools/depth/make_dataset.py``, its ``train``
split: rectified pairs with exact left depth) as extra training shards ``rooms_NNNN`` (5 scenes each, same arrays;
disparity = f b / z, the occlusion mask by forward warping). Crops are drawn shard by shard, so rooms make up about
their share of the frames. The validation split stays layered only, so the sigma
gain is fitted on the same frames as before.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np

from tools.depth.stereo_shards import KEYS

SPLIT_SEED = {"train": 10_000, "val": 20_000}
HEIGHTS = (256, 288, 320, 352)
WIDTHS = (320, 384, 448, 512)
SERVICE_RANGE = 96


def render_shard(job: tuple[str, str, int, int, int, str | None]) -> str:
    out, split, seed, index, n, real_dir = job
    from tools.depth.layered_stereo import random_frame
    from tools.depth.materials import cached_photos

    final = Path(out) / split / f"shard_{index:04d}"
    if (final / "u_max.npy").is_file():
        return f"{final} kept"
    rng = np.random.default_rng([seed, SPLIT_SEED[split], index])
    h, w = int(rng.choice(HEIGHTS)), int(rng.choice(WIDTHS))
    photos = cached_photos(real_dir)
    arrays = {k: [] for k in KEYS}
    for _ in range(n):
        f = random_frame(rng, photos, h, w)
        _add_frame(arrays, rng, f["left"], f["right"], f["disparity"], f["nonocc"], f["u_max"])
    _write_shard(final, arrays)
    return f"{final} {n} frames {h}x{w}"


def occlusion_free(disparity: np.ndarray) -> np.ndarray:
    """Pixels of the left view that the right view sees: the left pixel x lands at x - d in the right image; it is
    occluded when a pixel of the same row with a larger disparity lands within half a pixel of it, or when it
    leaves the right image."""
    h, w = disparity.shape
    d = np.nan_to_num(disparity, nan=0.0)
    xr = np.arange(w)[None, :] - d
    col = np.rint(xr).astype(int)
    inside = (col >= 0) & (col < w)
    front = np.full((h, w), -np.inf)
    rows = np.broadcast_to(np.arange(h)[:, None], (h, w))
    np.maximum.at(front, (rows[inside], col[inside]), d[inside])
    seen = np.zeros((h, w), bool)
    seen[inside] = d[inside] >= front[rows[inside], col[inside]] - 0.5
    return seen & np.isfinite(disparity)


def room_shard(job: tuple[str, list[str], int]) -> str:
    """Procedural room scenes (make_dataset's npz files, all 512x384) as training shard ``rooms_<index>``."""
    out, scene_paths, index = job
    final = Path(out) / "train" / f"rooms_{index:04d}"
    if (final / "u_max.npy").is_file():
        return f"{final} kept"
    rng = np.random.default_rng([index, 31_000])
    arrays = {k: [] for k in KEYS}
    for scene_path in scene_paths:
        with np.load(scene_path) as z:
            s = dict(z)
        if "right" not in s:
            raise SystemExit(f"{scene_path}: no right views (rendered with --left-only)")
        fb = float(s["K"][0, 0]) * float(s["baseline_m"])
        for left, right, z in zip(s["left"], s["right"], s["depth"]):
            ok = np.isfinite(z) & (z > 0)
            disp = np.where(ok, fb / np.where(ok, z, 1.0), np.nan).astype(np.float32)
            _add_frame(arrays, rng, left, right, disp, occlusion_free(disp), float(np.nanmax(disp)))
    _write_shard(final, arrays)
    return f"{final} {len(arrays['left'])} frames from {len(scene_paths)} scenes"


def _add_frame(arrays: dict[str, list], rng: np.random.Generator, left: np.ndarray, right: np.ndarray,
               disparity: np.ndarray, nonocc: np.ndarray, u_max: float) -> None:
    """Appends one pair to a shard's arrays, encoded, with SGBM run at the service's 96 px or (at random) the frame's
    range rounded up to 16."""
    from services.depth.sgbm import SgbmParams, sgbm_disparity

    rng_sgbm = SERVICE_RANGE if rng.random() < 0.5 else int(np.ceil((u_max + 1) / 16) * 16)
    sg = sgbm_disparity(left, right, SgbmParams(num_disparities=rng_sgbm))
    arrays["left"].append(left)
    arrays["right"].append(right)
    arrays["disparity"].append(np.clip(np.rint(np.nan_to_num(disparity) * 256), 0, 65535).astype(np.uint16))
    arrays["nonocc"].append(nonocc.astype(np.uint8))
    arrays["sgbm"].append(np.where(np.isfinite(sg), np.rint(np.nan_to_num(sg) * 16), 0).astype(np.uint16))
    arrays["u_max"].append(np.float32(u_max))
    arrays["sgbm_range"].append(np.int16(rng_sgbm))


def _write_shard(final: Path, arrays: dict[str, list]) -> None:
    """Writes the arrays to a temporary folder and renames it: a killed render leaves no half shard."""
    tmp = final.with_name(final.name + f".tmp{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for k, v in arrays.items():
        np.save(tmp / f"{k}.npy", np.stack(v))
    shutil.rmtree(final, ignore_errors=True)
    tmp.rename(final)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="data/stereo_train")
    p.add_argument("--train", type=int, default=4096, help="training frames")
    p.add_argument("--val", type=int, default=256, help="validation frames (the sigma calibration)")
    p.add_argument("--shard", type=int, default=64, help="frames per shard")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--real", default=None, help="folder of real images used as photographic materials (default "
                   "$SIGMASLAM_SHARED/data/real when present; 'none': scikit-image photographs only)")
    p.add_argument("--rooms", default=None, help="also convert the train split of this procedural room set "
                   "(tools/depth/make_dataset.py, with right views) into training shards rooms_NNNN")
    a = p.parse_args(argv)
    from shared.paths import shared_dir
    from tools.depth.materials import load_photos

    real = None if a.real == "none" else (a.real or str(shared_dir() / "data" / "real"))
    if real and not Path(real).is_dir():
        print(f"[make_stereo_data] {real} not found: scikit-image photographs only", flush=True)
        real = None
    _, sources = load_photos(Path(real) if real else None)
    jobs = []
    for split, frames in (("train", a.train), ("val", a.val)):
        for i in range((frames + a.shard - 1) // a.shard):
            jobs.append((a.out, split, a.seed, i, min(a.shard, frames - i * a.shard), real))
    rooms = sorted((Path(a.rooms) / "train").glob("scene_*.npz")) if a.rooms else []
    if a.rooms and not rooms:
        raise SystemExit(f"{a.rooms}/train: no scene_*.npz (render them: python -m tools.depth.make_dataset)")
    per = max(1, a.shard // 12)  # make_dataset's walks have 12 frames: a room shard about as large as a layered one
    room_jobs = [(a.out, [str(r) for r in rooms[i:i + per]], i // per) for i in range(0, len(rooms), per)]
    t0 = time.time()
    Path(a.out).mkdir(parents=True, exist_ok=True)
    with Pool(a.workers) as pool:
        done = [pool.imap_unordered(render_shard, jobs),
                pool.imap_unordered(room_shard, room_jobs)]
        total = len(jobs) + len(room_jobs)
        for k, msg in enumerate(m for it in done for m in it):
            print(f"[make_stereo_data] {k + 1}/{total} {msg} ({time.time() - t0:.0f} s)", flush=True)
    meta = {"command": "python -m tools.depth.make_stereo_data " + " ".join(argv if argv is not None else sys.argv[1:]),
            "generator": "tools/depth/layered_stereo.py + tools/depth/materials.py", "seed": a.seed,
            "split_seed": SPLIT_SEED, "frames": {"train": a.train, "val": a.val}, "shard": a.shard,
            "heights": HEIGHTS, "widths": WIDTHS, "materials": sources,
            "rooms": {"from": a.rooms, "scenes": [r.name for r in rooms]} if rooms else None, "render_wall_s": round(time.time() - t0)}
    (Path(a.out) / "dataset.json").write_text(json.dumps(meta, indent=1))
    print(f"[make_stereo_data] done in {time.time() - t0:.0f} s: {a.out}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
