"""Budgets of the design brief (configs/budgets.yaml) and the pass/over table of ``python -m tools bench pipeline``.

:func:`check_budgets` turns a bench summary (the dict :mod:`tools.bench_pipeline` writes to bench.json) into
rows ``Check(name, measured, limit, unit, ok)``; a measurement that is missing gives ``ok=None`` ("n/a").
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from shared.config import load_yaml, param
from shared.paths import REPO_ROOT

BUDGETS_FILE = REPO_ROOT / "configs" / "budgets.yaml"


@dataclasses.dataclass(frozen=True)
class Budgets:
    """Per-stage budgets (BRIEF sec. 7)."""

    estimator_frame_ms: float = param(33.0, "frontend + backend compute per camera frame, median", "ms")
    depth_frame_ms: float = param(100.0, "depth networks + fusion per depth frame at 512x384, median", "ms")
    integrate_frame_ms: float = param(50.0, "occupancy integration per depth frame at 2.5 cm, median", "ms")
    state_latency_p99_ms: float = param(50.0, "sensor time -> causal pose published, p99", "ms")
    transport_frame_p50_ms: float = param(1.0, "786 KB image between processes, p50 (bench transport)", "ms")
    transport_frame_p99_ms: float = param(3.0, "786 KB image between processes, p99 (bench transport)", "ms")
    estimator_dropped_frames: int = param(0, "camera frames the estimator may drop at real-time rate")


def load_budgets(path: str | Path | None = None) -> Budgets:
    return load_yaml(Budgets, path or BUDGETS_FILE)


@dataclasses.dataclass(frozen=True)
class Check:
    name: str
    measured: float | None
    limit: float
    unit: str
    ok: bool | None  # None: not measured

    def row(self) -> str:
        meas = "n/a" if self.measured is None else f"{self.measured:.2f}"
        verdict = {True: "pass", False: "OVER", None: "n/a"}[self.ok]
        return f"| {self.name} | {meas} | {self.limit:g} | {self.unit} | {verdict} |"


def _get(d: dict, *path: str) -> float | None:
    for k in path:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return None if d is None or (isinstance(d, float) and math.isnan(d)) else float(d)


def _check(name: str, measured: float | None, limit: float, unit: str) -> Check:
    return Check(name, measured, float(limit), unit, None if measured is None else bool(measured <= limit))


def check_budgets(summary: dict, budgets: Budgets) -> list[Check]:
    """Rows of the pass/over table from a bench summary (see :func:`tools.bench_pipeline.summarise`)."""
    st = summary.get("stages", {})
    lat = summary.get("latency_ms", {})
    # a frame's path to its state: the frontend process's stage, tracking and the fast path (the back end's window
    # optimisation runs beside it, at keyframes; the row of its stage shows its cost)
    frame = _get(st, "frontend.track", "median_ms")
    rows = [
        _check("frontend + fast path per frame, median", frame, budgets.estimator_frame_ms, "ms"),
        _check("depth per frame, median", _get(st, "depth.depth", "median_ms"), budgets.depth_frame_ms, "ms"),
        _check("occupancy integration per frame, median", _get(st, "mapping.integrate", "median_ms"),
               budgets.integrate_frame_ms, "ms"),
        _check("sensor -> estimator/state latency, p99", _get(lat, "state", "p99"), budgets.state_latency_p99_ms, "ms"),
        _check("frames dropped by the estimator", _get(summary, "drops", "estimator_frames"),
               budgets.estimator_dropped_frames, "frames"),
    ]
    tr = summary.get("transport")  # filled only when the bench also ran the transport bench
    rows.append(_check("transport 786 KB frame, p50", _get(tr or {}, "p50_ms"), budgets.transport_frame_p50_ms, "ms"))
    rows.append(_check("transport 786 KB frame, p99", _get(tr or {}, "p99_ms"), budgets.transport_frame_p99_ms, "ms"))
    return rows


def format_table(rows: list[Check]) -> str:
    head = "| check | measured | budget | unit | verdict |\n|---|---:|---:|---|---|"
    return "\n".join([head, *(r.row() for r in rows)])
