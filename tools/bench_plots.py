"""PNG plots and the per-item series file of ``python -m tools bench pipeline``.

latency_time.png (latency per sensor frame over the run), latency_hist.png, compute_hist.png (per-item compute
time per stage) and processes.png (CPU and resident memory per service over time).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

LABELS = {"features": "frontend/frame", "state": "estimator/state", "depth": "depth/fused", "map": "map/submap",
          "state_sent": "estimator/state as sent", "state_sensor": "estimator/state from the sensor clock"}


def save_series(path: Path, series: dict) -> None:
    arrays = {}
    for k, rec in series["stages"].items():
        arrays[f"stage/{k}/end_ns"] = rec["end_ns"]
        arrays[f"stage/{k}/ms"] = rec["seconds"] * 1e3
    for k, lat in series["latency"].items():
        arrays[f"latency/{k}/stamp_ns"] = lat["stamp_ns"]
        arrays[f"latency/{k}/ms"] = lat["latency_ms"]
    for k, a in series["processes"].items():
        arrays[f"process/{k}/t_cpu_rss"] = a
    np.savez_compressed(path, **arrays)


def write_plots(out: Path, series: dict) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    lat = series["latency"]
    t0 = min((int(v["stamp_ns"].min()) for v in lat.values() if len(v["stamp_ns"])), default=0)
    fig, ax = plt.subplots(figsize=(9, 4))
    for k, v in lat.items():
        if len(v["stamp_ns"]):
            ax.plot((v["stamp_ns"] - t0) / 1e9, v["latency_ms"], ".", ms=3, label=LABELS[k])
    ax.set_yscale("log")
    ax.set(xlabel="sensor time [s]", ylabel="latency from sensor time [ms]", title="end-to-end latency")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    paths.append(_save(fig, out / "latency_time.png"))

    fig, axes = plt.subplots(1, len(lat), figsize=(4 * len(lat), 3.5))
    for ax, (k, v) in zip(np.atleast_1d(axes), lat.items()):
        if len(v["latency_ms"]):
            ax.hist(v["latency_ms"], bins=40)
        ax.set(title=LABELS[k], xlabel="latency [ms]", ylabel="messages")
    paths.append(_save(fig, out / "latency_hist.png"))

    stages = series["stages"]
    n = max(len(stages), 1)
    fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 3.2), squeeze=False)
    for ax, (k, rec) in zip(axes[0], stages.items()):
        ax.hist(rec["seconds"] * 1e3, bins=40)
        ax.set(title=k, xlabel="compute per item [ms]", ylabel="items")
    paths.append(_save(fig, out / "compute_hist.png"))

    procs = series["processes"]
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for k, a in procs.items():
        if len(a):
            a1.plot(a[:, 0], a[:, 1], label=k)
            a2.plot(a[:, 0], a[:, 2], label=k)
    a1.set(ylabel="CPU [% of one core]")
    a2.set(ylabel="RSS [MiB]", xlabel="bench time [s]")
    a1.legend(fontsize=7, ncol=4)
    a1.grid(alpha=0.3)
    a2.grid(alpha=0.3)
    paths.append(_save(fig, out / "processes.png"))
    return paths


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path
