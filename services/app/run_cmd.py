"""``sigmaslam run DATASET --out DIR [CONFIG] [--set k=v]``: the pipeline on one dataset, as real processes.

The command line of :func:`services.app.run_pipeline.run_pipeline`: the services of ``supervisor.services`` (enabled
ones; the recorder only with ``--record``; frontend and back end when it names no pipeline process) plus the player of
DATASET (lockstep by default, ``--realtime`` plays at sensor rate, ``--rate R`` at R times), on a router and a
namespace of their own. ``rig.calibration`` defaults to DATASET. Once the player has ended and the last state is in
(or no state came for ``--settle-s``), it stops the services and writes

- ``DIR/trajectory_causal.txt`` (TUM) and ``DIR/trajectory_causal.csv`` (EuRoC): each pose as published at its
  frame time, never revised; ``DIR/trajectory.txt`` / ``.csv`` are the same until a non-causal trajectory exists;
- ``DIR/stats.json``: per service and stage the whole-run count and overruns, the last window's p50/p99, and the
  median of the per-window medians over the run; queue drops; frontend+backend median per frame;
- ``DIR/trajectory_final.txt`` / ``.csv``: the non-causal trajectory (final bundle adjustment with loops, from
  ``estimator/trajectory_final``; ``loop.final_ba``), which then also becomes ``DIR/trajectory.txt``; loop counts
  in stats.json;
- ``DIR/ate.json`` and a printed line when there is ground truth (SE(3) alignment, shared/metrics/ate.py), causal
  and non-causal, over the poses that have a ground-truth pose within 10 ms (a ground truth that starts late or
  ends early only shortens the span; ate.json says how many poses and which span). The ground truth is
  ``--gt PATH`` (EuRoC CSV or TUM ``.txt``), else the first of :data:`GT_CANDIDATES` found in DATASET; it is also
  the viewer's overlay unless ``viewer.ground_truth`` is set;
- ``DIR/config.yaml``: the resolved config every service got;
- ``DIR/map/``: the saved map (docs/maps.md): ``sparse.npz`` from the back end (``loop.map_output``), ``dense.npz``
  from the mapping process.

``--map SAVED`` localises in a saved map (a run folder or its map/ folder): the back end relocalises against it and
publishes in its frame from then on; the states before (``header.frame_id`` ``odom``) are left out of the
trajectory files and counted in stats.json's ``localisation``; the mapping starts from the saved submaps; the map
written to ``DIR/map/`` is the saved one extended by this run (not with ``--localise-only``: no sparse map written).

``--serve-s S`` then shows the run's final map and trajectories in the web viewer for S seconds.
"""

from __future__ import annotations

import argparse
import functools
from pathlib import Path

from services.app.run_outputs import GT_CANDIDATES, find_ground_truth
from services.app.run_pipeline import run_pipeline
from shared.map_folder import sparse_path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", help="EuRoC ASL folder (real or replica; the folder holding mav0/, or mav0), or a ROS "
                   "bag (ROS 2 folder/.mcap/.db3, ROS 1 .bag: converted to DIR/dataset first, with --calib)")
    p.add_argument("config", nargs="?", help="YAML system config (default: built-in defaults); before or after "
                   "the options")
    p.add_argument("--gt", metavar="PATH", help="ground truth for the ATE: EuRoC CSV (state_groundtruth_estimate0 "
                   "or 8-column pose CSV, .xz ok) or TUM .txt (default: the first of "
                   f"{', '.join(GT_CANDIDATES)} in DATASET; none: no ATE)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    p.add_argument("--realtime", action="store_true", help="play at sensor rate instead of lockstep")
    p.add_argument("--rate", type=float, default=0.0, metavar="R",
                   help="play at R times sensor rate instead of lockstep (overrides --realtime; 0: off)")
    p.add_argument("--map", metavar="SAVED", default=None, help="localise in this saved map (a run's output folder "
                   "or its map/ folder): poses in its frame once relocalised; DIR/map/ then holds it extended")
    p.add_argument("--localise-only", action="store_true", help="with --map: do not extend the saved map (no "
                   "DIR/map/sparse.npz is written)")
    p.add_argument("--record", action="store_true", help="also record every topic to DIR/recording.mcap")
    p.add_argument("--ros2-bag", metavar="BAG", default=None, help="also write the results as a ROS 2 bag (MCAP "
                   "storage, standard messages: services/app/datasets/ros2_export.py) to the new folder BAG; implies --record")
    p.add_argument("--ros2-input", action="store_true", help="feed the pipeline through ROS 2: the player plays the "
                   "dataset as a ROS 2 robot (--as-ros2) and sigmaslam ros2_input reads its topics (ros2.input; "
                   "= --set ros2.input.enabled=true)")
    p.add_argument("--player-arg", action="append", default=[], metavar="ARG",
                   help="extra argument for the player (repeatable), e.g. --player-arg=--max-frames=200")
    p.add_argument("--settle-s", type=float, default=5.0, help="after the player ended, stop when no state came "
                   "for this long [s]")
    p.add_argument("--timeout-s", type=float, default=0.0, help="give up after this long (0: no limit) [s]")
    p.add_argument("--final-timeout-s", type=float, default=600.0, help="wait this long for the back end's final "
                   "bundle adjustment (estimator/trajectory_final) after the stream ended [s]")
    p.add_argument("--serve-s", type=float, default=0.0, help="after the run, show its final map and trajectories "
                   "in the web viewer (viewer.host:viewer.port) this long [s] (0: no)")
    from services.app.datasets.bag_input import add_bag_arguments

    add_bag_arguments(p)
    _intermixed(p)


def _intermixed(p: argparse.ArgumentParser) -> None:
    """Let CONFIG come after the options (``run DATASET --out DIR CONFIG``): argparse of Python 3.11 binds every
    positional at the first one (CONFIG to nothing) and then refuses a later CONFIG; intermixed parsing first
    takes the options, then the positionals. The subcommand parser is called through ``parse_known_args``."""
    plain = functools.partial(type(p).parse_known_args, p)

    def parse_known_args(args=None, namespace=None):
        p.parse_known_args = plain  # intermixed parsing calls parse_known_args itself
        try:
            return p.parse_known_intermixed_args(args, namespace)
        finally:
            p.parse_known_args = parse_known_args

    p.parse_known_args = parse_known_args


def _bag_dataset(args: argparse.Namespace, out: Path) -> str:
    """A ROS bag converted to OUT/dataset (an EuRoC folder; reused when it is already there)."""
    from services.app.datasets.bag_input import bag_to_euroc

    dst = out / "dataset"
    if (dst / "mav0").is_dir():
        print(f"[sigmaslam run] {args.dataset}: using the conversion already in {dst}", flush=True)
    else:
        counts = bag_to_euroc(args.dataset, dst, getattr(args, "calib", None), getattr(args, "imu_calib", None),
                              getattr(args, "cam", None), getattr(args, "imu", None),
                              getattr(args, "sync_tolerance_ms", 2.0))
        print(f"[sigmaslam run] converted {args.dataset} -> {dst}: " + ", ".join(f"{k} {v}" for k, v in counts.items()),
              flush=True)
    return str(dst.resolve())


def _ground_truth(gt_arg: str | None, dataset: str) -> tuple[Path | None, str | None]:
    """(the ground truth of the ATE, None) or (None, why --gt is refused)."""
    if gt_arg and gt_arg != "none" and not Path(gt_arg).is_file():
        return None, f"--gt {gt_arg}: file not found"
    if gt_arg:
        return (None if gt_arg == "none" else Path(gt_arg).resolve()), None
    return find_ground_truth(Path(dataset)), None


def main(args: argparse.Namespace) -> int:
    from shared.euroc_reader import DatasetError
    from services.app.datasets.ros_bag import is_ros_bag

    out = Path(args.out)
    dataset = str(Path(args.dataset).resolve())
    if is_ros_bag(dataset):
        out.mkdir(parents=True, exist_ok=True)
        try:
            dataset = _bag_dataset(args, out)
        except (DatasetError, OSError) as exc:
            print(f"sigmaslam run: {exc}", flush=True)
            return 2
    gt, why = _ground_truth(getattr(args, "gt", None), dataset)
    saved = getattr(args, "map", None)
    if why is None and saved and not sparse_path(saved).is_file():
        why = f"--map {saved}: no saved map there ({sparse_path(saved)} not found)"
    if why is None and getattr(args, "localise_only", False) and not saved:
        why = "--localise-only needs --map"
    if why is not None:
        print(f"sigmaslam run: {why}", flush=True)
        return 2
    if getattr(args, "ros2_bag", None):
        args.record = True
    if getattr(args, "ros2_input", False):
        args.set = [*args.set, "ros2.input.enabled=true"]
    rate = args.rate if getattr(args, "rate", 0.0) > 0 else (1.0 if args.realtime else 0.0)
    res = run_pipeline(dataset, out, args.config, args.set, rate=rate, record=args.record,
                       saved_map=str(Path(saved).resolve()) if saved else None,
                       localise_only=getattr(args, "localise_only", False), gt=gt, player_args=args.player_arg,
                       settle_s=args.settle_s, timeout_s=args.timeout_s, final_timeout_s=args.final_timeout_s)
    rc = res.rc
    if gt is None and getattr(args, "gt", None) != "none" and res.stats.get("poses", 0) >= 3:
        print("[sigmaslam run] no ground truth (none of " + ", ".join(GT_CANDIDATES) + " in the dataset, no --gt): "
              "no ATE", flush=True)
    if getattr(args, "ros2_bag", None):
        rc = _ros2_bag(out, args.ros2_bag) or rc
    if getattr(args, "serve_s", 0.0) > 0:
        from services.app.demo_serve import serve_run
        from services.app.system_config import load_system_config

        viewer = load_system_config(args.config, args.set).viewer
        print(f"[sigmaslam run] serving the final map at http://{viewer.host}:{viewer.port} for {args.serve_s:.0f} s "
              "(Ctrl-C stops)", flush=True)
        serve_run(out, args.config, [*([f"viewer.ground_truth={gt}"] if gt else []), *args.set], args.serve_s)
    return rc


def _ros2_bag(out: Path, bag: str) -> int:
    """The results as a ROS 2 bag (services/app/datasets/ros2_export.py); 1 when it cannot be written."""
    from services.app.datasets.ros2_export import recording_to_ros2

    try:
        counts = recording_to_ros2(out / "recording.mcap", bag)
        print(f"[sigmaslam run] ROS 2 bag {bag}: " + ", ".join(f"{k} {v}" for k, v in counts.items()), flush=True)
    except (OSError, ValueError) as exc:
        print(f"[sigmaslam run] ROS 2 bag not written: {exc}", flush=True)
        return 1
    return 0
