"""Tables of ``sigmaslam eval suite``: ours beside the paper's, as markdown.

The paper's numbers (paper/uncertainty-aware-vi-slam.txt, Tables I, II and V) were measured on the *real*
EuRoC sequences (Table V: MH01, RTX 3080 GPU); ours on synthetic replicas of them (rendered scenes along the
real trajectories with the real IMU), so they show the same protocol, not the same data.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.app.metrics.stages import stage_items

import math
import statistics

# Table I, ATE RMSE [m] after SE(3) alignment: sequence -> (ours causal, ours non-causal, OKVIS2 causal, OKVIS2 nc)
PAPER_ATE = {"MH_01": (0.034, 0.019, 0.034, 0.021), "MH_02": (0.031, 0.019, 0.029, 0.020),
             "MH_03": (0.037, 0.029, 0.039, 0.032), "MH_04": (0.072, 0.071, 0.065, 0.059),
             "MH_05": (0.081, 0.066, 0.087, 0.061), "V1_01": (0.035, 0.035, 0.037, 0.035),
             "V1_02": (0.028, 0.014, 0.031, 0.014), "V1_03": (0.029, 0.021, 0.035, 0.020),
             "V2_01": (0.033, 0.024, 0.039, 0.023), "V2_02": (0.028, 0.016, 0.030, 0.019),
             "V2_03": (0.041, 0.022, 0.041, 0.027)}
# Table I, ORB-SLAM3 (stereo-inertial, non-causal; the paper quotes its paper's figures)
PAPER_ORB3 = {"MH_01": 0.036, "MH_02": 0.033, "MH_03": 0.035, "MH_04": 0.051, "MH_05": 0.082, "V1_01": 0.038,
              "V1_02": 0.014, "V1_03": 0.024, "V2_01": 0.032, "V2_02": 0.014, "V2_03": 0.024}
# Table II, "Ours": mesh accuracy [m] (no threshold) and completeness [%] (0.2 m); only the Vicon rooms have GT clouds
PAPER_MESH = {"V1_01": (0.042, 44.28), "V1_02": (0.041, 58.38), "V1_03": (0.048, 68.48),
              "V2_01": (0.072, 43.64), "V2_02": (0.069, 57.66), "V2_03": (0.072, 59.96)}
# Table V, "Ours", mean +- sigma [ms] (EuRoC MH01, GPU)
PAPER_TIMING = {"VI optimisation (per frame)": (34.3, 6.6), "occupancy update (per depth frame)": (11.6, 3.6),
                "stereo network": (56.3, 24.1), "MVS network": (75.9, 9.7)}

NOTE = ("Paper columns: measured by the paper's authors on the real EuRoC sequences (Table V on MH01 with an "
        "RTX 3080 GPU). Ours: synthetic replicas of those sequences (real trajectory and IMU, rendered scene) on "
        "this shared 2-core CPU machine; same protocol, different data.")


def _m(v: float | None, fmt: str = ".3f") -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, fmt)


# the paper's averages over its eleven sequences (causal, non-causal) and issue 23's target: at most 0.8x of them
PAPER_MEAN = tuple(float(sum(v[k] for v in PAPER_ATE.values()) / len(PAPER_ATE)) for k in (0, 1))
TARGET_MEAN_FACTOR = 0.8


def _mean(values) -> float | None:
    v = [x for x in values if x is not None and not (isinstance(x, float) and math.isnan(x))]
    return sum(v) / len(v) if v else None


def ate_table(rows: dict[str, dict]) -> str:
    """Table I: ``rows[key]`` with 'ate_causal_m', 'ate_noncausal_m' (None when absent), 'poses' and 'sequence'
    (the EuRoC name the paper's columns are looked up by; default the key). Ends with the mean of the rows of each
    mode beside the paper's mean over the same sequences and its eleven-sequence mean x 0.8 (the target)."""
    out = ["| sequence | ours causal | ours non-causal | poses | paper ours causal | paper ours non-causal | "
           "paper OKVIS2 causal | paper OKVIS2 non-causal | paper ORB-SLAM3 non-causal |",
           "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    paper_of = lambda key, r: (*PAPER_ATE.get(r.get("sequence", key), (None,) * 4),  # noqa: E731
                               PAPER_ORB3.get(r.get("sequence", key)))
    for key, r in rows.items():
        p = paper_of(key, r)
        out.append(f"| {key} | {_m(r.get('ate_causal_m'))} | {_m(r.get('ate_noncausal_m'))} | {r.get('poses', '-')} | "
                   + " | ".join(_m(v) for v in p) + " |")
    for mode in dict.fromkeys(r.get("mode", "") for r in rows.values()):
        group = [(k, r) for k, r in rows.items() if r.get("mode", "") == mode]
        if len(group) < 2:
            continue
        paper = [paper_of(k, r) for k, r in group]
        out.append(f"| **mean of {len(group)}**{' ' + mode if mode else ''} | "
                   f"{_m(_mean(r.get('ate_causal_m') for _, r in group))} | "
                   f"{_m(_mean(r.get('ate_noncausal_m') for _, r in group))} | - | "
                   + " | ".join(_m(_mean(p[i] for p in paper)) for i in range(5)) + " |")
    out.append(f"| target: 0.8 x the paper's mean of 11 | {_m(TARGET_MEAN_FACTOR * PAPER_MEAN[0])} | "
               f"{_m(TARGET_MEAN_FACTOR * PAPER_MEAN[1])} | - | {_m(PAPER_MEAN[0])} | {_m(PAPER_MEAN[1])} | - | - | - |")
    return "\n".join(out)


def segment_table(rows: dict[str, dict]) -> str:
    """First 10 s and fastest 10 s of each row (keys 'first10_causal_m', 'fastest10_causal_m', ... as written by
    tools/eval/suite.evaluate_sequence), with their ratio to the row's RMSE."""
    def cell(r, stretch, kind):
        v, whole = r.get(f"{stretch}_{kind}_m"), r.get(f"ate_{kind}_m")
        if v is None or whole is None or not whole:
            return "-"
        return f"{v:.3f} ({v / whole:.1f}x)"

    out = ["| sequence | first 10 s causal | first 10 s non-causal | fastest 10 s: start [s], mean rate [deg/s] | "
           "fastest 10 s causal | fastest 10 s non-causal |", "|---|---:|---:|---:|---:|---:|"]
    for key, r in rows.items():
        where = "-" if r.get("fastest10_start_s") is None else \
            f"{r['fastest10_start_s']:.0f}, {r['fastest10_deg_s']:.0f}"
        out.append(f"| {key} | {cell(r, 'first10', 'causal')} | {cell(r, 'first10', 'noncausal')} | {where} | "
                   f"{cell(r, 'fastest10', 'causal')} | {cell(r, 'fastest10', 'noncausal')} |")
    return "\n".join(out)


def spread_table(rows: dict[str, dict]) -> str:
    """Per row of several runs ('runs': start offset -> its 'ate_causal_m', 'ate_noncausal_m', as written by
    tools/eval/suite.median_row): min / median / max of each over the runs that have it, and the run count."""
    def cell(runs, key):
        v = [r[key] for r in runs.values() if r.get(key) is not None]
        return "-" if not v else f"{min(v):.3f} / {statistics.median(v):.3f} / {max(v):.3f}"

    out = ["| sequence | runs | causal min / median / max | non-causal min / median / max |", "|---|---:|---:|---:|"]
    for key, r in rows.items():
        runs = r.get("runs", {})
        out.append(f"| {key} | {len(runs)} | {cell(runs, 'ate_causal_m')} | {cell(runs, 'ate_noncausal_m')} |")
    return "\n".join(out)


def mesh_table(rows: dict[str, dict]) -> str:
    """Table II: ``rows[seq]`` with 'accuracy_m' and 'completeness' (fraction) or None."""
    out = ["| sequence | ours accuracy [m] | ours completeness [%] | paper accuracy [m] | paper completeness [%] |",
           "|---|---:|---:|---:|---:|"]
    for seq, r in rows.items():
        acc, comp = r.get("accuracy_m"), r.get("completeness")
        pa, pc = PAPER_MESH.get(seq, (None, None))
        out.append(f"| {seq} | {_m(acc)} | {_m(None if comp is None else 100 * comp, '.2f')} | {_m(pa)} | "
                   f"{_m(pc, '.2f')} |")
    return "\n".join(out)


def timing_table(timing: dict[str, tuple[float, float, int] | None]) -> str:
    """Table V: ``timing[row] = (mean_ms, std_ms, items)`` of ours; rows named as in :data:`PAPER_TIMING` where
    they correspond (others get '-' for the paper)."""
    out = ["| stage | ours mean +- sigma [ms] | items | paper mean +- sigma [ms] |", "|---|---:|---:|---:|"]
    for name, v in timing.items():
        ours = "-" if v is None else f"{v[0]:.1f} +- {v[1]:.1f}"
        n = "-" if v is None else str(v[2])
        p = PAPER_TIMING.get(name)
        out.append(f"| {name} | {ours} | {n} | {'-' if p is None else f'{p[0]:.1f} +- {p[1]:.1f}'} |")
    return "\n".join(out)


def hilti_table(rows: dict[str, dict]) -> str:
    out = ["| sequence | score causal | score non-causal | control points |", "|---|---:|---:|---:|"]
    for seq, r in rows.items():
        out.append(f"| {seq} | {_m(r.get('hilti_causal'), '.2f')} | {_m(r.get('hilti_noncausal'), '.2f')} | "
                   f"{r.get('hilti_points', '-')} |")
    return "\n".join(out)


def mean_std(values_ms) -> tuple[float, float, int] | None:
    import numpy as np

    v = np.asarray(values_ms, float)
    v = v[np.isfinite(v)]
    return None if len(v) == 0 else (float(v.mean()), float(v.std()), int(len(v)))


def live_table(rows: dict[str, dict]) -> str:
    """Real-time figures of the live rows (keys of tools/eval/suite.LIVE_KEYS; rows without them are skipped)."""
    out = ["| sequence | pose latency p50 / p99 [ms] | frames without a state | keyframes skipped | "
           "frontend main thread ran / waited [% wall] | back end main thread ran / waited [% wall] |",
           "|---|---:|---:|---:|---:|---:|"]
    for key, r in rows.items():
        if "latency_p50_ms" not in r and "keyframes_skipped" not in r:
            continue
        out.append(f"| {key} | {_m(r.get('latency_p50_ms'), '.0f')} / {_m(r.get('latency_p99_ms'), '.0f')} | "
                   f"{r.get('frames_without_state', '-')} | {r.get('keyframes_skipped', '-')} | "
                   f"{_m(r.get('frontend_run_pct'), '.0f')} / {_m(r.get('frontend_wait_pct'), '.0f')} | "
                   f"{_m(r.get('backend_run_pct'), '.0f')} / {_m(r.get('backend_wait_pct'), '.0f')} |")
    return "\n".join(out)


def pooled_timing(stage_dirs: list[Path]) -> dict:
    """Table V rows of ours from the per-item stage logs of the runs (pooled)."""
    pooled: dict[str, list[np.ndarray]] = {}
    for d in stage_dirs:
        for k, rec in stage_items(d).items():
            pooled.setdefault(k, []).append(rec["seconds"] * 1e3)
    get = lambda k: np.concatenate(pooled[k]) if k in pooled else np.zeros(0)  # noqa: E731
    fe, be = mean_std(get("frontend.track")), mean_std(get("backend.optimise"))
    vi = None if fe is None or be is None else (fe[0] + be[0], float(np.hypot(fe[1], be[1])), min(fe[2], be[2]))
    return {"VI optimisation (per frame)": vi,
            "  of which frontend tracking": fe,
            "  of which backend optimisation": be,
            "occupancy update (per depth frame)": mean_std(get("mapping.integrate")),
            "stereo network": None, "MVS network": None,
            "depth service: stereo + MVS + fusion": mean_std(get("depth.depth"))}


def write_report(out: Path, rows: dict[str, dict], timing: dict, args, rates: list[float],
                 starts: list[float] = (0.0,)) -> Path:
    from services.app.eval.suite_plots import summary_figure

    summary_figure(out / "summary.png", rows, PAPER_ATE, PAPER_MESH)
    dur = "whole sequences" if args.duration <= 0 else f"first {args.duration:g} s of each sequence"
    if args.seconds > 0:
        dur += f", the first {args.seconds:g} s played"
    if len(starts) > 1:
        dur += f"; one run per start offset ({', '.join(f'{s:g}' for s in starts)} s), figures: the median over them"
    modes = ", ".join(("lockstep playback" if r <= 0 else f"playback at {r:g}x sensor rate (live)") for r in rates)
    imus = ", ".join(sorted({f"{r.get('sequence', k)}: {r['imu']}" for k, r in rows.items() if "imu" in r}))
    lines = ["# sigmaslam evaluation suite", "",
             f"Replicas ({dur}; scene variant {args.variant}; profile {args.profile or 'default'}; IMU {imus}), "
             f"{modes}{' (the estimator alone, in one process)' if args.in_process else ''}. {NOTE}", "",
             "## Table I: ATE RMSE [m], SE(3) alignment", "", ate_table(rows), "",
             *(["## Spread over the start offsets", "",
                "Causal and non-causal ATE [m] of each run: min / median / max (one run alone can be tens of percent "
                "off its sequence's median).", "", spread_table(rows), ""] if len(starts) > 1 else []),
             "## Where the error is: first 10 s and the fastest-turning 10 s", "",
             "RMSE [m] of the stretch within the whole run's alignment, and its ratio to the run's RMSE "
             "(issue 23's targets: first 10 s at most 2x).", "", segment_table(rows), "",
             "## Table II: mesh accuracy [m] (no threshold) and completeness [%] (0.2 m)", "",
             "Completeness is against the whole replica scene mesh, of which a short run sees only a part.", "",
             mesh_table(rows), "",
             "## Table V: timing, mean +- sigma [ms]", "",
             "Ours: per-item compute times of all runs pooled, CPU only, on a machine shared with other jobs. "
             "Our depth service runs stereo, MVS and fusion as one stage.", "",
             timing_table(timing), "",
             *(["## Live: real-time figures", "",
                "Pose latency from sensor time to estimator/state, frames without a state, keyframes the back end "
                "skipped to catch up, and the share of the wall time the main threads of the frontend (tracking and "
                "the per-frame fast path) and of the back end ran and were ready but waited for a core.", "",
                live_table(rows), ""] if any(r > 0 for r in rates) else []),
             "## Hilti 2022 score (control points from the ground truth)", "", hilti_table(rows), "",
             "![summary](summary.png)", ""]
    for seq, r in rows.items():
        lines.append(f"### {seq}")
        lines.append("")
        for key in ("error_causal", "error_noncausal", "error_mesh", "error_run", "mesh_source"):
            if key in r:
                lines.append(f"- {key}: {r[key]}")
        where = r.get("dir", seq)  # the (first) run's folder under out
        if (out / where / "trajectory.png").is_file():
            lines.append(f"![{seq} trajectory]({where}/trajectory.png)")
        if (out / where / "mesh" / "error_top.png").is_file():
            lines.append(f"![{seq} mesh error]({where}/mesh/error_top.png)")
        lines.append("")
    path = out / "report.md"
    path.write_text("\n".join(lines))
    return path
