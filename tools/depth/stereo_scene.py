"""Real stereo pairs with ground-truth disparity, read from Middlebury-style folders (no transport, no torch).

Two layouts are understood:

- **2001/2003** (Tsukuba, Venus, Teddy, Cones): ``imL.png``, ``imR.png``, ``groundtruth.png`` (disparity [px] =
  grey / scale, 0 = unknown), ``info.txt`` (line 1: the scale; line 2, optional: the largest disparity),
  masks ``nonocc.png``, ``all.png``, ``disc.png`` (255 = evaluated; palette PNGs are read as grey);
- **2014/2021** (and ETH3D two-view with GT): ``im0.png``, ``im1.png``, ``disp0GT.pfm`` or ``disp0.pfm`` (float
  disparity [px], inf = unknown), ``mask0nocc.png`` (255 = non-occluded, 128 = occluded, 0 = unknown).

Images are converted to 8-bit grey (the networks and SGBM match grey). Disparities are left-view, in pixels
of the stored images: the right image's pixel is at x - d.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np


class StereoSceneError(RuntimeError):
    """A folder that is not a readable Middlebury-style scene; the message names the file."""


@dataclass
class StereoScene:
    name: str
    left: np.ndarray  # (H,W) uint8 grey
    right: np.ndarray  # (H,W) uint8 grey
    disparity: np.ndarray  # (H,W) float32 [px], NaN = unknown
    masks: dict[str, np.ndarray] = field(default_factory=dict)  # name -> (H,W) bool, at least 'nonocc' and 'all'
    max_disparity: float = float("nan")  # [px], from info.txt or the ground truth


def _grey(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise StereoSceneError(f"{path}: not a readable image")
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:  # 16-bit images: keep the top byte's range
        img = cv2.convertScaleAbs(img, alpha=255.0 / max(1.0, float(img.max())))
    return img


def _mask(path: Path) -> np.ndarray:
    """Palette or grey PNG -> grey values (cv2 reads palette PNGs as their colours; the palettes are grey)."""
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise StereoSceneError(f"{path}: not a readable mask")
    return img


def read_pfm(path: Path) -> np.ndarray:
    """A PFM file (one channel, 'Pf') -> float32 (H,W), top row first."""
    with open(path, "rb") as f:
        header = f.readline().strip()
        if header != b"Pf":
            raise StereoSceneError(f"{path}: not a one-channel PFM (header {header!r})")
        w, h = (int(v) for v in f.readline().split())
        scale = float(f.readline().strip())
        data = np.fromfile(f, "<f4" if scale < 0 else ">f4", count=w * h)
    if data.size != w * h:
        raise StereoSceneError(f"{path}: truncated ({data.size} of {w * h} values)")
    return np.flipud(data.reshape(h, w)).astype(np.float32)


def _read_2003(d: Path) -> StereoScene:
    info = (d / "info.txt").read_text().split() if (d / "info.txt").is_file() else []
    if not info:
        raise StereoSceneError(f"{d / 'info.txt'}: missing (line 1 must give the disparity scale of groundtruth.png)")
    scale = float(info[0])
    raw = _mask(d / "groundtruth.png").astype(np.float32)
    disp = np.where(raw > 0, raw / scale, np.nan).astype(np.float32)
    masks = {}
    for name in ("nonocc", "all", "disc"):
        if (d / f"{name}.png").is_file():
            masks[name] = _mask(d / f"{name}.png") == 255
    masks.setdefault("all", np.isfinite(disp))
    masks.setdefault("nonocc", masks["all"])
    max_d = float(info[1]) if len(info) > 1 else float(np.nanmax(disp))
    return StereoScene(d.name, _grey(d / "imL.png"), _grey(d / "imR.png"), disp, masks, max_d)


def _read_2014(d: Path) -> StereoScene:
    gt = next((d / n for n in ("disp0GT.pfm", "disp0.pfm") if (d / n).is_file()), None)
    if gt is None:
        raise StereoSceneError(f"{d}: im0.png found but no disp0GT.pfm / disp0.pfm ground truth")
    disp = read_pfm(gt)
    disp[~np.isfinite(disp) | (disp <= 0)] = np.nan
    known = np.isfinite(disp)
    masks = {"all": known}
    if (d / "mask0nocc.png").is_file():
        masks["nonocc"] = (_mask(d / "mask0nocc.png") == 255) & known
    else:
        masks["nonocc"] = known
    return StereoScene(d.name, _grey(d / "im0.png"), _grey(d / "im1.png"), disp, masks, float(np.nanmax(disp)))


def read_stereo_scene(path: str | Path) -> StereoScene:
    """One scene folder in either layout (module docstring); StereoSceneError naming what is missing."""
    d = Path(path)
    if not d.is_dir():
        raise StereoSceneError(f"{d}: not a folder")
    if (d / "imL.png").is_file() and (d / "groundtruth.png").is_file():
        scene = _read_2003(d)
    elif (d / "im0.png").is_file():
        scene = _read_2014(d)
    else:
        raise StereoSceneError(f"{d}: neither imL.png + groundtruth.png (Middlebury 2001/2003) nor im0.png + "
                               f"disp0GT.pfm (Middlebury 2014) found")
    if scene.left.shape != scene.right.shape or scene.left.shape != scene.disparity.shape:
        raise StereoSceneError(f"{d}: image sizes differ: left {scene.left.shape}, right {scene.right.shape}, "
                               f"ground truth {scene.disparity.shape}")
    return scene


def find_scenes(paths: list[str | Path]) -> list[Path]:
    """Scene folders named directly, or the scene folders inside a folder of scenes (sorted)."""
    out: list[Path] = []
    for p in map(Path, paths):
        if (p / "imL.png").is_file() or (p / "im0.png").is_file():
            out.append(p)
        elif p.is_dir():
            inner = sorted(q for q in p.iterdir() if (q / "imL.png").is_file() or (q / "im0.png").is_file())
            if not inner:
                raise StereoSceneError(f"{p}: no stereo scene (imL.png or im0.png) in it or below it")
            out.extend(inner)
        else:
            raise StereoSceneError(f"{p}: not found")
    return out
