"""``python -m tools bench pipeline [DATASET]``: the whole pipeline at sensor rate, measured per stage and end to end.

One ``sigmaslam run`` (services/app/run_cmd.py: router, player, frontend, backend, depth, mapping as processes) with
the player at ``--rate`` times sensor rate (1 = real time), while this process

- has every service log the compute time of each item per stage ($SIGMASLAM_STAGE_LOG, transport/stats.py):
  median, p90, p99, achieved rate, items over the budgets of configs/budgets.yaml;
- subscribes to sensors/frame, frontend/frame, estimator/state, depth/fused and map/submap and records arrival
  wall times (services/app/metrics/processes.py): latency sensor -> state, -> features (the tracks, which the frontend
  process sends right after the state), -> fused depth, -> submap update;
- samples CPU share and resident memory of every service process (psutil);
- reads queue drops and the services' own overrun counts from the run's stats.json.

``--cpus LIST`` runs all of it (and this process) on those cores only (``--cpus 0``: one core), ``--load N`` beside N
busy processes at normal priority that it starts and stops itself (tools/bench_load.py): the pipeline on a small or
busy computer. Prints the tables, the run's health on that machine (frames without a state, pose latency p50 / p99,
depth rate, mapping drops, causal ATE where the dataset has ground truth; load average before and after) and the
pass/over table against the budgets, writes ``--out``/bench.json, bench_series.npz and PNG plots. ``--max-rate`` instead bisects the playback rate factor for the highest one at which the estimator
(frontend sensors/frame queue, backend frontend/frame queue) drops no frame, with a few short runs.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import uuid
from pathlib import Path

import numpy as np

from tools.bench_budgets import check_budgets, format_table, load_budgets
from tools.bench_load import BusyLoad, parse_cpus, pinned
from tools.bench_probe import Probe
from services.app.metrics.stages import stage_items
from services.app.run_pipeline import frames_within
from services.app.metrics.latency import (ArrivalLog, first_arrivals, map_latencies, matched_latencies,
                                          sensor_clock_latencies, sent_latencies, summary)
from transport.session import free_local_port

SERVICES = ("frontend", "backend", "depth", "mapping")
# (service, queue) pairs whose drops are frames lost by the estimator
ESTIMATOR_QUEUES = (("frontend", "sensors/frame"),)
LATENCY_TOPICS = ("features", "state", "depth", "map")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", nargs="?", help="EuRoC ASL folder (default: the cached 25 s V1_02 replica)")
    p.add_argument("--out", default="out/bench_pipeline", help="output folder (default out/bench_pipeline)")
    p.add_argument("--config", help="YAML system config (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    p.add_argument("--services", default=",".join(SERVICES),
                   help="pipeline services to start (comma-separated; 'config': those of --config)")
    p.add_argument("--seconds", type=float, default=0.0, help="play only the first S seconds of data (0: all) [s]")
    p.add_argument("--rate", type=float, default=1.0, help="playback rate factor (1: real sensor rate)")
    p.add_argument("--budgets", help="budgets YAML (default configs/budgets.yaml)")
    p.add_argument("--transport-s", type=float, default=0.0,
                   help="also run the transport bench's 30 Hz frame cases for this long and check the transport "
                        "budget (0: skip) [s]")
    p.add_argument("--max-rate", action="store_true", help="search the highest rate factor without estimator drops")
    p.add_argument("--max-rate-runs", type=int, default=4, help="runs of the --max-rate search")
    p.add_argument("--max-rate-seconds", type=float, default=8.0, help="seconds of data per --max-rate run [s]")
    p.add_argument("--cpus", metavar="LIST", help="run the whole pipeline on these cores only, e.g. 0 (one core), "
                                                  "0,1 or 0-1 (default: all this process may use)")
    p.add_argument("--load", type=int, default=0, metavar="N",
                   help="N busy processes at normal priority on the same cores while each run lasts (default 0)")
    p.add_argument("--timeout-s", type=float, default=900.0, help="give up a run after this long [s]")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")


# ----------------------------------------------------------------------------- one run

def run_once(dataset: Path, out: Path, rate: float, seconds: float, services: str, config: str | None,
             sets: list[str], timeout_s: float, load: int = 0, cpus: list[int] | None = None) -> dict:
    """One measured pipeline run into ``out`` (``rate`` <= 0: lockstep) beside ``load`` busy processes on ``cpus``
    (this process is already pinned there, see :func:`main`); returns the raw measurements (see :func:`summarise`)."""
    from services.app.run_outputs import find_ground_truth
    from services.app.run_pipeline import run_pipeline, services_overrides

    out.mkdir(parents=True, exist_ok=True)
    port = free_local_port()
    overrides = [f"transport.namespace=sigmaslam/bench-{uuid.uuid4().hex[:8]}",
                 f"transport.connect=[tcp/127.0.0.1:{port}]", f"transport.router_listen=[tcp/127.0.0.1:{port}]",
                 "loop.final_ba=false",  # the bench measures the real-time part; --set loop.final_ba=true to add it
                 *services_overrides(services), *sets]
    frames = frames_within(dataset, seconds)
    load_before = os.getloadavg()
    with Probe(config, overrides, out / "arrivals.npz") as probe:
        with BusyLoad(load, cpus) as busy:
            if load:
                print(f"[bench pipeline] {load} busy process(es) at normal priority: pids {busy.pids}", flush=True)
            res = run_pipeline(dataset, out / "run", config, overrides, rate=max(rate, 0.0), max_frames=frames,
                               timeout_s=timeout_s, final_timeout_s=120.0, stage_log=out / "stage_log",
                               sample_processes=True, gt=find_ground_truth(dataset))
    log = probe.log
    machine = {"cpus": cpus, "load": load, "loadavg_before": list(load_before), "loadavg_after": list(os.getloadavg())}
    return {"rc": res.rc, "wall_s": res.wall_s, "rate": rate, "frames_requested": frames, "dataset": str(dataset),
            "log": log, "sampler": res.sampler, "stage_dir": res.stage_dir, "run_stats": res.stats,
            "ate": res.ate, "machine": machine}


# ----------------------------------------------------------------------------- summary

def stage_summary(rec: np.ndarray, budget_ms: float | None) -> dict:
    ms = rec["seconds"] * 1e3
    s = summary(ms)
    out = {"n": s["n"]}
    if s["n"]:
        out.update({"median_ms": s["median"], "p90_ms": s["p90"], "p99_ms": s["p99"], "mean_ms": s["mean"],
                    "max_ms": s["max"]})
        span = (rec["end_ns"][-1] - rec["end_ns"][0]) / 1e9
        out["rate_hz"] = float((len(rec) - 1) / span) if span > 0 else None
        cpu = summary(rec["cpu_seconds"] * 1e3)  # CPU time of the timing thread: what the item cost, not its wait
        if cpu["n"]:
            out.update({"cpu_median_ms": cpu["median"], "cpu_p99_ms": cpu["p99"]})
    if budget_ms is not None:
        out["budget_ms"] = float(budget_ms)
        out["over_budget"] = int(np.sum(ms > budget_ms))
    return out


def latency_series(log: ArrivalLog) -> dict[str, dict]:
    published = first_arrivals(*log.get("frame"))
    out = {name: matched_latencies(published, *log.get(name)) for name in ("features", "state", "depth")}
    ds, da = log.get("depth")
    out["map"] = map_latencies(published, ds, da, log.get("map")[1])
    out["state_sent"] = sent_latencies(log, "state")  # frontend put - player put: without the delivery to the probe
    out["state_sensor"] = sensor_clock_latencies(log, "state")  # frontend put - the frame's time: the player's lateness too
    return out


def summarise(raw: dict, budgets) -> tuple[dict, dict]:
    """(summary for bench.json, per-item series for plots and bench_series.npz)."""
    per_stage_budget = {"frontend.track": None, "frontend.fast_path": None, "backend.optimise": None, "depth.depth": budgets.depth_frame_ms,
                        "mapping.integrate": budgets.integrate_frame_ms}
    items = stage_items(raw["stage_dir"])
    stages = {k: stage_summary(v, per_stage_budget.get(k)) for k, v in items.items()}
    lat = latency_series(raw["log"])
    fs, fa = raw["log"].get("frame")
    published = first_arrivals(fs, fa)
    span = (max(published.values()) - min(published.values())) / 1e9 if len(published) > 1 else 0.0
    latency = {}
    for name in (*LATENCY_TOPICS, "state_sent", "state_sensor"):
        s = summary(lat[name]["latency_ms"])
        s["unmatched"] = lat[name]["unmatched"]
        stamps = lat[name]["stamp_ns"]
        s["rate_hz"] = float(len(np.unique(stamps)) / span) if span > 0 else None
        latency[name] = s
    svc = raw["run_stats"].get("services", {})
    queues = {f"{name}:{q}": v for name, s in svc.items() for q, v in s.get("queues", {}).items()}
    est_drops = sum(svc.get(n, {}).get("queues", {}).get(q, {}).get("dropped", 0) for n, q in ESTIMATOR_QUEUES)
    service_overruns = {f"{name}.{st}": {"overruns": v["overruns"], "budget_ms": v["budget_ms"], "count": v["count"]}
                        for name, s in svc.items() for st, v in s.get("stages", {}).items()}
    result = {
        "dataset": raw["dataset"], "rate": raw["rate"], "rc": raw["rc"], "wall_s": raw["wall_s"],
        "frames_requested": raw["frames_requested"], "frames_published": len(published),
        "sensor_rate_hz": float((len(published) - 1) / span) if span > 0 else None,
        "states": raw["run_stats"].get("states", {}), "stages": stages, "latency_ms": latency,
        "drops": {"estimator_frames": int(est_drops), "queues": queues},
        "service_overruns": service_overruns, "processes": raw["sampler"].summary(),
        "cpu_count": os.cpu_count(), "loadavg_1min": os.getloadavg()[0], "machine": raw.get("machine", {}),
    }
    result["health"] = run_health(result, raw["run_stats"], raw.get("ate"))
    series = {"stages": items, "latency": lat, "processes": raw["sampler"].series(),
              "t0_ns": min(published.values()) if published else 0}
    return result, series


def run_health(res: dict, run_stats: dict, ate: dict | None) -> dict:
    """What a small or busy computer costs the run: frames without a state, pose latency, depth rate, what the mapping
    lost, keyframes the back end skipped, causal ATE (None without ground truth)."""
    svc = run_stats.get("services", {})
    mapping = svc.get("mapping", {})
    map_counters = mapping.get("counters", {})
    map_dropped = {k: v for k, v in map_counters.items() if k.startswith("dropped") and v}
    map_dropped.update({f"queue {q}": v["dropped"] for q, v in mapping.get("queues", {}).items() if v.get("dropped")})
    state, depth = res["latency_ms"]["state"], res["latency_ms"]["depth"]
    sent = res["latency_ms"].get("state_sent", {})
    clock = res["latency_ms"].get("state_sensor", {})
    return {"frames_sent": run_stats.get("frames_sent"), "frames_without_state": run_stats.get("frames_without_state"),
            "pose_latency_p50_ms": state.get("median"), "pose_latency_p99_ms": state.get("p99"),
            "pose_latency_sent_p50_ms": sent.get("median"), "pose_latency_sent_p99_ms": sent.get("p99"),
            "pose_latency_sensor_p50_ms": clock.get("median"), "pose_latency_sensor_p99_ms": clock.get("p99"),
            "depth_frames": depth.get("n"), "depth_rate_hz": depth.get("rate_hz"),
            "mapping_integrated": res["stages"].get("mapping.integrate", {}).get("n", 0),
            "mapping_dropped": map_dropped,
            "keyframes_skipped": svc.get("backend", {}).get("counters", {}).get("keyframes_skipped"),
            "causal_ate_m": ate["ate_rmse_m"] if ate else None}


def format_health(res: dict) -> str:
    h, m = res["health"], res.get("machine", {})
    cores = ",".join(map(str, m["cpus"])) if m.get("cpus") else f"all {res['cpu_count']}"
    before, after = m.get("loadavg_before", [float("nan")] * 3), m.get("loadavg_after", [float("nan")] * 3)
    ate = "-" if h["causal_ate_m"] is None else f"{h['causal_ate_m']:.4f} m"
    return (f"on cores {cores} with {m.get('load', 0)} busy process(es) (load average before {before[0]:.2f} "
            f"{before[1]:.2f} {before[2]:.2f}, after {after[0]:.2f} {after[1]:.2f} {after[2]:.2f}): "
            f"{h['frames_without_state']} of {h['frames_sent']} frames without a state; pose latency p50 "
            f"{_f(h['pose_latency_p50_ms'])} / p99 {_f(h['pose_latency_p99_ms'])} ms (at the probe; as sent "
            f"{_f(h.get('pose_latency_sent_p50_ms'))} / {_f(h.get('pose_latency_sent_p99_ms'))}; from the sensor clock "
            f"{_f(h.get('pose_latency_sensor_p50_ms'))} / {_f(h.get('pose_latency_sensor_p99_ms'))}); depth {h['depth_frames']} "
            f"frames ({_f(h['depth_rate_hz'])} Hz); mapping integrated {h['mapping_integrated']}, dropped "
            f"{h['mapping_dropped'] or 'none'}; keyframes skipped {h['keyframes_skipped']}; causal ATE {ate}")


# ----------------------------------------------------------------------------- printing

def _f(v, fmt: str = ".1f") -> str:
    return "-" if v is None or v != v else format(v, fmt)  # None or NaN (e.g. no schedstat on this system): '-'


def format_report(res: dict) -> str:
    lines = [f"pipeline bench: {res['dataset']} at {res['rate']:g}x sensor rate; {res['frames_published']} frames "
             f"published ({_f(res['sensor_rate_hz'])} Hz); {res['cpu_count']} CPUs, load average "
             f"{res['loadavg_1min']:.1f} (shared machine: timings include other users' load)", "",
             "| stage | items | rate [Hz] | median [ms] | p90 [ms] | p99 [ms] | CPU median [ms] | CPU p99 [ms] | "
             "over budget |", "|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for k, s in res["stages"].items():
        over = f"{s['over_budget']} (> {s['budget_ms']:g} ms)" if "budget_ms" in s else "-"
        lines.append(f"| {k} | {s['n']} | {_f(s.get('rate_hz'))} | {_f(s.get('median_ms'))} | {_f(s.get('p90_ms'))} | "
                     f"{_f(s.get('p99_ms'))} | {_f(s.get('cpu_median_ms'))} | {_f(s.get('cpu_p99_ms'))} | {over} |")
    lines += ["", "| latency from sensor time | n | rate [Hz] | median [ms] | p90 [ms] | p99 [ms] | max [ms] |",
              "|---|---:|---:|---:|---:|---:|---:|"]
    names = {"features": "frontend/frame (the tracks, sent after the state)", "state": "estimator/state",
             "depth": "depth/fused", "map": "map/submap (first update after)",
             "state_sent": "estimator/state as sent (publishers' clocks: no delivery to the probe)",
             "state_sensor": "estimator/state from the sensor clock (as sent, plus the player's own lateness)"}
    for k, s in res["latency_ms"].items():
        lines.append(f"| {names[k]} | {s['n']} | {_f(s.get('rate_hz'))} | {_f(s.get('median'))} | {_f(s.get('p90'))} | "
                     f"{_f(s.get('p99'))} | {_f(s.get('max'))} |")
    lines += ["", "| process | CPU mean [% core] | CPU p90 | machine share | main thread ran / waited for a core "
              "[% wall] | RSS median [MiB] | RSS peak [MiB] |", "|---|---:|---:|---:|---:|---:|---:|"]
    for k, p in res["processes"].items():
        lines.append(f"| {k} | {p['cpu_mean_pct']:.0f} | {p['cpu_p90_pct']:.0f} | {p['machine_share']:.2f} | "
                     f"{_f(p.get('main_thread_run_pct'), '.0f')} / {_f(p.get('main_thread_wait_pct'), '.0f')} | "
                     f"{p['rss_median_mb']:.0f} | {p['rss_peak_mb']:.0f} |")
    face = res["processes"].get("ros2")
    if face is not None:  # --set ros2.enabled=true: what the ROS 2 face adds (docs/ros2.md; target <= 10 % of a core)
        lines += ["", f"ROS 2 face (sigmaslam ros2): CPU mean {face['cpu_mean_pct']:.1f} % of a core, p90 "
                      f"{face['cpu_p90_pct']:.1f} % (target <= 10 %) at {_f(res['sensor_rate_hz'])} Hz of frames"]
    drops = {k: v["dropped"] for k, v in res["drops"]["queues"].items() if v.get("dropped")}
    lines += ["", f"queue drops: {drops or 'none'}; estimator frames dropped: {res['drops']['estimator_frames']}; "
              f"states: {res['states']}"]
    ov = {k: f"{v['overruns']}/{v['count']} > {v['budget_ms']:g} ms" for k, v in res["service_overruns"].items()
          if v["overruns"]}
    lines.append(f"services' own budget overruns: {ov or 'none'}")
    lines += ["", format_health(res)] if "health" in res else []
    lines += ["", format_table([*map(_row, res["checks"])])] if res.get("checks") else []
    return "\n".join(lines)


def _row(d: dict):
    from tools.bench_budgets import Check

    return Check(**d)


# ----------------------------------------------------------------------------- max rate

def next_rate(lo: float | None, hi: float | None, rate: float) -> float:
    """Next rate factor to try: double while passing, halve while failing, then bisect (geometric mean)."""
    if lo is None:
        return rate / 2
    if hi is None:
        return rate * 2
    return float(np.sqrt(lo * hi))


def search_max_rate(args, dataset: Path, budgets) -> dict:
    lo, hi, rate, tried = None, None, args.rate, []
    for i in range(max(args.max_rate_runs, 1)):
        raw = run_once(dataset, Path(args.out) / f"rate_{i}_{rate:.3g}", rate, args.max_rate_seconds, args.services,
                       args.config, args.set, args.timeout_s, args.load, args.cpus)
        res, _ = summarise(raw, budgets)
        drops = res["drops"]["estimator_frames"]
        ok = raw["rc"] == 0 and drops == 0 and res["frames_published"] > 0
        tried.append({"rate": rate, "estimator_drops": drops, "rc": raw["rc"], "ok": ok,
                      "state_p99_ms": res["latency_ms"]["state"].get("p99")})
        print(f"[bench pipeline] rate {rate:.3g}x: estimator drops {drops}, rc {raw['rc']} -> "
              f"{'ok' if ok else 'drops'}", flush=True)
        if ok:
            lo = rate if lo is None else max(lo, rate)
        else:
            hi = rate if hi is None else min(hi, rate)
        rate = next_rate(lo, hi, rate)
    return {"max_rate": lo, "first_failing_rate": hi, "runs": tried, "seconds_per_run": args.max_rate_seconds}


# ----------------------------------------------------------------------------- command

def _dataset(arg: str | None) -> Path:
    if arg:
        return Path(arg).resolve()
    from services.app.synth.api import ensure_default_replica

    return ensure_default_replica()


def main(args: argparse.Namespace) -> int:
    if args.rate <= 0 or args.seconds < 0 or args.load < 0:
        print("bench pipeline: --rate must be positive, --seconds and --load >= 0", file=sys.stderr)
        return 2
    try:
        dataset = _dataset(args.dataset)
        frames_within(dataset, 0.0)
        args.cpus = parse_cpus(args.cpus) if args.cpus else None
    except (FileNotFoundError, ValueError) as exc:
        print(f"bench pipeline: {exc}", file=sys.stderr)
        return 2
    with pinned(args.cpus):  # before any thread or process is started: they all inherit the cores
        return _bench(args, dataset)


def _bench(args: argparse.Namespace, dataset: Path) -> int:
    budgets = load_budgets(args.budgets)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.max_rate:
        res = search_max_rate(args, dataset, budgets)
        (out / "max_rate.json").write_text(json.dumps(res, indent=2))
        print(f"[bench pipeline] highest rate without estimator drops: {res['max_rate']} "
              f"(first failing: {res['first_failing_rate']}); wrote {out / 'max_rate.json'}", flush=True)
        return 0 if res["max_rate"] is not None else 1
    raw = run_once(dataset, out, args.rate, args.seconds, args.services, args.config, args.set, args.timeout_s,
                   args.load, args.cpus)
    res, series = summarise(raw, budgets)
    if args.transport_s > 0:
        from tools.bench_transport import benchmark

        tr = benchmark(argparse.Namespace(duration=args.transport_s, rate=30.0, samples=200, port=0))
        res["transport"] = {k: tr["frames"][0][k] for k in ("p50_ms", "p99_ms", "drops")}
    res["checks"] = [c.__dict__ for c in check_budgets(res, budgets)]
    (out / "bench.json").write_text(json.dumps(res, indent=2))
    from tools.bench_plots import save_series, write_plots

    save_series(out / "bench_series.npz", series)
    if not args.no_plots:
        write_plots(out, series)
    print(format_report(res), flush=True)
    print(f"[bench pipeline] wrote {out / 'bench.json'}" + ("" if args.no_plots else " and PNG plots"), flush=True)
    return 0 if raw["rc"] == 0 else 1
