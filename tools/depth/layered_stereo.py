"""Stereo training pairs that look like the world: layered surfaces with exact disparity and occlusion.

A frame is a stack of surfaces seen by a rectified pair. Each surface has a shape in the left image (ellipse,
polygon, box with a hole, furniture-like frame with legs, thin bar or wire, noise blob), a disparity that is a
plane or a gently curved patch over the image (``u(x, y) = u0 + gx (x - cx) + gy (y - cy) + c r^2``: fronto-parallel
walls, slanted floors, curved objects), a material (tools/depth/materials.py) and its own shading (light
gradient, soft spot light, soft shadows; optionally a view-dependent highlight and a small non-Lambertian
brightness change between the views). Everything is defined in the left image's coordinates, extended to the
right by the largest disparity, so the right view is exact: the right pixel x_r sees a surface point at the left
coordinate x_l solving x_l - u(x_l, y) = x_r (fixed-point iteration; |du/dx| < 0.5 makes it contract), and the
nearest surface (largest disparity) wins in each view, so occlusions are as in a real pair.

The frame's range of disparity (its focal length times baseline over depth) is drawn per frame, log-uniform, so
that a network learns matching rather than one rig's scale; object counts, sizes, closeness to the camera and
thin structures vary too. Camera effects follow (:func:`camera_effects`): optical blur, a left/right gain and
offset difference, gamma, vignetting, shot and read noise, JPEG compression.

Output per frame: left and right uint8 grey, left-view disparity [px] (float32, every pixel), and the
non-occluded mask (the left pixel is seen in the right image).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from tools.depth.materials import _smooth_noise, random_material


@dataclass
class Surface:
    mask: np.ndarray  # (h, W_ext) float32 coverage in [0, 1] (left-image coordinates, extended to the right)
    u0: float  # disparity at (cx, cy) [px]
    gx: float  # [px/px]
    gy: float
    curv: float  # [px] at one image width from the centre
    cx: float
    cy: float
    albedo: np.ndarray  # (h, W_ext) float32 radiance before camera effects
    right_gain: float = 1.0  # non-Lambertian brightness change seen by the right camera

    def disparity(self, x: np.ndarray, y: np.ndarray, width: int) -> np.ndarray:
        r2 = ((x - self.cx) ** 2 + (y - self.cy) ** 2) / float(width * width)
        return self.u0 + self.gx * (x - self.cx) + self.gy * (y - self.cy) + self.curv * r2


def _shape_mask(rng, h: int, w: int) -> np.ndarray:
    """One surface's outline (h, w) float32 in {0, 1}, drawn at a random place and size."""
    m = np.zeros((h, w), np.uint8)
    kind = rng.choice(["ellipse", "polygon", "box", "frame", "furniture", "bar", "wire", "blob"],
                      p=[0.16, 0.18, 0.14, 0.08, 0.1, 0.14, 0.08, 0.12])
    cx, cy = rng.uniform(0, w), rng.uniform(0, h)
    size = float(np.exp(rng.uniform(np.log(0.05), np.log(0.7)))) * min(h, w)
    if kind == "ellipse":
        cv2.ellipse(m, (int(cx), int(cy)), (int(size), int(size * rng.uniform(0.3, 1.0))), rng.uniform(0, 180), 0, 360, 1, -1)
    elif kind == "polygon":
        n = int(rng.integers(3, 9))
        ang = np.sort(rng.uniform(0, 2 * np.pi, n))
        rad = size * rng.uniform(0.4, 1.0, n)
        pts = np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], 1).astype(np.int32)
        cv2.fillPoly(m, [pts], 1)
    elif kind in ("box", "frame"):
        bw, bh = size * rng.uniform(0.5, 1.5), size * rng.uniform(0.5, 1.5)
        box = cv2.boxPoints(((cx, cy), (bw, bh), rng.uniform(-20, 20) if rng.random() < 0.5 else 0.0)).astype(np.int32)
        cv2.fillPoly(m, [box], 1)
        if kind == "frame":  # a hole: the background shows through, two more occlusion boundaries
            inner = cv2.boxPoints(((cx, cy), (bw * rng.uniform(0.3, 0.8), bh * rng.uniform(0.3, 0.8)), 0.0)).astype(np.int32)
            cv2.fillPoly(m, [inner], 0)
    elif kind == "furniture":  # a top with legs (table, chair, shelf)
        top_h = max(2, int(size * rng.uniform(0.08, 0.3)))
        bw = int(size * rng.uniform(0.8, 2.0))
        x0, y0 = int(cx - bw / 2), int(cy - size / 2)
        cv2.rectangle(m, (x0, y0), (x0 + bw, y0 + top_h), 1, -1)
        leg_w = max(1, int(size * rng.uniform(0.03, 0.12)))
        for lx in np.linspace(x0, x0 + bw - leg_w, int(rng.integers(2, 5))):
            cv2.rectangle(m, (int(lx), y0 + top_h), (int(lx) + leg_w, int(y0 + size * rng.uniform(0.8, 1.6))), 1, -1)
    elif kind in ("bar", "wire"):
        thick = int(rng.integers(1, 4)) if kind == "wire" else int(rng.integers(3, 14))
        a = rng.uniform(0, np.pi)
        L = size * rng.uniform(1.5, 4.0)
        p = (int(cx - L * np.cos(a)), int(cy - L * np.sin(a)))
        q = (int(cx + L * np.cos(a)), int(cy + L * np.sin(a)))
        cv2.line(m, p, q, 1, thick, cv2.LINE_8)
    else:
        noise = _smooth_noise(rng, h, w, rng.uniform(8, 60))
        y, x = np.mgrid[0:h, 0:w]
        fall = np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * size ** 2))
        m = ((noise * fall) > rng.uniform(0.25, 0.5)).astype(np.uint8)
    return m.astype(np.float32)


def _shading(rng, h: int, w: int) -> np.ndarray:
    """Light on a surface: a gradient, a soft spot, soft shadows (multiplicative, around 1)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    s = 1.0 + rng.uniform(-0.4, 0.4) * (x / w - 0.5) + rng.uniform(-0.4, 0.4) * (y / h - 0.5)
    if rng.random() < 0.4:
        cx, cy, r = rng.uniform(0, w), rng.uniform(0, h), rng.uniform(0.1, 0.6) * w
        s += rng.uniform(0.2, 0.8) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * r * r))
    if rng.random() < 0.35:
        shadow = cv2.GaussianBlur((_smooth_noise(rng, h, w, rng.uniform(20, 120)) > 0.6).astype(np.float32), (0, 0),
                                  rng.uniform(1, 8))
        s *= 1.0 - rng.uniform(0.3, 0.7) * shadow
    return s.astype(np.float32) * rng.uniform(0.5, 1.3)


def _prefilter(albedo: np.ndarray) -> np.ndarray:
    """A slight blur before sampling, so that the right view's interpolation at fractional positions does not
    smooth it more than the left view's sampling at whole pixels."""
    return cv2.GaussianBlur(albedo, (0, 0), 0.6)


def random_surfaces(rng, photos, h: int, w: int, u_max: float) -> tuple[list[Surface], int]:
    """The surfaces of one frame, background first; returns them and the extended width they are defined on."""
    w_ext = w + int(np.ceil(u_max)) + 8
    u_min = u_max * rng.uniform(0.0, 0.25)
    surfaces = []
    # background: a wall or a floor-like slant over the whole view
    gy = rng.uniform(0.0, 0.25) * u_max / h if rng.random() < 0.5 else 0.0
    surfaces.append(Surface(np.ones((h, w_ext), np.float32), u_min + 0.1 * u_max * rng.random(),
                            rng.uniform(-0.05, 0.05) * u_max / w, gy, 0.0, w / 2, h / 2,
                            _prefilter(random_material(rng, photos, h, w_ext) * _shading(rng, h, w_ext))))
    n = int(rng.integers(3, 28))
    for _ in range(n):
        mask = _shape_mask(rng, h, w_ext)
        if mask.sum() < 20:
            continue
        ys, xs = np.nonzero(mask)
        cx, cy = float(xs.mean()), float(ys.mean())
        close = rng.random() < 0.15  # objects right in front of the camera
        u0 = u_max * (rng.uniform(0.75, 0.97) if close else rng.uniform(0.05, 0.8)) + u_min * 0.5
        slope = 0.35 if rng.random() < 0.3 else 0.08
        gx, gy = rng.uniform(-slope, slope) * u0 / w * 2, rng.uniform(-slope, slope) * u0 / h * 2
        gx = float(np.clip(gx, -0.45, 0.45))
        curv = rng.uniform(-0.3, 0.3) * u0 if rng.random() < 0.3 else 0.0
        tex = _prefilter(random_material(rng, photos, h, w_ext) * _shading(rng, h, w_ext))
        right_gain = float(rng.uniform(0.93, 1.07)) if rng.random() < 0.3 else 1.0
        surfaces.append(Surface(mask, u0, gx, gy, curv, cx, cy, tex, right_gain))
    return surfaces, w_ext


def render_pair(surfaces: list[Surface], h: int, w: int, u_max: float) -> dict[str, np.ndarray]:
    """Radiance of both views, left disparity (clipped to [0, u_max]) and the non-occluded mask."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    best_l = np.full((h, w), -np.inf, np.float32)
    left = np.zeros((h, w), np.float32)
    id_l = np.zeros((h, w), np.int32)
    best_r = np.full((h, w), -np.inf, np.float32)
    right = np.zeros((h, w), np.float32)
    id_r = np.full((h, w), -1, np.int32)
    for k, s in enumerate(surfaces):
        u = np.clip(s.disparity(x, y, w), 0.0, u_max)
        cand = np.where(s.mask[:, :w] > 0.5, u, -np.inf)
        take = cand > best_l
        best_l[take], left[take], id_l[take] = cand[take], s.albedo[:, :w][take], k
        xl = x + s.u0  # right view: x_l - u(x_l, y) = x_r, by fixed-point iteration
        for _ in range(6):
            xl = x + np.clip(s.disparity(xl, y, w), 0.0, u_max)
        ur = np.clip(s.disparity(xl, y, w), 0.0, u_max)
        m = cv2.remap(s.mask, xl, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        cand = np.where((m > 0.5) & (xl <= s.mask.shape[1] - 1), ur, -np.inf)
        take = cand > best_r
        a = cv2.remap(s.albedo, xl, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT101) * s.right_gain
        best_r[take], right[take], id_r[take] = cand[take], a[take], k
    disp = best_l
    xr = np.rint(x - disp).astype(np.int32)
    inside = xr >= 0
    seen = np.zeros((h, w), bool)
    rows = np.arange(h)[:, None].repeat(w, 1)
    seen[inside] = id_r[rows[inside], xr[inside]] == id_l[inside]
    return {"left": left, "right": right, "disparity": disp.astype(np.float32), "nonocc": seen}


def _highlight(rng, h, w, x_shift):
    """A soft specular spot that sits at a different place in the two views (view-dependent)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    cx, cy, r = rng.uniform(0, w), rng.uniform(0, h), rng.uniform(5, 40)
    amp = rng.uniform(0.2, 0.8)
    spot = lambda dx: amp * np.exp(-((x - cx - dx) ** 2 + (y - cy) ** 2) / (2 * r * r))
    return spot(0.0), spot(x_shift)


def camera_effects(rng, left: np.ndarray, right: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """Radiance pair -> uint8 grey pair through blur, exposure, gain difference, gamma, vignetting, noise, JPEG
    (right None: the left view alone, through the same draws)."""
    h, w = left.shape
    fx = {}
    if rng.random() < 0.2:
        hl, hr = _highlight(rng, h, w, rng.uniform(-15, 15))
        left, right = left + hl, (None if right is None else right + hr)
    blur = float(rng.uniform(0.0, 1.4)) if rng.random() < 0.7 else 0.0
    exposure = float(np.exp(rng.uniform(np.log(0.45), np.log(1.25))))
    gain_lr = float(np.exp(rng.uniform(-0.15, 0.15)))
    gamma = float(np.exp(rng.uniform(-0.4, 0.4)))
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    r2 = ((x - w / 2) ** 2 + (y - h / 2) ** 2) / float((w / 2) ** 2 + (h / 2) ** 2)
    vig = 1.0 - rng.uniform(0.0, 0.4) * r2
    noise = float(rng.uniform(0.0, 0.03))
    out = []
    for img, gain in ((left, 1.0), (right, gain_lr)):
        if img is None:
            out.append(None)
            continue
        b = blur * rng.uniform(0.85, 1.15)
        if b > 0.25:
            img = cv2.GaussianBlur(img, (0, 0), b)
        img = np.clip(img * exposure * gain * vig + rng.uniform(-0.03, 0.03), 0, None)
        img = np.clip(img, 0, 1) ** gamma
        img = img + rng.normal(0, 1, img.shape).astype(np.float32) * (noise * np.sqrt(img + 0.01) + 0.004)
        out.append(np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8))
    quality = int(rng.integers(35, 95)) if rng.random() < 0.3 else 0
    if quality:
        out = [None if im is None else
               cv2.imdecode(cv2.imencode(".jpg", im, [cv2.IMWRITE_JPEG_QUALITY, quality])[1], cv2.IMREAD_GRAYSCALE)
               for im in out]
    fx.update(blur=blur, exposure=exposure, gain_lr=gain_lr, gamma=gamma, noise=noise, jpeg=quality)
    return out[0], out[1], fx


def random_frame(rng, photos, h: int, w: int, u_max: float | None = None) -> dict[str, np.ndarray]:
    """One training pair: 'left', 'right' (uint8), 'disparity' [px], 'nonocc', 'u_max'."""
    u_max = float(np.exp(rng.uniform(np.log(10.0), np.log(92.0)))) if u_max is None else u_max
    surfaces, _ = random_surfaces(rng, photos, h, w, u_max)
    f = render_pair(surfaces, h, w, u_max)
    left, right, _ = camera_effects(rng, f["left"], f["right"])
    return {"left": left, "right": right, "disparity": f["disparity"], "nonocc": f["nonocc"], "u_max": u_max}
