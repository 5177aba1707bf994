"""Online extrinsic refinement, measured: a replica run with its calibration perturbed, with and without refinement.

    python -m tools.vio.extrinsics_bench REPLICA [--rot-deg 1] [--trans-m 0.01] [--seed 0] [--seconds S] [--jobs N]
                                         [--out DIR]

Four in-process runs of frontend, fast path and back end (services/app/inprocess.py; loop closure and occupancy
terms off) on one replica: with the replica's own (true) calibration, with and without ``backend.refine_extrinsics``
(refinement must not spoil a good calibration); with every camera's T_SC perturbed by ``--rot-deg`` about a random
axis and ``--trans-m`` along a random direction (seeded), with and without refinement. Prints each run's causal ATE
(SE(3)) and, per camera, the refined T_SC's rotation and translation error against the true one (at the end, and
the median over the second half of the run); ``--out`` writes them as JSON, the perturbed rig YAML and a plot of
the perturbed run's error over time (from each estimator/window).

Use a replica with a simulated IMU (MH_01, MH_02, or ``tools.vio.sim_imu_variant`` of another): the images of a
replica follow a smooth fit of the ground truth, which a real IMU does not, and refinement absorbs the difference.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import dataclasses
import json
from pathlib import Path

import numpy as np

from shared.camera import CameraCalib, load_rig, write_rig_yaml
from shared.geometry import make_T, pose_error, so3_exp


def perturb_extrinsics(T_SC: np.ndarray, rot_deg: float, trans_m: float, seed: int) -> np.ndarray:
    """(C,4,4): each T_SC rotated by ``rot_deg`` about a random axis (in S) and moved ``trans_m`` along a random
    direction (in S), from ``seed``."""
    rng = np.random.default_rng(seed)
    out = []
    for T in np.asarray(T_SC, float):
        axis, direction = (v / np.linalg.norm(v) for v in rng.normal(size=(2, 3)))
        out.append(make_T(so3_exp(np.deg2rad(rot_deg) * axis) @ T[:3, :3], T[:3, 3] + trans_m * direction))
    return np.array(out)


def perturbed_rig(cameras: list[CameraCalib], rot_deg: float, trans_m: float, seed: int) -> list[CameraCalib]:
    """The rig with every camera's T_SC perturbed as :func:`perturb_extrinsics` does."""
    T = perturb_extrinsics(np.array([c.T_SC for c in cameras]), rot_deg, trans_m, seed)
    return [dataclasses.replace(c, T_SC=t) for c, t in zip(cameras, T)]


def _run(dataset: str, overrides: list[str], seconds: float) -> dict:
    """One in-process run (tools.vio.offline): causal ATE, poses and the refined extrinsics of every window."""
    from shared import topics
    from tools.vio.offline import run

    windows: list[tuple[int, np.ndarray]] = []

    def tap(topic, msg) -> None:
        if topic == topics.WINDOW and len(msg.T_SC):
            windows.append((int(msg.header.stamp_ns), np.array(msg.T_SC, float)))

    res, _ = run(dataset, None, overrides, seconds=seconds, taps=[tap])
    return {"ate_m": float(res["ate_rmse_m"]), "poses": res["poses"], "windows": windows}


def bench(dataset: str, rot_deg: float, trans_m: float, seed: int, seconds: float, overrides: list[str],
          out: Path | None, jobs: int = 1) -> dict:
    true_rig = load_rig(dataset)
    pert = perturbed_rig(true_rig, rot_deg, trans_m, seed)
    rig_file = write_rig_yaml((out or Path("/tmp")) / f"perturbed_rig_seed{seed}.yaml", pert,
                              f"{dataset}'s rig, each T_SC perturbed by {rot_deg} deg and {trans_m} m (seed {seed})")
    true_T = np.array([c.T_SC for c in true_rig])
    start = [pose_error(c.T_SC, t) for c, t in zip(pert, true_T)]
    res = {"dataset": dataset, "rot_deg": rot_deg, "trans_m": trans_m, "seed": seed, "seconds": seconds,
           "perturbed_rig": str(rig_file),
           "start_error": [{"rot_deg": float(np.degrees(r)), "trans_m": float(t)} for t, r in start]}
    runs = {"true calibration": [], "true calibration, refined": ["backend.refine_extrinsics=true"],
            "perturbed": [f"rig.calibration={rig_file}"],
            "perturbed, refined": [f"rig.calibration={rig_file}", "backend.refine_extrinsics=true"]}
    series = None
    with concurrent.futures.ProcessPoolExecutor(max(1, jobs)) as pool:
        futures = {name: pool.submit(_run, dataset, [*extra, *overrides], seconds) for name, extra in runs.items()}
        results = {name: f.result() for name, f in futures.items()}
    for name, r in results.items():
        res[name] = {"ate_m": r["ate_m"], "poses": r["poses"]}
        print(f"{name:>20}: causal ATE {r['ate_m']:.4f} m over {r['poses']} poses", flush=True)
        if r["windows"]:
            st = np.array([s for s, _ in r["windows"]])
            T = np.array([w for _, w in r["windows"]])
            t_err, r_err = pose_error(T, true_T[None])
            if name == "perturbed, refined":
                series = (1e-9 * (st - st[0]), np.degrees(r_err), t_err)
            half = st >= st[0] + (st[-1] - st[0]) // 2  # the second half of the run: after the settling
            res[name]["final_error"] = [{"rot_deg": float(np.degrees(r_err[-1, c])), "trans_m": float(t_err[-1, c])}
                                        for c in range(len(true_T))]
            res[name]["second_half_median_error"] = [
                {"rot_deg": float(np.degrees(np.median(r_err[half, c]))), "trans_m": float(np.median(t_err[half, c]))}
                for c in range(len(true_T))]
            for c in range(len(true_T)):
                t0, r0 = start[c] if name.startswith("perturbed") else (0.0, 0.0)
                print(f"{'':>20}  cam{c}: {np.degrees(r_err[-1, c]):.3f} deg, {1e3 * t_err[-1, c]:.1f} mm at the end "
                      f"(start {np.degrees(r0):.3f} deg, {1e3 * t0:.1f} mm; median over the second half "
                      f"{np.degrees(np.median(r_err[half, c])):.3f} deg, {1e3 * np.median(t_err[half, c]):.1f} mm)",
                      flush=True)
    base = res["true calibration"]["ate_m"]
    for name in ("true calibration, refined", "perturbed", "perturbed, refined"):
        res[name]["ate_vs_true"] = res[name]["ate_m"] / base if base > 0 else float("nan")
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "extrinsics_bench.json").write_text(json.dumps(res, indent=1))
        if series is not None:
            _plot(out / "extrinsics_error.png", *series)
    return res


def _plot(path: Path, t: np.ndarray, rot_deg: np.ndarray, trans_m: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    for c in range(rot_deg.shape[1]):
        ax[0].plot(t, rot_deg[:, c], label=f"cam{c}")
        ax[1].plot(t, 1e3 * trans_m[:, c], label=f"cam{c}")
    ax[0].set_ylabel("rotation error [deg]")
    ax[1].set_ylabel("translation error [mm]")
    ax[1].set_xlabel("time since the first window [s]")
    ax[0].legend()
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset")
    p.add_argument("--rot-deg", type=float, default=1.0)
    p.add_argument("--trans-m", type=float, default=0.01)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seconds", type=float, default=0.0, help="only the first S seconds (0: all)")
    p.add_argument("--set", action="append", default=[], help="config overrides for every run")
    p.add_argument("--jobs", type=int, default=1, help="runs at once (each is one process)")
    p.add_argument("--out")
    a = p.parse_args()
    bench(a.dataset, a.rot_deg, a.trans_m, a.seed, a.seconds, a.set, Path(a.out) if a.out else None, a.jobs)


if __name__ == "__main__":
    main()
