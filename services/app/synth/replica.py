"""Generate a synthetic EuRoC replica: real trajectory, real calibration, real image stamps, rendered images.

Steps: read the ground truth (EuRoC CSV or TUM) and, for ``imu='real'``, the recorded imu0 data;
estimate the clock offset between the two (:func:`services.app.synth.imu_sim.time_offset`) and shift the ground
truth onto the IMU/camera clock; fit a smooth :class:`services.app.synth.trajectory.Trajectory` (with a recorded IMU, the
knot spacings and the offset that agree best with it, then the IMU's own fine motion on top:
:mod:`services.app.synth.imu_consistency`; the agreement reached is written to ``replica.yaml``, ``trajectory_fit``); render every
camera at the real image stamps from it; write imu0 (real samples, or simulated from the trajectory
with the imu0 noise model) and ``state_groundtruth_estimate0`` (17 columns, sampled from the same
trajectory at the IMU stamps) so that images, IMU and ground truth agree. Output: the EuRoC ASL
layout plus ``mav0/depth0`` (see :mod:`services.app.synth.depth_io`), ``mav0/scene/mesh.ply`` and ``replica.yaml``.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Literal

import numpy as np
import yaml

from shared.camera import CameraCalib, camera_from_sensor_yaml, load_rig, read_sensor_yaml_file
from shared.config import param, to_dict
from services.app.synth.depth_io import choose_scale, write_depth_png, write_depth_sensor_yaml
from shared.euroc import PoseSeries, read_trajectory
from services.app.datasets.euroc_writer import write_euroc
from services.app.synth.imu_consistency import (POSITION_CUTOFF_HZ, POSITION_KNOTS_S, ROTATION_CUTOFF_HZ, ROTATION_KNOTS_S,
                                    fit_to_imu)
from services.app.synth.imu_sim import ImuData, ImuNoise, read_imu_csv, simulate_imu, time_offset
from shared.paths import euroc_files
from services.app.synth.trajectory import Trajectory
from services.app.synth.render import RenderConfig, Renderer
from services.app.synth.scene import build_scene

# Bumped whenever a replica of the same spec would come out different; a cached replica of an older version is
# made again (services/app/synth/api.py). 2: the trajectory fitted to the recorded IMU (services/app/synth/imu_consistency.py).
# 3: the IMU's fine motion on top of that fit (imu_consistency.follow_imu): images that agree with the recorded IMU.
# 4: coarser texture levels sampled where cv2.pyrDown put them (they were 0.5 / 1.5 / 3.5 texels off at levels
# 1 / 2 / 3, so texture slid along surfaces as the camera's distance changed). 5: one scene per site whatever the
# replica's trajectory (services/app/synth/scene.py): the room had been sized with the replica's own positions, and a
# tenth of a millimetre of room moved every patch's texture, so two replicas of one room showed different rooms.
GENERATOR_VERSION = 5


@dataclasses.dataclass(frozen=True)
class ReplicaSpec:
    """What to generate. A known ``sequence`` fills groundtruth/imu_data/image_timestamps/calib."""

    scene: str = param("vicon-a", "scene name (services.app.synth.scene.SCENES)")
    sequence: str = param("V1_02", "EuRoC sequence whose real files are used ('' when all paths are given)")
    imu: Literal["real", "sim"] = param("real", "'real': the recorded imu0 data (time-aligned); 'sim': simulated from the trajectory")
    imu_noise: bool = param(True, "simulated IMU: add white noise and bias random walks of the imu0 noise model")
    start_s: float = param(0.0, "skip this much from the first usable image", "s")
    duration_s: float = param(0.0, "length of the replica (0 = to the end)", "s")
    seed: int = param(0, "seed of scene, noise, exposure and simulated IMU")
    groundtruth: str = param("", "ground-truth file (EuRoC CSV or TUM); '' = the sequence's")
    imu_data: str = param("", "imu0 data.csv(.xz); '' = the sequence's")
    image_timestamps: str = param("", "image timestamps [ns], one per line; '' = the sequence's")
    calib: str = param("", "calibration: folder with camN_sensor.yaml + imu0_sensor.yaml, an EuRoC folder or a rig YAML")
    depth_cameras: tuple[int, ...] = param((0,), "cameras whose ground-truth depth is written (mav0/depth<i>)")
    knot_spacing_s: float = param(0.0, "knot spacing of the position spline fitted to the ground truth; 0: with "
                                  "imu='real' the candidate that agrees best with the recorded accelerometer "
                                  "(services/app/synth/imu_consistency.py), else 0.05", "s")
    rotation_knot_spacing_s: float = param(0.0, "knot spacing of the orientation spline; 0: with imu='real' the "
                                           "candidate that agrees best with the recorded gyro, else 0.05", "s")
    timeshift_cam_imu_s: float = param(0.0, "camera-IMU clock offset as Kalibr writes it (t_imu = t_cam + shift): the "
                                       "image stamped t shows the scene at IMU time t + shift (0 = in sync)", "s")
    render: RenderConfig = param(RenderConfig(), "photometric settings")


def resolve_files(spec: ReplicaSpec) -> dict[str, Path]:
    known = euroc_files(spec.sequence) if spec.sequence else {}
    out = {}
    for key, given in (("groundtruth", spec.groundtruth), ("imu", spec.imu_data),
                       ("image_timestamps", spec.image_timestamps), ("calib", spec.calib)):
        if key == "imu" and not given and key not in known:
            if spec.imu == "real":
                raise ValueError(f"replica: no recorded IMU for sequence {spec.sequence!r}: use imu='sim' "
                                 "(--imu sim) or give the imu0 data file")
            continue
        if not given and key not in known:
            raise ValueError(f"replica: no {key} file: name a known --sequence or give it explicitly")
        out[key] = Path(given) if given else known[key]
        if not out[key].exists():
            raise FileNotFoundError(f"{out[key]}: {key} not found")
    return out


def load_calibration(path: Path) -> tuple[list[CameraCalib], list[dict], dict]:
    """Cameras, their sensor.yaml dicts and the imu0 sensor.yaml dict (EuRoC defaults if absent)."""
    files = sorted(path.glob("cam*_sensor.yaml"), key=lambda p: int(p.name[3:].split("_")[0])) if path.is_dir() else []
    if files:
        yamls = [read_sensor_yaml_file(f) for f in files]
        cams = [camera_from_sensor_yaml(y, f.name.split("_")[0], str(f)) for y, f in zip(yamls, files)]
        imu_file = path / "imu0_sensor.yaml"
    else:
        from shared.camera import camera_to_sensor_yaml

        cams = load_rig(path)
        yamls = [camera_to_sensor_yaml(c) for c in cams]
        root = path / "mav0" if (path / "mav0").is_dir() else path
        imu_file = root / "imu0" / "sensor.yaml"
    imu_yaml = read_sensor_yaml_file(imu_file) if imu_file.is_file() else {
        "sensor_type": "imu", "rate_hz": 200, "gyroscope_noise_density": ImuNoise.gyro_noise_density,
        "gyroscope_random_walk": ImuNoise.gyro_random_walk, "accelerometer_noise_density": ImuNoise.accel_noise_density,
        "accelerometer_random_walk": ImuNoise.accel_random_walk,
        "T_BS": {"cols": 4, "rows": 4, "data": np.eye(4).ravel().tolist()}}
    return cams, yamls, imu_yaml


def _groundtruth_biases(gt: PoseSeries, stamps_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gyro/accel biases of a ground truth that has them (17-column EuRoC) interpolated at stamps (zeros otherwise)."""
    if gt.gyro_bias is None or gt.acc_bias is None:
        zeros = np.zeros((len(stamps_ns), 3))
        return zeros, zeros
    t = (gt.stamps_ns - gt.stamps_ns[0]) * 1e-9
    s = (np.asarray(stamps_ns, np.int64) - gt.stamps_ns[0]) * 1e-9
    interp = lambda a: np.stack([np.interp(s, t, a[:, k]) for k in range(3)], 1)  # noqa: E731
    return interp(gt.gyro_bias), interp(gt.acc_bias)


def write_groundtruth17(path: Path, stamps_ns, p, q, v, bg, ba) -> None:
    """EuRoC state_groundtruth_estimate0/data.csv: t, p, q_wxyz, v, b_w, b_a."""
    path.parent.mkdir(parents=True, exist_ok=True)
    cols = np.column_stack([p, q, v, bg, ba])
    with open(path, "w") as f:
        f.write("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
                "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], "
                "b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], "
                "b_a_RS_S_z [m s^-2]\n")
        for t, row in zip(stamps_ns, cols):
            f.write(f"{int(t)}," + ",".join(f"{x:.9f}" for x in row) + "\n")


def plan(spec: ReplicaSpec) -> dict:
    """Everything but the rendering: trajectory (on the IMU clock), frame stamps, IMU, clock offset."""
    files = resolve_files(spec)
    if spec.imu not in ("real", "sim"):
        raise ValueError(f"replica: imu must be 'real' or 'sim', got {spec.imu!r}")
    gt = read_trajectory(files["groundtruth"])
    offset_ns, corr = 0, float("nan")
    real = read_imu_csv(files["imu"]) if "imu" in files else None
    if spec.imu == "real":
        offset_ns, _, c = time_offset(Trajectory(gt), real)
        corr = float(c.max())
        gt = dataclasses.replace(gt, stamps_ns=gt.stamps_ns - offset_ns)  # on the IMU clock, to 1 ms
        fit = fit_to_imu(gt, real, (spec.rotation_knot_spacing_s,) if spec.rotation_knot_spacing_s else ROTATION_KNOTS_S,
                         (spec.knot_spacing_s,) if spec.knot_spacing_s else POSITION_KNOTS_S)
        traj, offset_ns = fit.trajectory, offset_ns + fit.offset_ns  # and to 0.1 ms
        gt = dataclasses.replace(gt, stamps_ns=gt.stamps_ns - fit.offset_ns)
        consistency = {"position_knot_spacing_s": round(fit.position_knot_spacing_s, 4),
                       "rotation_knot_spacing_s": round(fit.rotation_knot_spacing_s, 4),
                       "spline_gyro_mismatch_deg_per_50ms": round(fit.spline_gyro_mismatch_deg, 4),
                       "spline_accel_mismatch_mm_per_250ms": round(fit.spline_accel_mismatch_mm, 3),
                       "follows_imu_above_hz": {"rotation": ROTATION_CUTOFF_HZ, "position": POSITION_CUTOFF_HZ},
                       "gyro_mismatch_deg_per_50ms": round(fit.gyro_mismatch_deg, 4),
                       "accel_mismatch_mm_per_250ms": round(fit.accel_mismatch_mm, 3)}
    else:
        traj = Trajectory(gt, spec.knot_spacing_s or 0.05, spec.rotation_knot_spacing_s or None)
        consistency = {"position_knot_spacing_s": round(traj.knot_spacing_s, 4),
                       "rotation_knot_spacing_s": round(traj.rotation_knot_spacing_s, 4)}
    frames = np.loadtxt(files["image_timestamps"], dtype=np.int64, comments="#", ndmin=1)
    if np.any(np.diff(frames) <= 0):
        raise ValueError(f"{files['image_timestamps']}: image timestamps not strictly increasing")
    lo, hi = traj.t0_ns + 500_000_000, traj.t_end_ns - 100_000_000
    if real is not None:
        lo, hi = max(lo, int(real.stamps_ns[0]) + 500_000_000), min(hi, int(real.stamps_ns[-1]) - 100_000_000)
    frames = frames[(frames >= lo) & (frames <= hi)]
    if not len(frames):
        raise ValueError("replica: no image stamp inside the ground truth (and IMU) time span")
    t_first = frames[0] + int(spec.start_s * 1e9)
    t_last = t_first + int(spec.duration_s * 1e9) if spec.duration_s > 0 else frames[-1]
    frames = frames[(frames >= t_first) & (frames <= t_last)]
    if not len(frames):
        raise ValueError(f"replica: no frames in [{spec.start_s}, {spec.start_s + spec.duration_s}] s")
    imu_lo, imu_hi = max(frames[0] - 500_000_000, traj.t0_ns), min(frames[-1] + 50_000_000, traj.t_end_ns)
    if real is not None:
        keep = (real.stamps_ns >= imu_lo) & (real.stamps_ns <= imu_hi)
        imu_stamps = real.stamps_ns[keep]
    else:
        imu_stamps = np.arange(imu_lo, imu_hi, 5_000_000, dtype=np.int64)
    return {"files": files, "gt": gt, "traj": traj, "frames": frames, "imu_stamps": imu_stamps, "real": real,
            "offset_ns": offset_ns, "offset_corr": corr, "imu_consistency": consistency}


def imu_noise_from_yaml(d: dict) -> ImuNoise:
    return ImuNoise(float(d.get("gyroscope_noise_density", ImuNoise.gyro_noise_density)),
                    float(d.get("gyroscope_random_walk", ImuNoise.gyro_random_walk)),
                    float(d.get("accelerometer_noise_density", ImuNoise.accel_noise_density)),
                    float(d.get("accelerometer_random_walk", ImuNoise.accel_random_walk)))


def generate(spec: ReplicaSpec, out: str | Path, progress: bool = True) -> Path:
    """Write the replica into ``out`` (created; must not hold a replica already). Returns ``out``."""
    from tqdm import tqdm

    out = Path(out)
    if (out / "mav0").exists():
        raise FileExistsError(f"{out}: already holds a dataset (mav0/)")
    t_start = time.monotonic()
    p = plan(spec)
    traj, frames, imu_stamps = p["traj"], p["frames"], p["imu_stamps"]
    cams, cam_yamls, imu_yaml = load_calibration(p["files"]["calib"])
    for i in spec.depth_cameras:
        if not 0 <= i < len(cams):
            raise ValueError(f"replica: depth camera {i} not in the rig ({len(cams)} cameras)")
    scene = build_scene(spec.scene, spec.seed, extra_positions=traj.position(imu_stamps))
    renderer = Renderer(scene, cams, spec.render)
    if spec.imu == "real":
        keep = np.isin(p["real"].stamps_ns, imu_stamps)
        imu = ImuData(imu_stamps, p["real"].omega_S[keep], p["real"].acc_S[keep])
        bg, ba = _groundtruth_biases(p["gt"], imu_stamps)
    else:
        imu = simulate_imu(traj, imu_stamps, imu_noise_from_yaml(imu_yaml) if spec.imu_noise else None, seed=spec.seed)
        bg, ba = imu.gyro_bias, imu.accel_bias
    scale = choose_scale(scene.max_range_m)
    mav0 = out / "mav0"
    for i in spec.depth_cameras:
        write_depth_sensor_yaml(mav0 / f"depth{i}", cams[i].name, scale)
    depth_csv = {i: open(mav0 / f"depth{i}" / "data.csv", "w") for i in spec.depth_cameras}
    rng = np.random.default_rng([spec.seed, 11])
    stats = {"depth_pixels_out_of_range": 0, "depth_pixels_no_hit": 0}
    nblur = spec.render.motion_blur_samples
    blur_dt = np.linspace(-0.5, 0.5, nblur) * spec.render.exposure_time_s * 1e9 if nblur > 1 else None
    shift_ns = int(round(spec.timeshift_cam_imu_s * 1e9))

    def frames_iter():
        for stamp in tqdm(frames, desc=f"render {spec.scene}", unit="frame", disable=not progress):
            stamp = int(stamp)
            t_true = int(np.clip(stamp + shift_ns, traj.t0_ns, traj.t_end_ns))  # when the image was really taken
            blur = None
            if blur_dt is not None:
                ts = np.clip(t_true + blur_dt.astype(np.int64), traj.t0_ns, traj.t_end_ns)
                blur = list(traj.pose(ts))
            imgs, depths = renderer.render_rig(traj.pose(t_true), (stamp - int(frames[0])) * 1e-9, rng,
                                               tuple(spec.depth_cameras), blur)
            for i, d in depths.items():
                stats["depth_pixels_no_hit"] += int(np.isnan(d).sum())
                stats["depth_pixels_out_of_range"] += write_depth_png(mav0 / f"depth{i}" / "data" / f"{stamp}.png", d, scale)
                depth_csv[i].write(f"{stamp},{stamp}.png\n")
            yield stamp, imgs

    try:
        for f in depth_csv.values():
            f.write("#timestamp [ns],filename\n")
        write_euroc(out, {c.name: y for c, y in zip(cams, cam_yamls)}, frames_iter(),
                    np.column_stack([imu.stamps_ns, imu.omega_S, imu.acc_S]), imu_yaml, imu_stamps_ns=imu.stamps_ns)
    finally:
        for f in depth_csv.values():
            f.close()
    q = traj.quaternion_wxyz(imu_stamps)
    write_groundtruth17(mav0 / "state_groundtruth_estimate0" / "data.csv", imu_stamps, traj.position(imu_stamps), q,
                        traj.velocity(imu_stamps), bg, ba)
    (mav0 / "scene").mkdir(exist_ok=True)
    scene.save_ply(mav0 / "scene" / "mesh.ply")
    info = {"spec": to_dict(spec), "files": {k: str(v) for k, v in p["files"].items()},
            "frames": int(len(frames)), "imu_samples": int(len(imu_stamps)),
            "generator_version": GENERATOR_VERSION,
            "groundtruth_clock_offset_ns": int(p["offset_ns"]), "offset_correlation": p["offset_corr"],
            "trajectory_fit": p["imu_consistency"],
            "scene": {"name": scene.name, "seed": scene.seed, "triangles": int(len(scene.triangles)),
                      "room_min": scene.room_min.tolist(), "room_max": scene.room_max.tolist()},
            "depth_scale_m": scale, "stats": stats, "generation_s": round(time.monotonic() - t_start, 1)}
    (out / "replica.yaml").write_text(yaml.safe_dump(info, sort_keys=False))
    return out
