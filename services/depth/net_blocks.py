"""Building blocks shared by the compact stereo and MVS networks (torch, CPU-friendly).

- :class:`Encoder`: grey image -> matching features and context features at 1/4 resolution;
- :class:`Aggregator`: a small 2D U-Net (1/4 -> 1/16 -> 1/4) over a cost volume stacked as channels,
  giving per-hypothesis logits, an uncertainty feature and RAFT-style convex upsampling weights;
- :func:`convex_upsample`: x4 upsampling of a coarse map as a learned convex combination of its 3x3
  neighbourhood (keeps edges sharp, never overshoots);
- :func:`normalise_image`: per-image standardisation of uint8 or float images;
- :func:`box_mean3`: 3x3 mean over the pixels inside the image (``avg_pool2d(x, 3, 1, 1, count_include_pad=False)``
  as two separable sums, ~4x cheaper on a CPU).
"""
from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

SCALE = 4  # networks work at 1/SCALE of the input resolution


def conv(cin: int, cout: int, stride: int = 1, dilation: int = 1, relu: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = [nn.Conv2d(cin, cout, 3, stride, padding=dilation, dilation=dilation)]
    if relu:
        layers.append(nn.LeakyReLU(0.1, inplace=True))
    return nn.Sequential(*layers)


def normalise_image(img: torch.Tensor) -> torch.Tensor:
    """(B,1,H,W) any range -> zero mean, unit std (unbiased) per image."""
    img = img.float()
    d = img - img.mean(dim=(1, 2, 3), keepdim=True)
    # the variance as a plain sum of squares: torch's std over several dims costs ~12x more on a CPU
    var = d.square().sum(dim=(1, 2, 3), keepdim=True) / max(img[0].numel() - 1, 1)
    return d / var.sqrt().clamp(min=1e-3)


def box_mean3(x: torch.Tensor) -> torch.Tensor:
    """(..., H, W) -> the mean of each pixel's 3x3 neighbourhood, counting only pixels inside the image (the border
    mean is over 6, the corner mean over 4)."""
    h, w = x.shape[-2:]
    p = F.pad(x, (1, 1, 1, 1))
    s = p[..., :, :-2] + p[..., :, 1:-1] + p[..., :, 2:]
    s = s[..., :-2, :] + s[..., 1:-1, :] + s[..., 2:, :]
    n_h = torch.full((h, 1), 3.0, dtype=x.dtype, device=x.device)
    n_w = torch.full((1, w), 3.0, dtype=x.dtype, device=x.device)
    n_h[0], n_h[-1], n_w[:, 0], n_w[:, -1] = min(h, 2), min(h, 2), min(w, 2), min(w, 2)
    return s / (n_h * n_w)


class Encoder(nn.Module):
    """(B,1,H,W) -> matching features (B,feat,H/4,W/4) (unit-normalised over channels) and context (B,ctx,H/4,W/4)."""

    def __init__(self, feat: int = 32, ctx: int = 16) -> None:
        super().__init__()
        self.body = nn.Sequential(conv(1, 16, 2), conv(16, 16), conv(16, 32, 2), conv(32, 32), conv(32, 32, dilation=2))
        self.match = nn.Conv2d(32, feat, 1)
        self.context = nn.Conv2d(32, ctx, 1)

    def forward(self, img: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.body(normalise_image(img))
        return F.normalize(self.match(x), dim=1), torch.relu(self.context(x))


class Aggregator(nn.Module):
    """Cost-volume-as-channels U-Net: (B,cin,h,w) -> logits (B,D,h,w), sigma features (B,32,h,w), upsampling mask."""

    def __init__(self, cin: int, n_hyp: int) -> None:
        super().__init__()
        self.inp = conv(cin, 32)
        self.down1 = nn.Sequential(conv(32, 48, 2), conv(48, 48))
        self.down2 = nn.Sequential(conv(48, 64, 2), conv(64, 64, dilation=2))
        self.up2 = nn.Sequential(conv(64 + 48, 48))
        self.up1_proj = nn.Conv2d(48, 32, 1)
        self.up1 = conv(32, 32)
        self.logits = nn.Conv2d(32, n_hyp, 3, padding=1)
        self.mask = nn.Conv2d(32, 9 * SCALE * SCALE, 1)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        x0 = self.inp(x)
        x1 = self.down1(x0)
        x2 = self.down2(x1)
        y1 = self.up2(torch.cat([F.interpolate(x2, size=x1.shape[-2:], mode="bilinear", align_corners=False), x1], 1))
        y0 = self.up1(x0 + F.interpolate(self.up1_proj(y1), size=x0.shape[-2:], mode="bilinear", align_corners=False))
        return self.logits(y0), y0, 0.25 * self.mask(y0)


class SigmaHead(nn.Module):
    """Uncertainty decoder: aggregated features + cost-distribution statistics -> positive sigma (coarse)."""

    def __init__(self, cin: int = 32 + 2) -> None:
        super().__init__()
        self.net = nn.Sequential(conv(cin, 32), nn.Conv2d(32, 1, 3, padding=1))

    def forward(self, feat: torch.Tensor, prob: torch.Tensor, hyp: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
        spread = torch.sqrt((prob * (hyp - mean) ** 2).sum(1, keepdim=True) + 1e-6)  # std of the hypotheses
        entropy = -(prob * torch.log(prob + 1e-8)).sum(1, keepdim=True)
        return self.net(torch.cat([feat, spread, entropy], 1))


def convex_upsample(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B,C,h,w) coarse values, (B,9*S*S,h,w) weights -> (B,C,S*h,S*w).

    Works pixel-major, (B, h*w, ...): per coarse pixel, its (C, 9) neighbour values times its (9, S*S) weights in
    one batched matrix product. This never builds the (C, 9, S*S) products of every pixel at once (14 MB at
    512x384, whose fresh pages cost more than the arithmetic: the network ran 48 -> 32 ms per frame on a CPU). The
    weights come from a convolution in channels-last memory, where each pixel's 9 x S*S are contiguous. The
    softmax is float32 whatever the weights' type (CPU autocast would run it in bfloat16, slower and coarser)."""
    b, c, h, w = x.shape
    m = torch.softmax(mask.permute(0, 2, 3, 1).float().reshape(b, h * w, 9, SCALE * SCALE), dim=2)
    nb = F.unfold(F.pad(x.float(), (1, 1, 1, 1), mode="replicate"), 3).view(b, c, 9, h * w).permute(0, 3, 1, 2)
    up = torch.matmul(nb, m)  # (b, h*w, c, S*S)
    return up.view(b, h, w, c, SCALE, SCALE).permute(0, 3, 1, 4, 2, 5).reshape(b, c, SCALE * h, SCALE * w)
