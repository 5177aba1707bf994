"""Training losses of the depth networks (torch): Laplacian negative log-likelihoods of the paper.

Tensors are (B, H, W); ``valid`` is a bool mask of pixels with ground truth. Each loss is the mean over
valid pixels (the paper's sum over the training set up to a constant factor).
"""
from __future__ import annotations

import torch


def laplace_nll(pred: torch.Tensor, sigma: torch.Tensor, target: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Eq. 9 (and eq. 12 with log depths): mean of |pred - target| / sigma + log sigma over valid pixels."""
    n = valid.sum().clamp(min=1)
    term = (pred - target).abs() / sigma + torch.log(sigma)
    return torch.where(valid, term, torch.zeros_like(term)).sum() / n


def gradient_terms(u: torch.Tensor, sigma: torch.Tensor, u_gt: torch.Tensor, valid: torch.Tensor, axis: int
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Central differences along ``axis`` (-1: x, -2: y) of prediction and ground truth, their sigma by
    eq. 10 (sqrt of the sum of the neighbours' variances) and the mask of pixels whose neighbours are valid."""
    def plus(t):
        return t.narrow(axis, 2, t.shape[axis] - 2)

    def minus(t):
        return t.narrow(axis, 0, t.shape[axis] - 2)

    grad = plus(u) - minus(u)
    grad_gt = plus(u_gt) - minus(u_gt)
    sigma_grad = torch.sqrt(plus(sigma) ** 2 + minus(sigma) ** 2)
    return grad, sigma_grad, grad_gt, plus(valid) & minus(valid)


def stereo_loss(u: torch.Tensor, sigma_u: torch.Tensor, u_gt: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Eq. 8: L_u + L_grad_x + L_grad_y on disparity [px] with the propagated gradient sigma of eq. 10."""
    loss = laplace_nll(u, sigma_u, u_gt, valid)
    for axis in (-1, -2):
        if u.shape[axis] < 3:
            continue
        g, s, g_gt, m = gradient_terms(u, sigma_u, u_gt, valid, axis)
        loss = loss + laplace_nll(g, s, g_gt, m)
    return loss


def mvs_loss(log_d: torch.Tensor, sigma_log: torch.Tensor, depth_gt: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Eq. 12: Laplacian NLL of log depth."""
    log_gt = torch.log(torch.where(valid, depth_gt, torch.ones_like(depth_gt)))
    return laplace_nll(log_d, sigma_log, log_gt, valid)
