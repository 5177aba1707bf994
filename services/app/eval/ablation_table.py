"""The markdown table of ``sigmaslam eval ablation`` (services/app/eval/ablation.py): one row per replica and ablation
row, and a line per replica saying which dense rows beat their baseline's causal ATE."""

from __future__ import annotations

import math

ROWS = ("baseline", "heuristic", "learned", "fused", "mono_baseline", "mono")
LABELS = {"baseline": "baseline (no dense terms)", "heuristic": "+ stereo net, heuristic sigma",
          "learned": "+ learned sigma", "fused": "+ depth fusion (stereo + MVS)",
          "mono_baseline": "mono-inertial, no dense terms (MVS depth map)", "mono": "mono-inertial (MVS depth)"}
DENSE = ("heuristic", "learned", "fused", "mono")
MONO = ("mono_baseline", "mono")
BASELINE_OF = {"mono": "mono_baseline"}  # the row a dense row is compared with (default: baseline)


def _f(x, fmt: str) -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, fmt)


def table_markdown(results: dict[str, dict[str, dict]]) -> str:
    """One markdown table (a replica column) and a verdict line per replica."""
    head = ("| replica | row | causal ATE [m] | non-causal ATE [m] | mesh acc causal / final map [m] | compl@0.2 | compl@0.05 "
            "| back end median / p99 [ms] | f2m / m2m factors (in pose graph) | wall [s] |")
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    verdicts = []
    for rep, rows in results.items():
        for row, r in rows.items():
            label = LABELS.get(row, row)
            if "error" in r:
                why = str(r["error"]).replace("|", "/").replace("\n", " ")
                why = why if len(why) <= 160 else why[:157] + "..."
                lines.append(f"| {rep} | {label} | failed: {why} | | | | | | | {_f(r.get('wall_s'), '.0f')} |")
                continue
            c = r.get("o2p_counts")
            fac = "-" if c is None else f"{c.get('frame_to_map', 0)} / {c.get('map_to_map', 0)}"
            if c is not None and "map_to_map_accepted" in r.get("loop", {}):
                fac += f" ({r['loop']['map_to_map_accepted']})"  # of which the loop closer's pose graph took
            comp = lambda k: _f(None if r.get(k) is None else 100 * r[k], ".1f") + ("%" if r.get(k) is not None else "")  # noqa: E731
            lines.append(f"| {rep} | {label} | {_f(r.get('ate_causal_m'), '.4f')} | {_f(r.get('ate_noncausal_m'), '.4f')} "
                         f"| {_f(r.get('accuracy_m'), '.3f')} / {_f(r.get('accuracy_final_m'), '.3f')} | {comp('completeness')} | {comp('completeness_5cm')} "
                         f"| {_f(r.get('backend_median_ms'), '.1f')} / {_f(r.get('backend_p99_ms'), '.0f')} | {fac} "
                         f"| {_f(r.get('wall_s'), '.0f')} |")
        verdicts.append(verdict(rep, rows))
    return "\n".join(lines + [""] + verdicts) + "\n"


def verdict(rep: str, rows: dict[str, dict]) -> str:
    """Whether the dense rows beat the baseline's causal ATE on one replica (the mono row: the mono baseline's,
    when that row ran)."""
    base = rows.get("baseline", {}).get("ate_causal_m")
    mono_base = rows.get("mono_baseline", {}).get("ate_causal_m")
    if base is None and mono_base is None:
        return f"- {rep}: no baseline causal ATE to compare with."
    better, worse = [], []
    for row, r in rows.items():
        ref = rows.get(BASELINE_OF.get(row, "baseline"), {}).get("ate_causal_m")
        if row in DENSE and r.get("ate_causal_m") is not None and ref is not None:
            (better if r["ate_causal_m"] < ref else worse).append(
                f"{row} {r['ate_causal_m']:.4f}" + (f" (vs {BASELINE_OF[row]} {ref:.4f})" if row in BASELINE_OF else ""))
    ref = f"the baseline's causal ATE ({base:.4f} m)" if base is not None else "their baseline's causal ATE"
    if not better and not worse:
        return f"- {rep}: no dense row finished ({ref[4:]})."
    return (f"- {rep}: dense rows beating {ref}: {', '.join(better) or 'none'}"
            + (f"; not beating: {', '.join(worse)}" if worse else "") + ".")
