"""A planner on the 2D occupancy grid (services/mapping/grid.py): A* over free cells kept a robot radius away from
everything that is not free, then checked against the map itself with the segment query of the combined map.

Only free cells are traversable; occupied and unknown cells are obstacles, grown by the robot's radius (a cell is
kept when the distance from its centre to the nearest non-free cell's edge is at least the radius). Moves go to the 8
neighbours (diagonal cost sqrt(2)), with the straight-line distance as the heuristic, so the path is a shortest one
on the grid. A start or goal that is not traversable (a pose close to a wall) moves to the nearest traversable cell
within ``snap_m``. Used by ``examples/06_plan_on_grid.py`` and the demo.
"""

from __future__ import annotations

import dataclasses
import heapq

import numpy as np

from services.mapping.grid import FREE_CELL, Grid2D

_MOVES = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


@dataclasses.dataclass(frozen=True)
class Plan:
    found: bool
    path_xy: np.ndarray  # (K, 2) cell centres in W from start to goal [m] (empty when not found)
    length_m: float
    expanded: int  # cells taken off the open list
    reason: str = ""  # why not found


def traversable(grid: Grid2D, radius_m: float) -> np.ndarray:
    """Cells (H, W) bool a disc robot of ``radius_m`` may centre on: free, and its radius clear of any non-free cell."""
    from scipy.ndimage import distance_transform_edt

    free = grid.cells == FREE_CELL
    if not free.any():
        return free
    # distance in cells from each free cell's centre to the nearest non-free cell's centre; its edge is half a cell
    # nearer (the grid's border counts as non-free)
    d = distance_transform_edt(np.pad(free, 1, constant_values=False))[1:-1, 1:-1]
    return free & ((d - 0.5) * grid.resolution_m >= radius_m)


def _snap(ok: np.ndarray, rc: tuple[int, int], max_cells: int) -> tuple[int, int] | None:
    h, w = ok.shape
    r0, c0 = rc
    if 0 <= r0 < h and 0 <= c0 < w and ok[r0, c0]:
        return rc
    rr, cc = np.nonzero(ok[max(r0 - max_cells, 0): r0 + max_cells + 1, max(c0 - max_cells, 0): c0 + max_cells + 1])
    if len(rr) == 0:
        return None
    rr, cc = rr + max(r0 - max_cells, 0), cc + max(c0 - max_cells, 0)
    i = int(np.argmin((rr - r0) ** 2 + (cc - c0) ** 2))
    if (rr[i] - r0) ** 2 + (cc[i] - c0) ** 2 > max_cells**2:
        return None
    return int(rr[i]), int(cc[i])


def plan(grid: Grid2D, start_xy: np.ndarray, goal_xy: np.ndarray, radius_m: float, snap_m: float = 0.5) -> Plan:
    """A* from ``start_xy`` to ``goal_xy`` (W, [m]) for a disc robot of ``radius_m`` (module docstring)."""
    ok = traversable(grid, radius_m)
    cells = max(int(np.ceil(snap_m / grid.resolution_m)), 0)
    start = _snap(ok, tuple(grid.cell_of(start_xy)[0]), cells)
    goal = _snap(ok, tuple(grid.cell_of(goal_xy)[0]), cells)
    if start is None or goal is None:
        which = "start" if start is None else "goal"
        return Plan(False, np.zeros((0, 2)), float("nan"), 0, f"no traversable cell within {snap_m} m of the {which}")
    h, w = ok.shape
    g = np.full((h, w), np.inf)
    parent = np.full((h, w), -1, np.int64)
    g[start] = 0.0
    heur = lambda r, c: float(np.hypot(r - goal[0], c - goal[1]))  # noqa: E731
    open_list = [(heur(*start), start)]
    expanded = 0
    closed = np.zeros((h, w), bool)
    while open_list:
        _, (r, c) = heapq.heappop(open_list)
        if closed[r, c]:
            continue
        closed[r, c] = True
        expanded += 1
        if (r, c) == goal:
            break
        for dr, dc in _MOVES:
            nr, nc = r + dr, c + dc
            if 0 <= nr < h and 0 <= nc < w and ok[nr, nc] and not closed[nr, nc]:
                cost = g[r, c] + (1.4142135623730951 if dr and dc else 1.0)
                if cost < g[nr, nc]:
                    g[nr, nc], parent[nr, nc] = cost, r * w + c
                    heapq.heappush(open_list, (cost + heur(nr, nc), (nr, nc)))
    if not closed[goal]:
        return Plan(False, np.zeros((0, 2)), float("nan"), expanded, "the goal is not reachable through free cells")
    path, i = [], goal[0] * w + goal[1]
    while i >= 0:
        path.append(divmod(int(i), w))
        i = parent[path[-1]]
    rc = np.array(path[::-1], float)
    xy = grid.origin_xy_m + (rc[:, ::-1] + 0.5) * grid.resolution_m
    return Plan(True, xy, float(g[goal] * grid.resolution_m), expanded)


def path_clearance(path_xy: np.ndarray, z_band_m: np.ndarray, distance_fn, step_m: float = 0.025) -> float:
    """Smallest distance [m] from the path (points every ``step_m`` along it, at heights every ``step_m`` over the
    band) to a surface, by ``distance_fn(points (N, 3) in W) -> (N,)``: what the planner test and demo check against
    the ground-truth mesh."""
    pts = [path_xy[:1]]
    for a, b in zip(path_xy[:-1], path_xy[1:]):
        n = max(int(np.ceil(np.linalg.norm(b - a) / step_m)), 1)
        pts.append(a + np.outer(np.arange(1, n + 1) / n, b - a))
    xy = np.concatenate(pts)
    z = np.arange(z_band_m[0], z_band_m[1] + 1e-9, step_m)
    p = np.column_stack([np.repeat(xy, len(z), axis=0), np.tile(z, len(xy))])
    return float(np.min(distance_fn(p)))


def _connected_endpoints(ok: np.ndarray, rc: np.ndarray, usable: np.ndarray, xy: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray] | None:
    """Of the poses above traversable cells (``usable``, cells ``rc``), in each region of traversable cells that
    connect (8-neighbours) the first pose and the one farthest from it; the pair farthest apart (None: no region
    holds two poses)."""
    from scipy.ndimage import label

    regions, _ = label(ok, structure=np.ones((3, 3), bool))
    of = regions[rc[usable, 0], rc[usable, 1]]
    best, best_m = None, 0.0
    for r in np.unique(of):
        idx = usable[of == r]
        d = np.linalg.norm(xy[idx] - xy[idx[0]], axis=1)
        if len(idx) >= 2 and d.max() > best_m:
            best, best_m = (xy[idx[0]], xy[idx[int(np.argmax(d))]]), float(d.max())
    return best


def plan_run(run, replica=None, radius_m: float = 0.2) -> dict:
    """Plan on a run's grid (``RUN/occupancy_grid.yaml``) between two poses of its trajectory: the first that lies
    above a cell the robot fits on and the one of those farthest from it (a flying camera's poses are often above
    unknown or occupied cells); where free cells do not connect those two, the two poses farthest apart that free
    cells do connect (``straight_m`` is then below ``farthest_straight_m``). With ``replica`` the path's clearance is
    checked against the scene mesh (brought into the run's W by the trajectory's alignment, only what reaches into
    the height band). Returns what was found, as a dict."""
    from pathlib import Path

    from services.mapping.grid_files import read_grid
    from shared.euroc import read_trajectory

    run = Path(run)
    grid = read_grid(run / "occupancy_grid.yaml")
    traj = next((run / n for n in ("trajectory_final.txt", "trajectory_causal.txt", "trajectory.txt")
                 if (run / n).is_file()), run / "trajectory.txt")
    xy = read_trajectory(traj).p_WS[:, :2]
    ok = traversable(grid, radius_m)
    rc = grid.cell_of(xy)
    inside = (rc[:, 0] >= 0) & (rc[:, 0] < ok.shape[0]) & (rc[:, 1] >= 0) & (rc[:, 1] < ok.shape[1])
    usable = np.flatnonzero(inside)[ok[rc[inside, 0], rc[inside, 1]]]  # poses above cells the robot fits on
    if len(usable) >= 2:
        start = xy[usable[0]]
        goal = xy[usable[int(np.argmax(np.linalg.norm(xy[usable] - start, axis=1)))]]
    else:
        start, goal = xy[0], xy[int(np.argmax(np.linalg.norm(xy - xy[0], axis=1)))]
    farthest_m = float(np.linalg.norm(goal - start))
    connected = _connected_endpoints(ok, rc, usable, xy)
    if connected is not None and not np.array_equal(connected[1], goal):
        start, goal = connected  # the farthest pair is not connected through free cells: the farthest pair that is
    p = plan(grid, start, goal, radius_m)
    out = {"found": p.found, "reason": p.reason, "start_xy": start.tolist(), "goal_xy": goal.tolist(),
           "straight_m": float(np.linalg.norm(goal - start)), "farthest_straight_m": farthest_m,
           "length_m": p.length_m, "radius_m": radius_m,
           "expanded": p.expanded, "path_xy": p.path_xy.tolist(), "clearance_m": None, "collision_free": None}
    if replica is not None and p.found:
        from services.app.metrics.occupancy import SceneTruth
        from services.app.synth.scene import read_ply
        from shared.metrics.ate import run_alignment

        replica = Path(replica)
        T_gt_W = run_alignment(traj,
                               replica / "mav0" / "state_groundtruth_estimate0" / "data.csv")
        v, f = read_ply(replica / "mav0" / "scene" / "mesh.ply")
        truth = SceneTruth.in_band(v, f, np.linalg.inv(T_gt_W), grid.z_band_m, grid.resolution_m)
        out["clearance_m"] = path_clearance(p.path_xy, grid.z_band_m, truth.distance)
        out["collision_free"] = out["clearance_m"] >= radius_m
    return out
