"""The dressed multi-view training scenes (tools/depth/scenes.py ``dress``, make_dataset --dressed): material
images stuck to the surfaces (every view sees the same albedo at a 3D point), a level of detail that follows the
pixel's footprint, added bars and near objects, and the left-only set the MVS network trains on."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tools.depth import make_dataset
from tools.depth.layered_stereo import camera_effects
from tools.depth.scenes import (add_objects, dress, look_at, material_levels, random_bars, random_scene, raycast,
                                render_rays)


def _photo_free_dressed(seed: int):
    rng = np.random.default_rng(seed)
    return dress(random_scene(rng, n_boxes=4, n_spheres=2), rng, photos=[])


def test_material_is_a_function_of_the_surface_point():
    rng = np.random.default_rng(3)
    scene = dress(random_scene(rng, n_boxes=0, n_spheres=1), rng, photos=[])  # an empty room and one sphere
    p = np.array([0.3, -0.2, 0.0]) + 0.0  # a point on the floor...
    p[2] = scene.box_lo[0, 2]
    seen = []
    for origin in (np.array([-0.8, -1.0, 1.3]), np.array([0.9, -1.2, 1.1]), np.array([0.2, 0.7, 2.0])):
        t, obj, _ = raycast(scene, origin, (p - origin)[None])
        if obj[0] != 0 or not np.allclose(origin + t[0] * (p - origin), p, atol=1e-9):
            continue  # ...hidden by the sphere from here
        T = look_at(origin, p)
        ray_C = T[:3, :3].T @ (p - origin)
        img, depth = render_rays(scene, T, (ray_C / ray_C[2])[None])
        assert depth[0] == pytest.approx(ray_C[2], rel=1e-9)  # z-depth in the camera
        seen.append(img[0])
    assert len(seen) >= 2
    # every view sees the same brightness there: albedo and light do not depend on the view
    np.testing.assert_allclose(seen, seen[0], atol=1e-9)


def test_level_of_detail_blurs_far_surfaces():
    scene = _photo_free_dressed(5)
    noise = np.random.default_rng(2).random((scene.n_objects, 256, 256))  # texel-sized detail everywhere
    scene = dataclasses.replace(scene, textures=np.stack([material_levels(t) for t in noise]),
                                texel_m=np.full(scene.n_objects, 0.004))
    T = look_at(np.array([0.0, 0.0, 1.2]), np.array([5.0, 0.3, 1.0]))
    v, u = np.mgrid[0:96, 0:128]
    f = 120.0
    rays = np.stack([(u.ravel() - 64) / f, (v.ravel() - 48) / f, np.ones(u.size)], 1)
    sharp, _ = render_rays(scene, T, rays)
    filtered, depth = render_rays(scene, T, rays, pixel_rad=1.0 / f)
    assert np.isfinite(depth).all()
    # pixel-to-pixel variation (aliasing) drops where the footprint spans many texels; the mean stays
    grad = lambda img: np.abs(np.diff(img.reshape(96, 128), axis=1)).mean()
    assert grad(filtered) < 0.8 * grad(sharp)
    assert filtered.mean() == pytest.approx(sharp.mean(), abs=0.05)


def test_add_objects_keeps_the_old_ones_and_bars_are_hit():
    rng = np.random.default_rng(0)
    scene = random_scene(rng, n_boxes=3, n_spheres=2)
    lo, hi = random_bars(scene, rng, 2)
    assert (np.sort(hi - lo, axis=1)[:, :2] <= 0.06).all()  # bars are thin in two directions
    bigger = add_objects(scene, rng, lo, hi, sph_c=[[0.0, 0.0, 1.0]], sph_r=[0.2])
    assert len(bigger.box_lo) == 6 and len(bigger.sph_r) == 3 and bigger.n_objects == 9
    nb = len(scene.box_lo)
    np.testing.assert_array_equal(bigger.wave_k[:nb], scene.wave_k[:nb])  # boxes keep their textures
    np.testing.assert_array_equal(bigger.wave_k[nb + 2:nb + 4], scene.wave_k[nb:])  # and so do the spheres
    # a 2 cm pole in an empty room is hit where it stands
    room = random_scene(np.random.default_rng(1), n_boxes=0, n_spheres=0)
    pole = add_objects(room, rng, [[-0.01, -0.01, 0.2]], [[0.01, 0.01, 1.8]])
    t, obj, normal = raycast(pole, np.array([1.0, 0.0, 1.0]), np.array([[-1.0, 0.0, 0.0]]))
    assert obj[0] == 1 and t[0] == pytest.approx(0.99) and normal[0] == pytest.approx([1.0, 0.0, 0.0])
    with pytest.raises(ValueError):
        add_objects(dress(scene, rng, []), rng, lo, hi)


def test_camera_effects_on_a_single_view():
    rng = np.random.default_rng(1)
    img = np.full((20, 30), 0.5, np.float32)
    left, right, fx = camera_effects(rng, img, None)
    assert right is None and left.dtype == np.uint8 and left.shape == (20, 30)
    assert {"exposure", "gamma", "jpeg"} <= set(fx)


@pytest.mark.e2e
def test_dressed_left_only_set(tmp_path):
    assert make_dataset.main(["--out", str(tmp_path), "--dressed", "--left-only", "--train", "1", "--val", "0",
                              "--test", "0", "--frames", "2", "--workers", "1"]) == 0
    s = np.load(tmp_path / "train" / "scene_01000.npz")
    assert "right" not in s and s["left"].shape == (2, 384, 512) and s["left"].dtype == np.uint8
    assert 230 <= s["K"][0, 0] <= 420 and np.isfinite(s["depth"]).all() and (s["depth"] > 0).all()
    assert s["left"].std() > 3  # textured, not blank
    with pytest.raises(SystemExit, match="without right views"):
        from tools.depth import train

        train.main(["--net", "stereo", "--data", str(tmp_path), "--out", str(tmp_path / "w"), "--minutes", "0.01"])
    with pytest.raises(SystemExit, match="--dressed"):
        make_dataset.main(["--out", str(tmp_path / "x"), "--left-only", "--train", "1"])
