"""Compact multi-view-stereo network with learned log-depth uncertainty (paper sec. IV-D, eq. 12-13).

Inputs: reference grey image (B,1,H,W); S source images (B,S,1,H,W) (S = 1..7; the cost is averaged
over the sources that see a pixel, so S may differ between training and use); pinhole intrinsics
``K`` (B,3,3) of all views [px]; ``T_src_ref`` (B,S,4,4) mapping points from the reference camera to
each source camera; a sparse prior depth map (B,H,W) [m] from landmarks, 0 or NaN where none.
Outputs: log depth (B,H,W) [log m] and its Laplacian scale sigma_log (B,H,W).

Plane sweep over ``n_planes`` depths uniform in inverse depth between ``min_depth`` and ``max_depth``,
at 1/4 resolution: source features are warped onto each plane (grid_sample) and correlated with the
reference features. The prior enters as a Gaussian bump over the planes at the prior's inverse depth
plus a mask channel. Aggregation, uncertainty decoder and convex upsampling as in the stereo network.
"""
from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from services.depth.net_blocks import SCALE, Aggregator, Encoder, SigmaHead, convex_upsample

SIGMA_LOG_MIN = 0.005


def coarse_rays(K: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """(B,3,3) full-resolution K -> (B,h*w,3) rays (z = 1) through the centres of the 1/SCALE-resolution pixels."""
    v, u = torch.meshgrid(torch.arange(h, dtype=K.dtype, device=K.device),
                          torch.arange(w, dtype=K.dtype, device=K.device), indexing="ij")
    u_full = u.reshape(-1) * SCALE + (SCALE - 1) / 2.0
    v_full = v.reshape(-1) * SCALE + (SCALE - 1) / 2.0
    x = (u_full[None] - K[:, 0, 2, None]) / K[:, 0, 0, None]
    y = (v_full[None] - K[:, 1, 2, None]) / K[:, 1, 1, None]
    return torch.stack([x, y, torch.ones_like(x)], -1)


PLANES_PER_PASS = 4  # planes warped and correlated at once (plane_sweep_cost)


def plane_sweep_cost(f_ref: torch.Tensor, f_src: torch.Tensor, K: torch.Tensor, T_src_ref: torch.Tensor,
                     depths: torch.Tensor, planes_per_pass: int = PLANES_PER_PASS) -> torch.Tensor:
    """Mean correlation over the sources that see each (plane, pixel): (B,C,h,w), (B,S,C,h,w) -> (B,D,h,w).

    Each source is warped ``planes_per_pass`` planes at a time. All 32 planes at once make two fresh (C,D,h,w)
    buffers per source (25 MB each at 512x384), and on a CPU their first touch costs more than the arithmetic:
    the sweep ran in 146-157 ms per frame that way and 84-88 ms four planes at a time (one core), the same result
    to the bit."""
    b, s, c, h, w = f_src.shape
    n_d = depths.numel()
    f_ref = f_ref.contiguous()  # channels-last features from the encoder multiply ~2x slower in the correlation
    rays = coarse_rays(K, h, w)  # (B,hw,3)
    cost = f_ref.new_zeros(b, n_d, h, w)
    count = f_ref.new_zeros(b, n_d, h, w)
    for j in range(s):  # one source view at a time, vectorised over planes and pixels
        R = T_src_ref[:, j, :3, :3].to(rays.dtype)
        t = T_src_ref[:, j, :3, 3].to(rays.dtype)
        p = torch.einsum("bij,bnj->bni", R, rays)[:, None] * depths.view(1, -1, 1, 1) + t[:, None, None, :]
        z = p[..., 2]
        zs = torch.where(z > 1e-3, z, torch.ones_like(z))
        u = (K[:, None, None, 0, 0] * p[..., 0] / zs + K[:, None, None, 0, 2] + 0.5) / SCALE - 0.5
        v = (K[:, None, None, 1, 1] * p[..., 1] / zs + K[:, None, None, 1, 2] + 0.5) / SCALE - 0.5
        grid = torch.stack([(u + 0.5) / w * 2 - 1, (v + 0.5) / h * 2 - 1], -1)  # (B,D,hw,2)
        seen = ((z > 1e-3) & (grid.abs() <= 1).all(-1)).view(b, n_d, h, w).to(cost.dtype)
        grid = grid.to(f_src.dtype)
        src = f_src[:, j].contiguous()
        corr = []
        for k in range(0, n_d, planes_per_pass):
            g = grid[:, k:k + planes_per_pass].reshape(b, -1, w, 2)
            warped = F.grid_sample(src, g, mode="bilinear", padding_mode="zeros", align_corners=False)
            corr.append((warped.view(b, c, -1, h, w) * f_ref[:, :, None]).mean(1))
        cost = cost + torch.cat(corr, 1) * seen
        count = count + seen
    return cost / count.clamp(min=1)


class MVSNet(nn.Module):
    def __init__(self, n_planes: int = 32, min_depth: float = 0.3, max_depth: float = 15.0) -> None:
        super().__init__()
        self.n_planes = n_planes
        self.min_depth, self.max_depth = min_depth, max_depth
        inv = torch.linspace(1.0 / min_depth, 1.0 / max_depth, n_planes)
        self.register_buffer("inv_depths", inv)
        self.register_buffer("plane_index", torch.arange(n_planes, dtype=torch.float32).view(1, -1, 1, 1))
        self.encoder = Encoder(16, 16)
        self.aggregator = Aggregator(2 * n_planes + 1 + 16, n_planes)
        self.sigma_head = SigmaHead()

    def prior_volume(self, prior_depth: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """(B,H,W) sparse depth -> (B,D+1,h,w): Gaussian bump (one plane wide) at the prior, and its mask."""
        d = torch.nan_to_num(prior_depth.float(), nan=0.0)
        inv = torch.where(d > 0, 1.0 / d.clamp(min=1e-3), torch.zeros_like(d))
        inv_c = F.adaptive_max_pool2d(inv[:, None], (h, w))  # nearest prior point per coarse cell
        has = (inv_c > 0).float()
        step = (self.inv_depths[0] - self.inv_depths[1]).abs()
        bump = torch.exp(-0.5 * ((inv_c - self.inv_depths.view(1, -1, 1, 1)) / step) ** 2) * has
        return torch.cat([bump, has], 1)

    def forward(self, ref: torch.Tensor, src: torch.Tensor, K: torch.Tensor, T_src_ref: torch.Tensor,
                prior_depth: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        b, s = src.shape[:2]
        if ref.shape[-1] % 16 or ref.shape[-2] % 16:
            raise ValueError(f"image size {tuple(ref.shape[-2:])} must be a multiple of 16")
        feats, ctx = self.encoder(torch.cat([ref, src.flatten(0, 1)], 0))
        h, w = feats.shape[-2:]
        return self.forward_features(feats[:b], ctx[:b], feats[b:].view(b, s, -1, h, w), K, T_src_ref,
                                     prior_depth, ref.shape[-2:])

    def forward_features(self, f_ref: torch.Tensor, ctx_ref: torch.Tensor, f_src: torch.Tensor, K: torch.Tensor,
                         T_src_ref: torch.Tensor, prior_depth: torch.Tensor | None,
                         size_hw: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
        """The network after the encoder, so that a caller can cache the features of its source views
        (``self.encoder(img)[0]`` of each keyframe)."""
        b = f_ref.shape[0]
        h, w = f_ref.shape[-2:]
        depths = 1.0 / self.inv_depths
        cost = plane_sweep_cost(f_ref, f_src, K.float(), T_src_ref.float(), depths) * 10.0
        if prior_depth is None:
            prior_depth = f_ref.new_zeros(b, *size_hw)
        prior = self.prior_volume(prior_depth, h, w)
        logits, agg, mask = self.aggregator(torch.cat([cost, prior, ctx_ref], 1))
        prob = torch.softmax(logits, 1)
        inv = (prob * self.inv_depths.view(1, -1, 1, 1)).sum(1, keepdim=True)
        log_d = -torch.log(inv)
        idx = (prob * self.plane_index).sum(1, keepdim=True)
        sigma = F.softplus(self.sigma_head(agg, prob, self.plane_index, idx)) + SIGMA_LOG_MIN
        up = convex_upsample(torch.cat([log_d, sigma], 1), mask)
        return up[:, 0], up[:, 1]
