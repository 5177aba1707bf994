"""``sigmaslam synth``: render a synthetic EuRoC replica of a real sequence in a procedural scene.

Examples::

    sigmaslam synth --sequence V1_02 --scene vicon-a --imu real --out data/v102 --duration 30
    sigmaslam synth --sequence '' --groundtruth gt.csv --imu-data imu.csv --image-timestamps ts.txt \\
        --calib data/euroc/calib --scene machinehall-b --imu sim --out data/custom
    sigmaslam synth --default          # the cached default replica (prints its path)
"""
from __future__ import annotations

import argparse
import sys

import yaml

from shared.config import from_dict, load_yaml, merge, parse_override
from services.app.synth.scene import SCENES


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sequence", default="V1_02", help="EuRoC sequence (MH_01..MH_04, V1_01, V1_02, V2_01, V2_03; "
                   "those whose files are found) or '' with explicit files")
    p.add_argument("--scene", default="vicon-a", choices=sorted(SCENES))
    p.add_argument("--imu", default="real", choices=("real", "sim"), help="recorded imu0 (time-aligned) or simulated")
    p.add_argument("--out", help="output folder (gets mav0/, replica.yaml)")
    p.add_argument("--duration", type=float, default=0.0, help="seconds to render (0 = whole sequence)")
    p.add_argument("--start", type=float, default=0.0, help="seconds to skip from the first usable image")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--groundtruth", default="", help="ground truth (EuRoC CSV or TUM)")
    p.add_argument("--imu-data", default="", help="imu0 data.csv(.xz)")
    p.add_argument("--image-timestamps", default="", help="image stamps [ns], one per line")
    p.add_argument("--calib", default="", help="calibration folder/rig YAML (default: the real EuRoC rig)")
    p.add_argument("--depth-cameras", default="0", help="comma-separated camera indices with GT depth ('' = none)")
    p.add_argument("--render-config", help="YAML with RenderConfig fields (noise, exposure, vignetting, blur)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a RenderConfig field")
    p.add_argument("--profile", default="", help="named harder settings (services/app/synth/profiles.py: 'hard' = "
                   "motion blur, auto-exposure jumps, 1 ms camera-IMU offset); --set/--render-config apply after it")
    p.add_argument("--timeshift-cam-imu", type=float, default=None, metavar="S",
                   help="camera-IMU clock offset left in the data, Kalibr's convention (t_imu = t_cam + S) [s]")
    p.add_argument("--default", action="store_true", help="make sure the bundled default replica exists; print its path")
    p.add_argument("--no-progress", action="store_true")


def main(args: argparse.Namespace) -> int:
    from services.app.synth.render import RenderConfig
    from services.app.synth.replica import ReplicaSpec, generate

    if args.default:
        from services.app.synth.api import ensure_default_replica

        print(ensure_default_replica(progress=not args.no_progress))
        return 0
    if not args.out:
        print("sigmaslam synth: --out DIR is required (or --default)", file=sys.stderr)
        return 2
    extra: dict = {}
    for text in args.set:
        extra = merge(extra, parse_override(text))
    from services.app.synth.profiles import profile_settings

    try:
        profile = profile_settings(args.profile)
    except ValueError as exc:
        print(f"sigmaslam synth: --profile: {exc}", file=sys.stderr)
        return 2
    extra = merge(dict(profile.get("render", {})), extra)  # --set and --render-config apply after the profile
    render = load_yaml(RenderConfig, args.render_config, extra) if args.render_config else from_dict(RenderConfig, extra)
    shift = profile.get("timeshift_cam_imu_s", 0.0) if args.timeshift_cam_imu is None else args.timeshift_cam_imu
    spec = ReplicaSpec(timeshift_cam_imu_s=shift, scene=args.scene, sequence=args.sequence, imu=args.imu, start_s=args.start,
                       duration_s=args.duration, seed=args.seed, groundtruth=args.groundtruth, imu_data=args.imu_data,
                       image_timestamps=args.image_timestamps, calib=args.calib,
                       depth_cameras=tuple(int(x) for x in args.depth_cameras.split(",") if x.strip()), render=render)
    try:
        out = generate(spec, args.out, progress=not args.no_progress)
    except (FileNotFoundError, FileExistsError, ValueError, KeyError) as exc:
        print(f"sigmaslam synth: {exc}", file=sys.stderr)
        return 1
    fit = (yaml.safe_load((out / "replica.yaml").read_text()) or {}).get("trajectory_fit", {})
    print(f"wrote replica {out}; trajectory fit: " + ", ".join(f"{k} {v}" for k, v in fit.items()))
    return 0
