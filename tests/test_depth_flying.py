"""Flying pixels (services/depth/flying.py): the ramp a network draws across a silhouette is dropped, the object and
the background on either side stay, and so do slanted surfaces: a floor seen at a grazing angle far away and a wall
seen steeply up close."""

import numpy as np

from services.depth.flying import flying_pixels

F_B = 312.0 * 0.11  # the depth service's EuRoC rig at 512 px: focal length [px] x baseline [m]


def _step(near=1.5, far=3.0, ramp_px=6, width=96):
    """A row image: an object at ``near`` on the left, the background at ``far`` on the right, the network's smooth
    ramp between them (linear in disparity over ``ramp_px``)."""
    disp = np.full(width, F_B / far)
    disp[: width // 2] = F_B / near
    ramp = np.arange(width // 2, width // 2 + ramp_px)
    disp[ramp] = np.interp(ramp, [width // 2 - 1, width // 2 + ramp_px], [F_B / near, F_B / far])
    return np.tile((F_B / disp).astype(np.float32), (24, 1)), ramp


def test_the_ramp_across_a_silhouette_is_flying_and_its_two_sides_are_not():
    d, ramp = _step()
    fly = flying_pixels(d, F_B, 2, 0.04, 0.15, 0.15)
    row = fly[12]
    assert row[ramp[1:-1]].all()  # the ramp's inner pixels
    assert not row[: ramp[0] - 2].any() and not row[ramp[-1] + 3:].any()  # the object, the background
    assert not flying_pixels(d, F_B, 0, 0.04, 0.15, 0.15).any()  # radius 0: off


def test_slanted_surfaces_and_missing_depth_are_not_flying():
    v = np.arange(200, 384, dtype=np.float64)[:, None]  # rows below the horizon (cy 192)
    floor = np.tile(1.5 * 312.0 / (v - 192.0 + 0.5), (1, 64)).astype(np.float32)  # camera 1.5 m above a floor
    far = floor > 3.0
    assert far.any() and (floor[far] < 60).all()
    assert not flying_pixels(floor, F_B, 2, 0.04, 0.15, 0.15).any()
    u = np.arange(64, dtype=np.float64)
    wall = np.tile(0.6 + 0.004 * u, (32, 1)).astype(np.float32)  # a wall receding 4 mm per pixel at 0.6-0.85 m
    assert not flying_pixels(wall, F_B, 2, 0.04, 0.15, 0.15).any()
    d, ramp = _step()
    d[:, ramp] = np.nan  # nothing measured where the ramp was
    fly = flying_pixels(d, F_B, 2, 0.04, 0.15, 0.15)
    assert not fly.any()
