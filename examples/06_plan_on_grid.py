"""06: plan a path for a ground robot on the 2D occupancy grid.

The mapping process summarises its combined map as a 2D grid over a height band above the floor (the band a ground
robot's body sweeps): free where the band is observed free, occupied where anything occupied lies in it, unknown
elsewhere. It publishes it live on ``<namespace>/map/grid`` and writes it as ``DIR/occupancy_grid.pgm`` + ``.yaml``
(the ROS map_server format, which ``nav2_map_server`` loads). ``services.app.planner`` plans on it: A* over the free
cells a disc robot of the given radius fits on (occupied and unknown cells grown by the radius). This script plans
from the first pose of a run's trajectory to the pose farthest from it, and with ``--replica`` checks the path
against the replica's exact scene: its clearance (distance to any surface within the band) must be at least the
radius::

    python -m examples.06_plan_on_grid out/demo --replica data/replicas/V1_02-vicon-a-real-s0-d25-seed0
    python -m examples.06_plan_on_grid --live --config out/run/config.yaml --start 0 0 --goal 2 1   # a running one

The grid and the planner: docs/occupancy.md.
"""

from __future__ import annotations

import argparse

import numpy as np


def _live_grid(config: str | None, timeout_s: float):
    from services.app.system_config import load_system_config
    from services.mapping.grid import Grid2D
    from shared import topics
    from shared.messages import OccupancyGrid2D
    from transport.pubsub import Subscriber
    from transport.queues import Empty
    from transport.session import open_session

    cfg = load_system_config(config, []).transport
    with open_session(cfg) as session:
        sub = Subscriber(session, topics.MAP_GRID.key_expr(cfg.namespace), OccupancyGrid2D, "latest", 1)
        try:
            msg = sub.get(timeout=timeout_s)
        except Empty:
            raise SystemExit(f"no grid on {topics.MAP_GRID.key_expr(cfg.namespace)} within {timeout_s:g} s") from None
        finally:
            sub.close()
    return Grid2D(np.array(msg.cells), msg.resolution_m, np.array(msg.origin_xy_m), np.array(msg.z_band_m),
                  float(msg.z_band_m[0]))


def main(argv: list[str] | None = None) -> dict:
    from services.app.planner import plan, plan_run

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dir", nargs="?", help="a run's output folder (occupancy_grid.yaml, trajectory files)")
    ap.add_argument("--replica", help="the replica the run played: check the path against its scene mesh")
    ap.add_argument("--radius", type=float, default=0.2, help="the robot's radius [m] (default 0.2)")
    ap.add_argument("--live", action="store_true", help="plan on the grid a running pipeline publishes")
    ap.add_argument("--config", help="the run's config.yaml, with --live")
    ap.add_argument("--start", type=float, nargs=2, metavar=("X", "Y"), help="start in W [m], with --live")
    ap.add_argument("--goal", type=float, nargs=2, metavar=("X", "Y"), help="goal in W [m], with --live")
    ap.add_argument("--timeout", type=float, default=10.0, help="wait this long for a live grid [s]")
    args = ap.parse_args(argv)
    if args.live:
        if args.start is None or args.goal is None:
            ap.error("--live needs --start and --goal")
        p = plan(_live_grid(args.config, args.timeout), np.array(args.start), np.array(args.goal), args.radius)
        got = {"found": p.found, "reason": p.reason, "length_m": p.length_m, "path_xy": p.path_xy.tolist()}
    else:
        if not args.dir:
            ap.error("give a run folder, or --live")
        got = plan_run(args.dir, args.replica, args.radius)
    if not got["found"]:
        print(f"no path: {got['reason']}")
        return got
    print(f"path of {len(got['path_xy'])} cells, {got['length_m']:.2f} m for a robot of radius {args.radius} m"
          + (f" (straight line {got['straight_m']:.2f} m)" if "straight_m" in got else ""))
    if got.get("clearance_m") is not None:
        verdict = "collision-free" if got["collision_free"] else "COLLIDES"
        print(f"against the scene mesh: clearance {got['clearance_m']:.3f} m >= {args.radius} m? {verdict}")
    return got


if __name__ == "__main__":
    main()
