"""05: ask the occupancy map whether points, segments and boxes are free.

The mapping process answers three questions about its combined map, every submap placed by its current pose in the
world frame W: the state (free / occupied / unknown) and log-odds of points, the first occupied point along a
segment swept by a radius and whether it is free all the way, and whether an axis-aligned box holds anything
occupied and how much of it is unknown. ``services.app.occupancy_client`` asks them of a running pipeline over Zenoh
(``<namespace>/map/query``, ``LiveOccupancy``) or of a saved map without any process (``SavedOccupancy``); both
give the same answers, and a question the map refuses (NaN, a wrong shape, too many points) raises ``QueryError``::

    python -m examples.05_query_occupancy out/demo                          # a run's saved map (offline)
    sigmaslam run data/replicas/V1_02-vicon-a-real-s0-d25-seed0 --out out/run --realtime &
    python -m examples.05_query_occupancy --live --config out/run/config.yaml   # the running pipeline

It asks about 20 000 random points in the map's extent, the straight segment (robot radius 0.2 m) from the first
to the last pose of the run's trajectory (``DIR/trajectory.txt``; without one, across the map), and a 1 m box
around the segment's middle. How the submaps are combined: docs/occupancy.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from services.app.occupancy_client import LiveOccupancy, QueryError, SavedOccupancy

NAMES = {0: "unknown", 1: "free", 2: "occupied"}


def _ends(folder: Path | None, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from shared.euroc import read_trajectory

    traj = folder / "trajectory.txt" if folder is not None else None
    if traj is not None and traj.is_file():
        p = read_trajectory(traj).p_WS
        return p[0], p[-1]
    return lo + 0.25 * (hi - lo), lo + 0.75 * (hi - lo)


def ask(occ, lo: np.ndarray, hi: np.ndarray, start: np.ndarray, end: np.ndarray, radius_m: float) -> dict:
    """The three questions; returns what was printed."""
    p = np.random.default_rng(0).uniform(lo, hi, (20_000, 3))
    got = occ.points(p)
    shares = {NAMES[s]: float(np.mean(got.state == s)) for s in NAMES}
    print("20000 random points: " + ", ".join(f"{v:.1%} {k}" for k, v in shares.items()))
    seg = occ.segments(start[None], end[None], radius_m)
    where = (f"first occupied point {seg.hit_distance_m[0]:.2f} m along it, at {np.round(seg.hit_point_W[0], 2)}"
             if seg.hit[0] else "nothing occupied on it")
    print(f"segment {np.round(start, 2)} -> {np.round(end, 2)} (radius {radius_m} m): "
          f"{'free all the way' if seg.free[0] else 'not free'}, {where}, {seg.unknown_fraction[0]:.1%} unknown")
    mid = (start + end) / 2
    box = occ.boxes((mid - 0.5)[None], (mid + 0.5)[None])
    print(f"1 m box around {np.round(mid, 2)}: {'holds occupied space' if box.any_occupied[0] else 'nothing occupied'}"
          f" ({box.occupied_fraction[0]:.1%} occupied, {box.unknown_fraction[0]:.1%} unknown)")
    try:
        occ.points(np.array([[0.0, np.nan, 0.0]]))
    except QueryError as exc:
        print(f"a point with NaN is refused: {exc}")
    return {"points": shares, "segment_free": bool(seg.free[0]), "segment_hit": bool(seg.hit[0]),
            "hit_distance_m": float(seg.hit_distance_m[0]), "box_any_occupied": bool(box.any_occupied[0]),
            "box_unknown_fraction": float(box.unknown_fraction[0])}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dir", nargs="?", help="a run's output folder or its map/ folder (offline)")
    ap.add_argument("--live", action="store_true", help="ask the running pipeline over Zenoh instead")
    ap.add_argument("--config", help="the run's config.yaml (its Zenoh router and namespace), with --live")
    ap.add_argument("--extent", type=float, nargs=6, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                    help="box in W to sample points in [m] (default: the saved map's submap origins +- 3 m)")
    ap.add_argument("--radius", type=float, default=0.2, help="robot radius of the segment question [m]")
    args = ap.parse_args(argv)
    if args.live:
        from services.app.system_config import load_system_config

        cfg = load_system_config(args.config, [])
        lo, hi = (np.array(args.extent[:3]), np.array(args.extent[3:])) if args.extent else (np.full(3, -3.0),
                                                                                            np.full(3, 3.0))
        folder = Path(args.config).parent if args.config else None
        with LiveOccupancy(cfg.transport) as occ:
            print(f"asking {occ.key_expr}")
            return ask(occ, lo, hi, *_ends(folder, lo, hi), args.radius)
    if not args.dir:
        ap.error("give a saved map folder, or --live")
    occ = SavedOccupancy(args.dir)
    origins = np.array([sm.T_WM[:3, 3] for sm in occ.mapper.submaps]).reshape(-1, 3)
    if args.extent:
        lo, hi = np.array(args.extent[:3]), np.array(args.extent[3:])
    else:
        lo, hi = origins.min(0) - 3.0, origins.max(0) + 3.0
    print(f"saved map {args.dir}: {len(occ.mapper.submaps)} submaps")
    run = Path(args.dir).parent if Path(args.dir).name == "map" else Path(args.dir)
    return ask(occ, lo, hi, *_ends(run, lo, hi), args.radius)


if __name__ == "__main__":
    main()
