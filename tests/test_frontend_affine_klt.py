"""Affine refinement against each track's first patch (services/frontend/affine_klt.py): against an image warped by
a known affine map and brightness change, and inside the tracker."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.frontend import affine_klt, klt


def _texture(seed: int = 0, shape=(240, 320)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, shape).astype(np.float32), (0, 0), 2.0)
    img = (img - img.min()) / (img.max() - img.min()) * 200 + 20
    return img.astype(np.uint8)


def _warped(img: np.ndarray, scale: float, angle_deg: float, shift, gain: float, offset: float):
    """``img`` scaled and turned about its centre, shifted, with a brightness change; the 2x3 map x -> M x + b."""
    h, w = img.shape
    M = cv2.getRotationMatrix2D((w / 2, h / 2), angle_deg, scale)
    M[:, 2] += shift
    out = cv2.warpAffine(img.astype(np.float32), M, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return np.clip(out * gain + offset, 0, 255).astype(np.uint8), M


def _points(img: np.ndarray, n: int = 40) -> np.ndarray:
    pts = cv2.goodFeaturesToTrack(img, n, 0.01, 12, mask=None).reshape(-1, 2)
    h, w = img.shape
    c = np.array([w / 2, h / 2])
    return pts[np.all(np.abs(pts - c) < [w / 4, h / 4], axis=1)].astype(np.float32)


def test_refine_finds_points_under_scale_rotation_and_gain():
    img = _texture()
    new, M = _warped(img, 1.25, 12.0, (3.0, -2.0), 0.7, 25.0)
    pts = _points(img)
    truth = pts @ M[:, :2].T + M[:, 2]
    tpl = affine_klt.make_templates(img, pts, 15)
    start = truth + np.random.default_rng(1).uniform(-0.8, 0.8, truth.shape)  # a KLT-like start, off by < 1 px
    got, ok = affine_klt.refine(tpl, new, start, iterations=15)
    assert len(pts) >= 10 and ok.mean() > 0.9
    err = np.linalg.norm(got[ok] - truth[ok], axis=1)
    assert np.median(err) < 0.05, err
    # the warp it found is the map's linear part
    np.testing.assert_allclose(np.median(tpl.A[ok], axis=0), M[:, :2], atol=0.02)
    # translation-only KLT from the same start, on the same images, is off by several times more
    uv, ok_klt = klt.track(img, new, pts, start, 15, 0, 15, 1e9, (img.shape[1], img.shape[0]))
    assert np.median(np.linalg.norm(uv[ok_klt] - truth[ok_klt], axis=1)) > 4 * np.median(err)


def test_refine_rejects_a_patch_that_is_not_there():
    img = _texture(0)
    other = _texture(5)  # another texture: no template fits
    pts = _points(img)
    tpl = affine_klt.make_templates(img, pts, 15)
    _, ok = affine_klt.refine(tpl, other, pts)
    assert ok.mean() < 0.2
    np.testing.assert_allclose(tpl.A[~ok], np.tile(np.eye(2), ((~ok).sum(), 1, 1)))  # failed warps left alone


def test_templates_keep_append_replace_follow_their_tracks():
    img = _texture()
    pts = _points(img)[:6]
    tpl = affine_klt.make_templates(img, pts, 11)
    tpl.set_A(np.arange(6) == 2, np.array([[[1.1, 0], [0, 1.1]]], np.float32))
    tpl.keep(np.array([False, False, True, True, True, True]))
    assert len(tpl) == 4 and tpl.A[0, 0, 0] == pytest.approx(1.1)
    tpl.append(affine_klt.make_templates(img, pts[:2], 11))
    assert len(tpl) == 6 and tpl.grad.shape == (6, 2, 121) and tpl.h_inv.shape == (6, 6, 6)
    tpl.replace(np.array([0]), affine_klt.make_templates(img, pts[5:6], 11))
    np.testing.assert_allclose(tpl.A[0], np.eye(2))
    np.testing.assert_allclose(tpl.values[0], tpl.values[3])  # pts[5] was kept at index 3
    np.testing.assert_allclose(tpl.values[4], affine_klt.make_templates(img, pts[:1], 11).values[0])


def test_templates_follow_their_tracks_through_many_drops_and_additions():
    """Tracks dropped and added over many frames (the store compacts now and then): each track's template is
    always the one made for it, in track order."""
    img = _texture()
    pts = _points(img)
    rng = np.random.default_rng(0)
    tpl = affine_klt.make_templates(img, pts[:5], 11)
    owner = list(range(5))  # track -> index of the point its template was made from
    for _ in range(60):
        keep = rng.random(len(owner)) > 0.2
        tpl.keep(keep)
        owner = [o for o, k in zip(owner, keep) if k]
        new = rng.integers(0, len(pts), int(rng.integers(0, 5)))
        tpl.append(affine_klt.make_templates(img, pts[new], 11))
        owner += new.tolist()
        assert len(tpl) == len(owner)
    assert len(owner) > 3
    np.testing.assert_allclose(tpl.values, affine_klt.make_templates(img, pts[owner], 11).values)


def test_warp_is_sane():
    A = np.array([np.eye(2), 1.4 * np.eye(2), 1.6 * np.eye(2), [[1.0, 0.0], [0.0, 0.6]],
                  cv2.getRotationMatrix2D((0, 0), 50, 1.0)[:, :2]])
    np.testing.assert_array_equal(affine_klt.warp_is_sane(A, 1.5), [True, True, False, False, True])
