"""Surface materials for the layered stereo generator (tools/depth/layered_stereo.py): grey textures in [0, 1].

Sources, mixed at random per surface:

- **photographs**: the scikit-image sample photographs that ship with the package (never its Middlebury
  ``stereo_motorcycle``), and, when ``../shared/data/real`` is present, the unlabelled real ETH3D two-view images
  and real EuRoC frames used as pictures (their content only, never as stereo pairs with labels). Each use takes a
  random crop at a random scale (0.2-3x), rotation and shear, recoloured (gamma, contrast, inversion);
- **procedural**: fractal value noise, plane-wave gratings, checkers, dots, random lines, text-like glyphs,
  cells, smooth gradients, nearly uniform (textureless) paint;
- **combinations**: two materials blended through a smooth random mask or multiplied, warped by a smooth random
  displacement field, or one small patch tiled (repetitive structure, the hard case for matching).

The Middlebury test scenes are never read here.
"""
from __future__ import annotations

import functools
from pathlib import Path

import cv2
import numpy as np

SKIMAGE_PHOTOS = ("astronaut", "brick", "camera", "cat", "chelsea", "coffee", "coins", "grass", "gravel", "horse",
                  "hubble_deep_field", "immunohistochemistry", "moon", "page", "rocket", "text", "clock", "retina",
                  "cell", "colorwheel")


def _to_grey01(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY)
    img = img.astype(np.float32)
    return (img - img.min()) / max(1e-6, float(img.max() - img.min()))


def load_photos(real_dir: Path | None = None, max_real: int = 80) -> tuple[list[np.ndarray], dict]:
    """Grey photographs in [0, 1] and a record of where they came from (for the dataset's provenance)."""
    import skimage.data

    photos, names = [], []
    for n in SKIMAGE_PHOTOS:
        try:
            photos.append(_to_grey01(getattr(skimage.data, n)()))
            names.append(n)
        except Exception:  # noqa: BLE001 - images that would need a download are skipped
            continue
    real: list[str] = []
    if real_dir is not None and real_dir.is_dir():
        files = sorted((real_dir / "eth3d_two_view").rglob("*.png"))
        files += sorted((real_dir / "euroc_V1_01_micro" / "mav0").glob("cam*/data/*.png"))[::10]
        for f in files[:max_real]:
            img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if img is not None and min(img.shape) >= 64:
                photos.append(_to_grey01(img))
                real.append(str(f.relative_to(real_dir)))
    return photos, {"skimage": names, "real": real}


@functools.lru_cache(maxsize=4)
def cached_photos(real_dir: str | None) -> list[np.ndarray]:
    """``load_photos`` once per process and folder (each render worker reads them once)."""
    return load_photos(Path(real_dir) if real_dir else None)[0]


def _smooth_noise(rng, h: int, w: int, cell: float) -> np.ndarray:
    """Value noise with features of about ``cell`` px, in [0, 1]."""
    gh, gw = max(2, int(h / cell) + 2), max(2, int(w / cell) + 2)
    g = rng.random((gh, gw)).astype(np.float32)
    return cv2.resize(g, (w, h), interpolation=cv2.INTER_CUBIC).clip(0, 1)


def fractal_noise(rng, h: int, w: int) -> np.ndarray:
    out = np.zeros((h, w), np.float32)
    cell, amp, total = rng.uniform(1.5, 64.0), 1.0, 0.0
    for _ in range(int(rng.integers(2, 6))):
        out += amp * _smooth_noise(rng, h, w, cell)
        total += amp
        cell, amp = cell / 2.0, amp * rng.uniform(0.4, 0.8)
        if cell < 1.0:
            break
    return out / total


def _grating(rng, h, w):
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    out = np.zeros((h, w), np.float32)
    for _ in range(int(rng.integers(1, 4))):
        a, f = rng.uniform(0, np.pi), rng.uniform(0.05, 1.2)
        out += np.sin(f * (np.cos(a) * x + np.sin(a) * y) + rng.uniform(0, 6.3))
    return out


def _checker(rng, h, w):
    s = rng.uniform(2, 40)
    y, x = np.mgrid[0:h, 0:w]
    return (((x // s).astype(int) + (y // s).astype(int)) % 2).astype(np.float32)


def _dots(rng, h, w):
    img = np.full((h, w), rng.uniform(0, 1), np.float32)
    for _ in range(int(rng.integers(20, 400))):
        cv2.circle(img, (int(rng.integers(0, w)), int(rng.integers(0, h))), int(rng.integers(1, 12)),
                   float(rng.uniform(0, 1)), -1, cv2.LINE_AA)
    return img


def _lines(rng, h, w):
    img = np.full((h, w), rng.uniform(0, 1), np.float32)
    for _ in range(int(rng.integers(10, 120))):
        p = (int(rng.integers(-w // 2, w * 3 // 2)), int(rng.integers(-h // 2, h * 3 // 2)))
        q = (int(rng.integers(-w // 2, w * 3 // 2)), int(rng.integers(-h // 2, h * 3 // 2)))
        cv2.line(img, p, q, float(rng.uniform(0, 1)), int(rng.integers(1, 6)), cv2.LINE_AA)
    return img


def _glyphs(rng, h, w):
    img = np.full((h, w), int(rng.uniform(150, 255)), np.uint8)  # putText draws on 8-bit images only
    chars = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789#%&@"
    scale, thick = rng.uniform(0.3, 1.6), int(rng.integers(1, 3))
    step = int(max(8, 22 * scale))
    ink = int(rng.uniform(0, 100))
    for y in range(step, h + step, step):
        x = int(rng.integers(-step, step))
        while x < w:
            word = "".join(rng.choice(list(chars), int(rng.integers(1, 9))))
            cv2.putText(img, word, (x, y), int(rng.integers(0, 8)), scale, ink, thick, cv2.LINE_AA)
            x += int(len(word) * step * 0.8 + rng.integers(step // 2, 3 * step))
    return img.astype(np.float32) / 255.0


def _cells(rng, h, w):
    n = int(rng.integers(8, 200))
    pts = rng.random((n, 2)) * (w, h)
    vals = rng.random(n).astype(np.float32)
    small = 4
    y, x = np.mgrid[0:h:small, 0:w:small].astype(np.float32)
    d = (x.ravel()[:, None] - pts[:, 0]) ** 2 + (y.ravel()[:, None] - pts[:, 1]) ** 2
    lab = vals[np.argmin(d, 1)].reshape(x.shape)
    return cv2.resize(lab, (w, h), interpolation=cv2.INTER_NEAREST)


def _gradient(rng, h, w):
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    return rng.normal() * x / w + rng.normal() * y / h


def _uniform(rng, h, w):
    return np.full((h, w), rng.uniform(0, 1), np.float32) + rng.normal(0, 0.003, (h, w)).astype(np.float32)


PROCEDURAL = (fractal_noise, _grating, _checker, _dots, _lines, _glyphs, _cells, _gradient, _uniform)


def _normalise(img: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(img, (1, 99))
    return ((img - lo) / max(1e-6, hi - lo)).clip(0, 1).astype(np.float32)


def photo_patch(rng, photos: list[np.ndarray], h: int, w: int) -> np.ndarray:
    """A random crop of a photograph at a random scale, rotation and shear, filling (h, w)."""
    src = photos[int(rng.integers(len(photos)))]
    scale = float(np.exp(rng.uniform(np.log(0.2), np.log(3.0))))
    ang, shear = rng.uniform(-np.pi, np.pi), rng.uniform(-0.3, 0.3)
    c, s = np.cos(ang) * scale, np.sin(ang) * scale
    A = np.array([[c, -s + shear * scale], [s, c]], np.float32)  # output -> source pixels
    centre = np.array([rng.uniform(0, src.shape[1]), rng.uniform(0, src.shape[0])], np.float32)
    M = np.hstack([A, (centre - A @ np.array([w / 2, h / 2], np.float32))[:, None]])
    return cv2.warpAffine(src, M, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REFLECT101)


def smooth_warp(rng, img: np.ndarray) -> np.ndarray:
    h, w = img.shape
    amp, cell = rng.uniform(2, 20), rng.uniform(20, 120)
    dx = (_smooth_noise(rng, h, w, cell) - 0.5) * 2 * amp
    dy = (_smooth_noise(rng, h, w, cell) - 0.5) * 2 * amp
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    return cv2.remap(img, x + dx, y + dy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT101)


def base_material(rng, photos: list[np.ndarray], h: int, w: int) -> np.ndarray:
    if photos and rng.random() < 0.5:
        return photo_patch(rng, photos, h, w)
    return _normalise(PROCEDURAL[int(rng.integers(len(PROCEDURAL)))](rng, h, w))


def random_material(rng, photos: list[np.ndarray], h: int, w: int) -> np.ndarray:
    """A grey texture (h, w) in [0, 1]: one base material, sometimes combined, warped or tiled, then recoloured."""
    r = rng.random()
    if r < 0.08:  # textureless paint: the network must learn where it cannot match
        tex = _uniform(rng, h, w)
    elif r < 0.16:  # repetitive: a small patch tiled
        th, tw = int(rng.integers(6, 40)), int(rng.integers(6, 40))
        tile = base_material(rng, photos, th, tw)
        tex = np.tile(tile, (h // th + 1, w // tw + 1))[:h, :w]
    else:
        tex = base_material(rng, photos, h, w)
        if rng.random() < 0.3:
            other = base_material(rng, photos, h, w)
            if rng.random() < 0.5:
                m = cv2.GaussianBlur((_smooth_noise(rng, h, w, rng.uniform(10, 80)) > 0.5).astype(np.float32), (0, 0), 2)
                tex = m * tex + (1 - m) * other
            else:
                tex = _normalise(tex * (0.3 + other))
        if rng.random() < 0.3:
            tex = smooth_warp(rng, tex)
    tex = tex.clip(0, 1) ** float(np.exp(rng.uniform(-0.7, 0.7)))  # recolour: gamma
    if rng.random() < 0.2:
        tex = 1.0 - tex
    contrast = rng.uniform(0.05, 1.0) if rng.random() < 0.25 else rng.uniform(0.4, 1.0)
    mean = rng.uniform(0.15, 0.85)
    return (mean + contrast * (tex - tex.mean())).astype(np.float32)
