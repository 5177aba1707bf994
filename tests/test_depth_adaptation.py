"""Adaptation on unlabelled real pairs: folders are found in the ETH3D layout, the Middlebury test set is refused,
and the proxy loss is the L1 to SGBM on its matched pixels plus an edge-aware smoothness term."""
import cv2
import numpy as np
import pytest
import torch

from tools.depth.layered_stereo import random_frame
from tools.depth.real_pairs import load_real_pairs, proxy_loss, real_batch

pytestmark = pytest.mark.unit


def test_eth3d_layout_is_read_and_middlebury_refused(tmp_path):
    f = random_frame(np.random.default_rng(1), [], 96, 128, u_max=20.0)
    for i, img in enumerate((f["left"], f["right"])):
        (tmp_path / "set" / f"image_{i}").mkdir(parents=True)
        cv2.imwrite(str(tmp_path / "set" / f"image_{i}" / "a.png"), img)
    pairs = load_real_pairs([tmp_path / "set"], search_px=32)
    assert len(pairs) == 1 and pairs[0]["name"] == "set/a"
    assert np.isfinite(pairs[0]["d0"]).all() and np.isnan(pairs[0]["sgbm"]).any()
    left, right, d0, matched, label = real_batch(pairs, np.random.default_rng(0), 2, (64, 96))
    assert left.shape == (2, 1, 64, 96) and torch.equal(label[~matched], torch.zeros_like(label[~matched]))
    with pytest.raises(SystemExit, match="test set"):
        load_real_pairs([tmp_path / "middlebury_2001_2003"])
    with pytest.raises(SystemExit, match="no ETH3D"):
        load_real_pairs([tmp_path / "set" / "image_0"])


def test_proxy_loss_by_hand():
    u = torch.tensor([[[1.0, 2.0, 4.0], [1.0, 2.0, 4.0]]])
    label = torch.tensor([[[1.5, 0.0, 4.0], [1.0, 0.0, 4.0]]])
    matched = torch.tensor([[[True, False, True], [True, False, True]]])
    flat = torch.zeros(1, 1, 2, 3)  # a uniform image: smoothness weight exp(0) = 1
    got = proxy_loss(u, flat, label, matched, smooth_weight=0.1)
    # L1 over the 4 matched pixels; x differences 1, 2 per row (mean 1.5), no y differences
    assert got.item() == pytest.approx(0.5 / 4 + 0.1 * 1.5)
