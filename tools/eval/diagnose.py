"""Why a run's error is where it is: per-frame and per-segment diagnostics of the estimator on a replica.

    python -m tools.eval.diagnose REPLICA [--max-frames N] [--set KEY=VALUE] [--segment-s 10] --out DIR

Runs frontend, fast path and back end with loop closure on the in-process runner (services/app/inprocess.py, as
tools/eval_loop.py) and lines up, per published state, against the replica's ground truth (17 columns: pose,
velocity, biases):

- the position error of the causal trajectory after the whole run's SE(3) alignment (shared/metrics/ate.py);
- the velocity error (the estimate rotated by that alignment) and the gyro / accelerometer bias errors (NaN, shown
  '-', when the ground truth's bias columns are all zero: a real-IMU replica of a sequence whose ground truth has no
  biases, MH_03 today, writes zeros there, while its IMU carries EuRoC's ~80 mrad/s gyro bias);
- per segment, the travel ratio (how far the estimate moved against the ground truth: a scale drift);
- the frontend's features per frame, the keyframes, the ground truth's angular speed; the state's status.

Writes DIR/diagnose.csv (one row per state), DIR/segments.md (per ``--segment-s`` stretch: RMSE, features,
keyframe rate, bias errors, rotation rate), DIR/diagnose.png and DIR/diagnose.json (summary); prints the table.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def collect(dataset: str, overrides: list[str], max_frames: int = 0) -> dict:
    """Run the estimator in process; returns per-state and per-frame arrays."""
    from services.app.inprocess import run_in_process
    from services.app.system_config import load_system_config
    from shared import topics

    cfg = load_system_config(None, ["o2p.enabled=false", *overrides])
    states, features, kf = [], {}, []

    def tap(topic, msg) -> None:
        if topic == topics.STATE and msg.status not in ("initialising", "reset"):
            states.append((msg.header.stamp_ns, msg.T_WS, msg.v_W, msg.gyro_bias, msg.acc_bias, msg.status))
        elif topic == topics.FEATURES:
            cams = np.asarray(msg.camera_index)
            features[msg.header.stamp_ns] = (int((cams == 0).sum()), int(len(cams)))
        elif topic == topics.WINDOW and msg.status not in ("initialising", "reset"):
            kf.append(int(msg.header.stamp_ns))

    run = run_in_process(dataset, cfg, max_frames, taps=[tap])
    if not states:
        raise ValueError(f"{dataset}: the estimator published no state")
    st = np.array([s[0] for s in states], np.int64)
    return {"stamps_ns": st, "T_WS": np.array([s[1] for s in states]), "v_W": np.array([s[2] for s in states]),
            "bg": np.array([s[3] for s in states]), "ba": np.array([s[4] for s in states]),
            "status": [s[5] for s in states],
            "features_cam0": np.array([features.get(int(t), (0, 0))[0] for t in st]),
            "features_all": np.array([features.get(int(t), (0, 0))[1] for t in st]),
            "keyframes_ns": np.unique(np.array(kf, np.int64)), "groundtruth": run.groundtruth_path,
            "frames": run.frames}


def analyse(d: dict, segment_s: float = 10.0) -> dict:
    """Per-state errors and per-segment figures of :func:`collect`'s output against its ground truth."""
    from shared.euroc import read_euroc_csv
    from shared.metrics.ate import associate, compute_ate
    from services.app.metrics.segments import angular_speed

    gt = read_euroc_csv(d["groundtruth"])
    if gt.gyro_bias is None:
        raise ValueError(f"{d['groundtruth']}: expected 17 columns (pose, velocity, biases)")
    ate = compute_ate(gt.stamps_ns, gt.p_WS, d["stamps_ns"], d["T_WS"][:, :3, 3], mode="se3")
    ie, ig = associate(d["stamps_ns"], gt.stamps_ns, 10_000_000)
    biases_known = bool(np.any(gt.gyro_bias) or np.any(gt.acc_bias))
    unknown = np.full(len(ie), np.nan)
    R = ate.alignment.R
    t_mid, w = angular_speed(gt.stamps_ns, gt.q_WS_wxyz)
    rows = {"t_s": (d["stamps_ns"][ie] - d["stamps_ns"][ie[0]]) * 1e-9, "err_m": ate.errors_m,
            "vel_err_m_s": np.linalg.norm(d["v_W"][ie] @ R.T - gt.v_WS[ig], axis=1),
            "bg_err_rad_s": np.linalg.norm(d["bg"][ie] - gt.gyro_bias[ig], axis=1) if biases_known else unknown,
            "ba_err_m_s2": np.linalg.norm(d["ba"][ie] - gt.acc_bias[ig], axis=1) if biases_known else unknown,
            "features_cam0": d["features_cam0"][ie], "features_all": d["features_all"][ie],
            "gt_deg_s": np.degrees(np.interp(d["stamps_ns"][ie], t_mid, w)),
            "imu_only": np.array([d["status"][i] == "imu_only" for i in ie], float)}
    p_est, p_gt = d["T_WS"][ie][:, :3, 3], gt.p_WS[ig]
    t0 = int(d["stamps_ns"][ie[0]])
    kf_t = (d["keyframes_ns"] - t0) * 1e-9
    segs = []
    for a in np.arange(0.0, rows["t_s"][-1] + 1e-9, segment_s):
        sel = (rows["t_s"] >= a) & (rows["t_s"] < a + segment_s)
        if not sel.any():
            continue
        span = min(segment_s, rows["t_s"][-1] - a) or segment_s
        segs.append({"start_s": float(a), "rmse_m": float(np.sqrt(np.mean(rows["err_m"][sel] ** 2))),
                     "vel_err_m_s": float(np.median(rows["vel_err_m_s"][sel])),
                     "bg_err_mrad_s": 1e3 * float(np.median(rows["bg_err_rad_s"][sel])),
                     "ba_err_m_s2": float(np.median(rows["ba_err_m_s2"][sel])),
                     "features_cam0": float(np.median(rows["features_cam0"][sel])),
                     "keyframes_per_s": float(((kf_t >= a) & (kf_t < a + segment_s)).sum() / span),
                     "travel_ratio": travel_ratio(p_est[sel], p_gt[sel]),
                     "gt_deg_s": float(np.mean(rows["gt_deg_s"][sel])),
                     "imu_only": int(rows["imu_only"][sel].sum())})
    return {"rows": rows, "segments": segs, "ate_m": ate.rmse_m, "states": len(ie), "frames": d["frames"],
            "keyframes": int(len(d["keyframes_ns"])), "biases_known": biases_known}


def travel_ratio(p_est: np.ndarray, p_gt: np.ndarray, min_travel_m: float = 0.2) -> float:
    """How far the estimate moved over a stretch against the ground truth, ``|p_est[-1] - p_est[0]| /
    |p_gt[-1] - p_gt[0]|`` (independent of the frames' alignment): below 1 the estimator under-reports travel (a
    scale drift). NaN when the ground truth moved less than ``min_travel_m`` [m]."""
    if len(p_gt) < 2:
        return float("nan")
    true = float(np.linalg.norm(p_gt[-1] - p_gt[0]))
    return float(np.linalg.norm(p_est[-1] - p_est[0])) / true if true >= min_travel_m else float("nan")


def segments_markdown(res: dict) -> str:
    out = [f"causal ATE {res['ate_m']:.4f} m over {res['states']} states of {res['frames']} frames, "
           f"{res['keyframes']} keyframe windows"
           + ("" if res.get("biases_known", True) else "; the ground truth has no biases (all zero): bias errors '-'"),
           "",
           "| from [s] | RMSE [m] | velocity err [m/s] | gyro bias err [mrad/s] | acc bias err [m/s^2] | "
           "travel ratio | cam0 features | keyframes/s | GT rotation [deg/s] | imu_only |",
           "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for s in res["segments"]:
        bg, ba = (("-" if np.isnan(v) else format(v, f)) for v, f in ((s["bg_err_mrad_s"], ".2f"),
                                                                        (s["ba_err_m_s2"], ".3f")))
        out.append(f"| {s['start_s']:.0f} | {s['rmse_m']:.4f} | {s['vel_err_m_s']:.3f} | {bg} | "
                   f"{ba} | {s['travel_ratio']:.3f} | {s['features_cam0']:.0f} | "
                   f"{s['keyframes_per_s']:.1f} | {s['gt_deg_s']:.0f} | {s['imu_only']} |")
    return "\n".join(out)


def figure(path: Path, res: dict, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = res["rows"]
    fig, ax = plt.subplots(4, 1, figsize=(10, 9), sharex=True)
    ax[0].plot(r["t_s"], 100 * r["err_m"], lw=1)
    ax[0].set(ylabel="position err [cm]", title=f"{title}: causal ATE {res['ate_m']:.4f} m")
    ax[1].plot(r["t_s"], r["vel_err_m_s"], lw=1, label="velocity [m/s]")
    ax[1].plot(r["t_s"], r["ba_err_m_s2"], lw=1, label="acc bias [m/s^2]")
    ax[1].plot(r["t_s"], 10 * r["bg_err_rad_s"], lw=1, label="gyro bias x10 [rad/s]")
    ax[1].set(ylabel="error")
    ax[1].legend(fontsize=7)
    ax[2].plot(r["t_s"], r["features_cam0"], lw=1)
    ax[2].set(ylabel="cam0 features")
    ax[3].plot(r["t_s"], r["gt_deg_s"], lw=1)
    ax[3].set(ylabel="GT rotation [deg/s]", xlabel="time [s]")
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset", help="replica folder (holding mav0/ with a 17-column ground truth)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--max-frames", type=int, default=0)
    p.add_argument("--segment-s", type=float, default=10.0)
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    res = analyse(collect(a.dataset, a.set, a.max_frames), a.segment_s)
    r = res["rows"]
    np.savetxt(out / "diagnose.csv", np.column_stack([r[k] for k in r]), delimiter=",", fmt="%.6g",
               header=",".join(r), comments="")
    table = segments_markdown(res)
    (out / "segments.md").write_text(table + "\n")
    (out / "diagnose.json").write_text(json.dumps({k: v for k, v in res.items() if k != "rows"}, indent=1))
    figure(out / "diagnose.png", res, Path(a.dataset).name)
    print(table, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
