"""Unlabelled real stereo pairs for adapting the SGBM-guided network (issue 18 item 3), never the Middlebury test.

Sources (``load_real_pairs``): ETH3D two-view folders (``image_0/<name>.png`` beside ``image_1/<name>.png``,
already rectified) and EuRoC folders (``mav0/cam0``, ``cam1``: rectified as the depth service does, 512x384).
Each pair gets SGBM's disparity (the depth service's parameters, 96 px search range, left-right checked).

The adaptation loss (:func:`proxy_loss`) uses SGBM's left-right-consistent pixels as proxy labels for the
disparity only (L1; the sigma is not trained on them, as their error is not known), plus an edge-aware
smoothness term over the whole crop, so that the network's answers in SGBM's holes stay plausible on real images.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from services.depth.net_blocks import normalise_image
from services.depth.sgbm import SgbmParams, fill_background, sgbm_disparity


def _pairs_in(folder: Path) -> list[tuple[np.ndarray, np.ndarray, str]]:
    if (folder / "image_0").is_dir():  # ETH3D two-view layout, found directly or one level down
        roots = [folder]
    else:
        roots = sorted(p.parent for p in folder.rglob("image_0") if p.is_dir())
    out = []
    for r in roots:
        for f in sorted((r / "image_0").glob("*.png")):
            g = r / "image_1" / f.name
            left, right = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE), cv2.imread(str(g), cv2.IMREAD_GRAYSCALE)
            if left is not None and right is not None and left.shape == right.shape:
                out.append((left, right, f"{r.name}/{f.stem}"))
    if not out and ((folder / "mav0").is_dir() or (folder / "cam0").is_dir()):
        out = _euroc_pairs(folder)
    return out


def _euroc_pairs(folder: Path, every: int = 5) -> list[tuple[np.ndarray, np.ndarray, str]]:
    from services.depth.config import DepthConfig
    from services.depth.pipeline import pipeline_for_rig
    from shared.camera import load_rig
    from shared.euroc_reader import EurocDataset

    cfg = DepthConfig(method="sgbm")  # the service's rectification, no network loaded
    rect = pipeline_for_rig(cfg, load_rig(folder)).rect
    ds = EurocDataset(folder)
    names = ds.camera_names
    out = []
    for t in ds.frame_stamps_ns[::every]:
        imgs = ds.load_frame(int(t))
        left, right = rect.rectify(imgs[names.index(cfg.left_camera)], imgs[names.index(cfg.right_camera)])
        out.append((left, right, f"{folder.name}/{t}"))
    return out


def load_real_pairs(folders: list[str | Path], search_px: int = 96) -> list[dict]:
    """Pairs with SGBM: dicts of 'left', 'right' (uint8), 'sgbm' (NaN holes), 'd0' (filled), 'name'."""
    pairs = []
    for folder in map(Path, folders):
        if "middlebury" in str(folder).lower():
            raise SystemExit(f"{folder}: the Middlebury scenes are the test set; never adapt on them")
        found = _pairs_in(folder)
        if not found:
            raise SystemExit(f"{folder}: no ETH3D-style (image_0/image_1) or EuRoC (mav0/cam0, cam1) pairs found")
        for left, right, name in found:
            sg = sgbm_disparity(left, right, SgbmParams(num_disparities=search_px))
            pairs.append({"left": left, "right": right, "sgbm": sg, "d0": fill_background(sg), "name": name})
    return pairs


def real_batch(pairs: list[dict], rng: np.random.Generator, batch: int, crop: tuple[int, int]):
    """(left, right (B,1,h,w), d0, matched, sgbm_label (B,h,w)) of random crops (pairs smaller than the crop are
    skipped)."""
    ch, cw = crop
    fits = [p for p in pairs if p["left"].shape[0] >= ch and p["left"].shape[1] >= cw]
    if not fits:
        raise SystemExit(f"no real pair is at least {ch}x{cw}")
    L, R, D, M, S = [], [], [], [], []
    for _ in range(batch):
        p = fits[int(rng.integers(len(fits)))]
        h, w = p["left"].shape
        y, x = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
        sl = np.s_[y:y + ch, x:x + cw]
        L.append(p["left"][sl])
        R.append(p["right"][sl])
        D.append(p["d0"][sl])
        M.append(np.isfinite(p["sgbm"][sl]))
        S.append(np.nan_to_num(p["sgbm"][sl]))
    t = lambda a: torch.from_numpy(np.ascontiguousarray(np.stack(a)))
    return t(L).float()[:, None], t(R).float()[:, None], t(D).float(), t(M), t(S).float()


def proxy_loss(u: torch.Tensor, left: torch.Tensor, label: torch.Tensor, matched: torch.Tensor,
               smooth_weight: float = 0.1) -> torch.Tensor:
    """L1 to SGBM's disparity on its matched pixels + edge-aware smoothness (|du/dx| exp(-|dI/dx|), standardised I)."""
    n = matched.sum().clamp(min=1)
    l1 = torch.where(matched, (u - label).abs(), torch.zeros_like(u)).sum() / n
    img = normalise_image(left)[:, 0]
    sx = ((u[:, :, 1:] - u[:, :, :-1]).abs() * torch.exp(-(img[:, :, 1:] - img[:, :, :-1]).abs())).mean()
    sy = ((u[:, 1:] - u[:, :-1]).abs() * torch.exp(-(img[:, 1:] - img[:, :-1]).abs())).mean()
    return l1 + smooth_weight * (sx + sy)
