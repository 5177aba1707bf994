"""The stats panel: a Markdown table of every service's stages (rate, latency, budget, overruns) and drops."""

from __future__ import annotations

import math

import numpy as np

from shared.messages import ServiceStats

STALE_S = 5.0


def _num(x: float, fmt: str) -> str:
    return "–" if not math.isfinite(float(x)) else format(float(x), fmt)


def stats_markdown(latest: dict[str, tuple[ServiceStats, float]], now_s: float) -> str:
    """Table from ``service -> (latest stats, receive time [s])``; services silent for STALE_S are marked."""
    if not latest:
        return "*no stats received yet*"
    rows = ["| service | stage | rate Hz | p50 ms | p99 ms | budget ms | over | drops |",
            "|---|---|---:|---:|---:|---:|---:|---:|"]
    for name in sorted(latest):
        st, t_rx = latest[name]
        label = name + (" *(stale)*" if now_s - t_rx > STALE_S else "")
        drops = int(np.sum(st.queue_dropped)) if len(st.queue_dropped) else 0
        if not st.stage_names:
            rows.append(f"| {label} | – | – | – | – | – | – | {drops} |")
            continue
        for i, stage in enumerate(st.stage_names):
            first = i == 0
            rows.append("| {} | {} | {} | {} | {} | {} | {} | {} |".format(
                label if first else "", stage, _num(st.stage_rate_hz[i], ".1f"), _num(st.stage_p50_ms[i], ".1f"),
                _num(st.stage_p99_ms[i], ".1f"), _num(st.stage_budget_ms[i], ".0f"), int(st.stage_overruns[i]),
                drops if first else ""))
    return "\n".join(rows)
