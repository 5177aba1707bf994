"""Texture atlas for synthetic scenes: one distinct, non-repeating grayscale tile per mesh patch.

Each tile mixes a randomly warped crop of a photograph bundled with scikit-image, procedural noise at
several scales and random shapes (edges and corners for feature trackers). ``style`` shifts the mix:
'photo' is dominated by photographs, 'pattern' by shapes and noise. The atlas is uint8 (255 = albedo 1),
slightly low-pass filtered against aliasing when minified.
"""
from __future__ import annotations

import functools

import cv2
import numpy as np

_PHOTOS = ("astronaut", "brick", "camera", "cat", "chelsea", "clock", "coffee", "coins", "grass", "gravel",
           "horse", "hubble_deep_field", "immunohistochemistry", "moon", "page", "retina", "rocket", "text", "cell")


@functools.lru_cache(maxsize=1)
def photographs() -> tuple[np.ndarray, ...]:
    """scikit-image's bundled photographs as float32 grayscale in [0, 1], at least 256 px on the short side."""
    import skimage.data

    out = []
    for name in _PHOTOS:
        try:
            img = getattr(skimage.data, name)()
        except Exception:  # a photo that needs a download: skip it
            continue
        img = np.asarray(img, dtype=np.float32)
        if img.ndim == 3:
            img = img[..., :3] @ np.array([0.299, 0.587, 0.114], np.float32)
        img = (img - img.min()) / max(float(np.ptp(img)), 1e-6)
        s = 256.0 / min(img.shape)
        if s > 1:
            img = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_CUBIC)
        out.append(np.clip(img, 0, 1).astype(np.float32))
    if not out:
        raise RuntimeError("no scikit-image photographs available for textures")
    return tuple(out)


def _noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Smooth value noise: a (cells x cells) random grid upsampled bicubically to size x size."""
    small = rng.standard_normal((cells + 3, cells + 3)).astype(np.float32)
    big = cv2.resize(small, (size + 3 * size // cells, size + 3 * size // cells), interpolation=cv2.INTER_CUBIC)
    o = size // cells
    return big[o:o + size, o:o + size]


def _photo_crop(rng: np.random.Generator, size: int) -> np.ndarray:
    photos = photographs()
    img = photos[rng.integers(len(photos))]
    h, w = img.shape
    angle = rng.uniform(0, 360)
    scale = rng.uniform(0.6, 2.0)
    cx, cy = rng.uniform(0.3, 0.7) * w, rng.uniform(0.3, 0.7) * h
    M = cv2.getRotationMatrix2D((cx, cy), angle, scale)
    M[:, 2] += np.array([size / 2 - cx, size / 2 - cy])
    out = cv2.warpAffine(img, M, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT101)
    return out if rng.random() < 0.5 else 1.0 - out


def _shapes(rng: np.random.Generator, size: int, n: int) -> np.ndarray:
    img = np.full((size, size), rng.uniform(0.2, 0.8), np.float32)
    for _ in range(n):
        kind = rng.integers(4)
        val = float(rng.uniform(0, 1))
        c = rng.integers(0, size, 2)
        r = int(rng.integers(size // 40 + 2, size // 4))
        if kind == 0:
            cv2.rectangle(img, tuple(int(x) for x in c), tuple(int(x) for x in c + rng.integers(-r, r, 2)), val, -1)
        elif kind == 1:
            cv2.circle(img, tuple(int(x) for x in c), r // 2 + 1, val, -1)
        elif kind == 2:
            cv2.line(img, tuple(int(x) for x in c), tuple(int(x) for x in rng.integers(0, size, 2)), val,
                     int(rng.integers(1, 6)))
        else:
            pts = (c + rng.integers(-r, r, (3, 2))).astype(np.int32)
            cv2.fillPoly(img, [pts], val)
    return img


def make_tile(rng: np.random.Generator, size: int, style: str) -> np.ndarray:
    """One (size, size) float32 tile in [0, 1]."""
    w_photo = {"photo": 0.75, "pattern": 0.25}[style]
    w_shape = 1.0 - w_photo
    tile = w_photo * _photo_crop(rng, size) + w_shape * _shapes(rng, size, int(rng.integers(8, 30)))
    for cells, amp in ((2, 0.15), (8, 0.08), (32, 0.05), (size // 4, 0.04)):
        tile += amp * _noise(rng, size, cells)
    tile = (tile - tile.mean()) / max(float(tile.std()), 1e-6)
    albedo = rng.uniform(0.35, 0.65)
    contrast = rng.uniform(0.12, 0.22)
    return np.clip(albedo + contrast * tile, 0.02, 1.0)


def make_atlas(rows: int, cols: int, tile_px: int, style: str, seed: int) -> np.ndarray:
    """Atlas (rows*tile_px, cols*tile_px) uint8 of distinct tiles (albedo 255 = 1)."""
    if style not in ("photo", "pattern"):
        raise ValueError(f"unknown texture style {style!r} ('photo' or 'pattern')")
    atlas = np.zeros((rows * tile_px, cols * tile_px), np.uint8)
    rng = np.random.default_rng(seed)
    for k in range(rows * cols):
        r, c = divmod(k, cols)
        tile = cv2.GaussianBlur(make_tile(rng, tile_px, style), (0, 0), 0.6)
        atlas[r * tile_px:(r + 1) * tile_px, c * tile_px:(c + 1) * tile_px] = np.round(tile * 255.0)
    return atlas
