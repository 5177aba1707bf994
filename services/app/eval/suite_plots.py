"""Figures of ``sigmaslam eval suite``: per sequence a trajectory figure (top view with ground truth, error over
time, causal and non-causal), and one summary bar chart of ours against the paper."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def trajectory_figure(path: Path, title: str, gt_p: np.ndarray, runs: dict[str, tuple]) -> Path:
    """``runs[label] = (AteResult, aligned estimate positions (N,3))``; ``gt_p`` (M,3) ground truth [m]."""
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.5))
    a1.plot(gt_p[:, 0], gt_p[:, 1], "k-", lw=1.5, label="ground truth")
    for label, (res, p) in runs.items():
        a1.plot(p[:, 0], p[:, 1], "-", lw=1, label=f"{label} (RMSE {res.rmse_m:.3f} m)")
        t = (res.stamps_ns - res.stamps_ns[0]) / 1e9
        a2.plot(t, res.errors_m * 100, lw=1, label=label)
    a1.set(xlabel="x [m]", ylabel="y [m]", title=f"{title}: top view (SE(3)-aligned)")
    a1.axis("equal")
    a1.legend(fontsize=8)
    a2.set(xlabel="time [s]", ylabel="position error [cm]", title="ATE per pose")
    a2.grid(alpha=0.3)
    a2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def summary_figure(path: Path, rows: dict[str, dict], paper_ate: dict, paper_mesh: dict) -> Path:
    plt = _plt()
    seqs = list(rows)
    x = np.arange(len(seqs))
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    val = lambda seq, key: rows[seq].get(key) if rows[seq].get(key) is not None else np.nan  # noqa: E731
    w = 0.2
    a1.bar(x - 1.5 * w, [val(s, "ate_causal_m") for s in seqs], w, label="ours causal (replica)")
    a1.bar(x - 0.5 * w, [val(s, "ate_noncausal_m") for s in seqs], w, label="ours non-causal (replica)")
    name = lambda key: rows[key].get("sequence", key)  # noqa: E731
    a1.bar(x + 0.5 * w, [paper_ate.get(name(s), (np.nan,) * 2)[0] for s in seqs], w, label="paper causal (real)")
    a1.bar(x + 1.5 * w, [paper_ate.get(name(s), (np.nan,) * 2)[1] for s in seqs], w, label="paper non-causal (real)")
    a1.set(xticks=x, xticklabels=seqs, ylabel="ATE RMSE [m]", title="Table I: trajectory error")
    a1.legend(fontsize=7)
    a2.bar(x - 0.2, [val(s, "accuracy_m") for s in seqs], 0.4, label="ours (replica)")
    a2.bar(x + 0.2, [paper_mesh.get(name(s), (np.nan, np.nan))[0] for s in seqs], 0.4, label="paper (real)")
    a2.set(xticks=x, xticklabels=seqs, ylabel="mesh accuracy [m]", title="Table II: mesh accuracy")
    a2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
