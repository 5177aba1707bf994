"""``python -m tools bench query``: 100 000 point queries of the occupancy map (``map/query``) while the pipeline
runs live, answered by the mapping process over Zenoh: the round trip the asker sees (encode, Zenoh, the snapshot
and lookup in the mapping process, the answer back, decode) and the mapping's own time per query (its ``query``
stage in stats/mapping), median and p99.

It starts ``sigmaslam run REPLICA configs/demo.yaml --out OUT`` at sensor rate (the demo's services), waits for the first grid on ``map/grid`` (the map's
extent and height band), then asks every ``--period`` seconds for the state of ``--points`` points drawn uniformly in
the grid's extent between 0.5 m below and 2.5 m above the floor, until the run ends or ``--queries`` were answered.
Writes OUT/bench_query.json. ``--saved DIR`` instead times the same questions in-process on a saved map (compute
only, no transport, no pipeline beside it).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--replica", help="replica to run (default: the bundled default replica)")
    p.add_argument("--out", default="out/bench_query", help="run folder (default out/bench_query)")
    p.add_argument("--points", type=int, default=100_000, help="points per query (default 100000)")
    p.add_argument("--queries", type=int, default=60, help="queries to time (default 60)")
    p.add_argument("--period", type=float, default=0.5, help="seconds between queries (default 0.5)")
    p.add_argument("--lockstep", action="store_true", help="run the pipeline in lockstep instead of at sensor rate (a "
                   "machine too busy for a live run still maps; the figure is then not a live one)")
    p.add_argument("--saved", metavar="DIR", help="time in-process queries of a saved map instead (no pipeline)")
    p.add_argument("--config", default="configs/demo.yaml", help="system config of the run (default configs/demo.yaml: "
                   "the demo's services, depth and mapping among them)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override of the run")


def _summary(ms: list[float]) -> dict:
    a = np.asarray(ms, float)
    return {"n": int(len(a)), "median_ms": float(np.median(a)) if len(a) else None,
            "p99_ms": float(np.percentile(a, 99)) if len(a) else None}


def _saved(folder: str, n_points: int, queries: int) -> dict:
    from services.app.occupancy_client import SavedOccupancy
    from services.mapping.grid import GridBuilder

    occ = SavedOccupancy(folder)
    g = GridBuilder().build(occ.mapper)
    rng = np.random.default_rng(0)
    ms = []
    for _ in range(queries):
        p = _draw(rng, g, n_points)
        t0 = time.perf_counter()
        occ.map.points(p)
        ms.append(1e3 * (time.perf_counter() - t0))
    return {"mode": "saved map, in-process", "map": folder, "submaps": len(occ.mapper.submaps),
            "points": n_points, "compute": _summary(ms)}


def _draw(rng, grid, n: int) -> np.ndarray:
    h, w = grid.cells.shape
    lo = np.array([grid.origin_xy_m[0], grid.origin_xy_m[1], grid.floor_z_m - 0.5])
    hi = np.array([lo[0] + w * grid.resolution_m, lo[1] + h * grid.resolution_m, grid.floor_z_m + 2.5])
    return rng.uniform(lo, hi, (n, 3))


def _live(args) -> dict:
    from services.app.occupancy_client import LiveOccupancy, QueryError
    from services.app.synth.api import ensure_default_replica
    from services.app.system_config import load_system_config
    from services.mapping.grid import Grid2D
    from shared import topics
    from shared.messages import OccupancyGrid2D, ServiceStats
    from transport.pubsub import Subscriber
    from transport.queues import Empty
    from transport.session import open_session

    out = Path(args.out).resolve()
    replica = args.replica or str(ensure_default_replica(progress=True))
    (out / "config.yaml").unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "services.app.cli", "run", replica, args.config, "--out", str(out),
           *([] if args.lockstep else ["--realtime"]), *[x for s in args.set for x in ("--set", s)]]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=os.environ.copy())
    rtt, server, answered, failed, reasons = [], [], 0, 0, {}
    try:
        while not (out / "config.yaml").is_file() and proc.poll() is None:
            time.sleep(0.2)
        cfg = load_system_config(str(out / "config.yaml"), []).transport
        with open_session(cfg) as session:
            grids = Subscriber(session, topics.MAP_GRID.key_expr(cfg.namespace), OccupancyGrid2D, "latest", 1)
            stats = Subscriber(session, f"{cfg.namespace}/stats/mapping", ServiceStats, "latest", 1)
            msg = None
            while msg is None and proc.poll() is None:
                try:
                    msg = grids.get(timeout=1.0)
                except Empty:
                    pass
            if msg is None:
                raise SystemExit("the run ended before the mapping published a grid")
            grid = Grid2D(np.array(msg.cells), msg.resolution_m, np.array(msg.origin_xy_m), np.array(msg.z_band_m),
                          float(msg.z_band_m[0]) - 0.1)
            rng = np.random.default_rng(0)
            with LiveOccupancy(cfg, timeout_s=10.0, session=session) as occ:
                while answered < args.queries and proc.poll() is None:
                    p = _draw(rng, grid, args.points)
                    t0 = time.perf_counter()
                    try:
                        occ.points(p)
                        rtt.append(1e3 * (time.perf_counter() - t0))
                        answered += 1
                    except QueryError as exc:
                        failed += 1
                        why = str(exc)[:120]
                        reasons[why] = reasons.get(why, 0) + 1
                    for s in stats.drain():
                        names = list(s.stage_names)
                        if "query" in names and np.isfinite(s.stage_p50_ms[names.index("query")]):
                            server.append(float(s.stage_p50_ms[names.index("query")]))
                    time.sleep(args.period)
            grids.close()
            stats.close()
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=120)
        except subprocess.TimeoutExpired:
            proc.kill()
    return {"mode": "sigmaslam run in lockstep" if args.lockstep else "live, sigmaslam run at sensor rate",
            "replica": replica, "points": args.points,
            "answered": answered, "failed": failed, "failures": reasons, "round_trip": _summary(rtt),
            "mapping_query_stage_p50_ms_per_stats_window": _summary(server)}


def main(args: argparse.Namespace) -> int:
    load = os.getloadavg()
    rep = _saved(args.saved, args.points, args.queries) if args.saved else _live(args)
    rep["load_before"], rep["load_after"] = list(load), list(os.getloadavg())
    if not args.saved:
        Path(args.out, "bench_query.json").write_text(json.dumps(rep, indent=1))
    print(json.dumps(rep, indent=1))
    return 0
