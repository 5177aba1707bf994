"""Losses of eq. 8-10 and 12 against hand-computed values; their gradients against finite differences."""
import math

import numpy as np
import pytest
import torch

from services.depth.losses import gradient_terms, laplace_nll, mvs_loss, stereo_loss


def test_laplace_nll_by_hand_and_mask():
    pred = torch.tensor([[[1.0, 2.0, 5.0]]])
    sigma = torch.tensor([[[0.5, 2.0, 1.0]]])
    target = torch.tensor([[[2.0, 2.0, 0.0]]])
    valid = torch.tensor([[[True, True, False]]])
    want = ((1.0 / 0.5 + math.log(0.5)) + (0.0 + math.log(2.0))) / 2
    assert laplace_nll(pred, sigma, target, valid).item() == pytest.approx(want, rel=1e-6)


def test_laplace_nll_optimal_sigma_is_absolute_error():
    err = 0.7  # d/dsigma (e/sigma + log sigma) = 0 at sigma = e
    sig = torch.linspace(0.2, 2.0, 181)
    vals = [laplace_nll(torch.tensor([[[err]]]), s.view(1, 1, 1), torch.zeros(1, 1, 1), torch.ones(1, 1, 1, dtype=bool)).item()
            for s in sig]
    assert sig[int(np.argmin(vals))].item() == pytest.approx(err, abs=0.011)


def test_gradient_sigma_is_eq10():
    u = torch.arange(12.0).view(1, 3, 4) ** 2
    s = torch.arange(1.0, 13.0).view(1, 3, 4)
    valid = torch.ones(1, 3, 4, dtype=torch.bool)
    g, sg, g_gt, m = gradient_terms(u, s, torch.zeros_like(u), valid, -1)
    # pixel (y=1, x=1): neighbours (1,0) and (1,2)
    assert g[0, 1, 0].item() == pytest.approx(u[0, 1, 2].item() - u[0, 1, 0].item())
    assert sg[0, 1, 0].item() == pytest.approx(math.sqrt(s[0, 1, 2].item() ** 2 + s[0, 1, 0].item() ** 2))
    g, sg, _, _ = gradient_terms(u, s, torch.zeros_like(u), valid, -2)
    assert sg[0, 0, 3].item() == pytest.approx(math.sqrt(s[0, 2, 3].item() ** 2 + s[0, 0, 3].item() ** 2))
    valid[0, 1, 2] = False  # a gradient needs both neighbours valid
    _, _, _, m = gradient_terms(u, s, torch.zeros_like(u), valid, -1)
    assert not m[0, 1, 0] and m[0, 1, 1]  # x=1 uses x=0,2 (invalid); x=2 uses x=1,3


def test_stereo_loss_by_hand_on_a_tiny_map():
    u = torch.tensor([[[1.0, 2.0, 4.0]]])
    u_gt = torch.tensor([[[1.0, 1.0, 1.0]]])
    s = torch.tensor([[[1.0, 2.0, 1.0]]])
    valid = torch.ones(1, 1, 3, dtype=torch.bool)
    l_u = np.mean([0 + 0, 1 / 2 + math.log(2), 3 + 0])
    sg = math.sqrt(2.0)  # x gradient at the middle pixel: (4 - 1) - 0, sigma sqrt(1 + 1)
    l_x = 3 / sg + math.log(sg)
    assert stereo_loss(u, s, u_gt, valid).item() == pytest.approx(l_u + l_x, rel=1e-6)  # no y neighbours: 0


def test_mvs_loss_by_hand():
    d_gt = torch.tensor([[[2.0, 4.0]]])
    log_d = torch.log(torch.tensor([[[2.0, 2.0]]]))
    s = torch.tensor([[[0.1, 0.5]]])
    want = ((0 + math.log(0.1)) + (math.log(2.0) / 0.5 + math.log(0.5))) / 2
    assert mvs_loss(log_d, s, d_gt, torch.ones(1, 1, 2, dtype=torch.bool)).item() == pytest.approx(want, rel=1e-6)


def test_loss_gradients_match_finite_differences():
    torch.manual_seed(0)
    u = (torch.rand(1, 5, 6, dtype=torch.float64) * 10).requires_grad_()
    s = (torch.rand(1, 5, 6, dtype=torch.float64) + 0.5).requires_grad_()
    u_gt = torch.rand(1, 5, 6, dtype=torch.float64) * 10
    valid = torch.rand(1, 5, 6) > 0.2
    assert torch.autograd.gradcheck(lambda a, b: stereo_loss(a, b, u_gt, valid), (u, s), eps=1e-6, atol=1e-6)
    d_gt = torch.rand(1, 5, 6, dtype=torch.float64) + 0.5
    assert torch.autograd.gradcheck(lambda a, b: mvs_loss(a, b, d_gt, valid), (u / 10, s), eps=1e-6, atol=1e-6)
