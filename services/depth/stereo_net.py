"""Compact stereo network with learned disparity uncertainty (paper sec. IV-D, eq. 8-11).

Rectified left/right grey images (B,1,H,W), H and W multiples of 16 (512x384 in the system) ->
disparity u [px] (B,H,W) and its Laplacian scale sigma_u [px] (B,H,W).

Architecture: shared :class:`Encoder` to 1/4 resolution; correlation volume over ``max_disparity/4``
candidate disparities (dot products of unit features); the volume plus left context features go through
a small 2D U-Net (:class:`Aggregator`); soft-argmin over candidates gives a coarse disparity; an
uncertainty decoder (:class:`SigmaHead`, fed with the aggregated features, the spread and the entropy
of the matching distribution) gives sigma_u; both are upsampled x4 by learned convex combinations.
"""
from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from services.depth.net_blocks import SCALE, Aggregator, Encoder, SigmaHead, convex_upsample

SIGMA_MIN_PX = 0.05


def correlation_volume(f_left: torch.Tensor, f_right: torch.Tensor, n_disp: int) -> torch.Tensor:
    """(B,C,h,w) x2 -> (B,n_disp,h,w): mean over channels of f_left(x) * f_right(x - d); 0 where x - d < 0.

    Computed per image row as one batched matrix product (every left pixel against every right pixel of its row,
    w x w) whose diagonals are the disparities: a third of the time of one product per disparity on a CPU."""
    b, c, h, w = f_left.shape
    rows = torch.bmm(f_left.permute(0, 2, 3, 1).reshape(b * h, w, c),
                     f_right.permute(0, 2, 1, 3).reshape(b * h, c, w)) / c  # (b*h, x_left, x_right)
    vol = rows.new_zeros(b * h, n_disp, w)
    for d in range(min(n_disp, w)):
        vol[:, d, d:] = torch.diagonal(rows, offset=-d, dim1=1, dim2=2)
    return vol.view(b, h, n_disp, w).permute(0, 2, 1, 3)


class StereoNet(nn.Module):
    def __init__(self, max_disparity: int = 96) -> None:
        super().__init__()
        if max_disparity % SCALE:
            raise ValueError(f"max_disparity must be a multiple of {SCALE}")
        self.max_disparity = max_disparity
        self.n_disp = max_disparity // SCALE
        self.encoder = Encoder(32, 16)
        self.aggregator = Aggregator(self.n_disp + 16, self.n_disp)
        self.sigma_head = SigmaHead()
        self.register_buffer("disp_values", torch.arange(self.n_disp, dtype=torch.float32).view(1, -1, 1, 1))

    def forward(self, left: torch.Tensor, right: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if left.shape[-1] % 16 or left.shape[-2] % 16:
            raise ValueError(f"image size {tuple(left.shape[-2:])} must be a multiple of 16")
        feats, ctx = self.encoder(torch.cat([left, right], 0))
        fl, fr = feats.chunk(2, 0)
        vol = correlation_volume(fl, fr, self.n_disp) * 10.0
        logits, agg, mask = self.aggregator(torch.cat([vol, ctx[: left.shape[0]]], 1))
        prob = torch.softmax(logits, 1)
        disp = (prob * self.disp_values).sum(1, keepdim=True)  # [coarse px]
        raw = self.sigma_head(agg, prob, self.disp_values, disp)
        sigma = F.softplus(raw) + SIGMA_MIN_PX / SCALE
        up = convex_upsample(torch.cat([disp, sigma], 1), mask) * SCALE
        return up[:, 0], up[:, 1]


def predict_disparity(net: nn.Module, left, right, device: str = "cpu", search_px: float | None = None,
                      precision: str = "float32"):
    """Disparity and sigma [px] (float32 numpy (H,W)) of a rectified uint8 pair of any size: padded at the right
    and bottom (edge pixels repeated) to multiples of 16 for the network, cropped back after. ``search_px``: the
    disparity range of the classical matching inside an SGBM-guided network (ignored by the others)."""
    import numpy as np

    h, w = left.shape
    ph, pw = -h % 16, -w % 16
    pad = lambda a: np.pad(np.asarray(a, np.float32), ((0, ph), (0, pw)), mode="edge")
    from services.depth.weights import inference

    with inference(device, precision):
        t = lambda a: torch.from_numpy(pad(a))[None, None].to(device)
        u, su = net(t(left), t(right), search_px) if hasattr(net, "refine") and search_px else net(t(left), t(right))
    return u[0, :h, :w].float().cpu().numpy(), su[0, :h, :w].float().cpu().numpy()
