"""The ``sigmaslam`` command. Each subcommand lives in its own module, imported only when used.

A subcommand module provides ``add_arguments(parser)`` and ``main(args) -> int``. To add one, add a
line to :data:`SUBCOMMANDS`.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

# name -> (module, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "config": ("services.app.config_cmd", "print the resolved config or the documented defaults"),
    "router": ("services.app.router", "run the Zenoh router that services connect to"),
    "bench": ("tools.bench_cmd", "benchmarks: transport, netns, mapping, mapping-ablation, pipeline (live budgets)"),
    "up": ("services.app.up_cmd", "run the router and all configured services, restarting failed ones"),
    "health": ("services.app.health_cmd", "exit 0 when a service's heartbeat (or the router) is seen on the bus"),
    "record": ("services.recorder.service", "record topics to MCAP (with Foxglove mirrors); --recover a cut file"),
    "synth": ("services.app.synth.synth_cmd", "render a synthetic EuRoC replica (images, GT depth, mesh, IMU) of a real sequence"),
    "convert": ("tools.dataset_convert", "convert a dataset: EuRoC ASL folder <-> sigmaslam MCAP recording"),
    "frontend": ("services.frontend.service", "feature tracker and per-frame fast path: sensors/frame + sensors/imu + "
                 "estimator/window -> estimator/state, frontend/frame"),
    "backend": ("services.backend.service", "visual-inertial window estimator: keyframes of frontend/frame + sensors/imu "
                "-> estimator/window, keyframes, landmarks"),
    "player": ("services.player.service", "replay an EuRoC ASL folder onto the sensor topics (--lockstep, --realtime)"),
    "demo": ("services.app.demo_cmd", "the README's main job: the whole pipeline on the bundled replica, with its figures"),
    "run": ("services.app.run_cmd", "run the pipeline on a dataset; write the trajectory, stats and ATE to --out DIR"),
    "viewer": ("services.viewer.service", "web viewer (viser): submap meshes, trajectories, live images, stats"),
    "depth": ("services.depth.service", "stereo + MVS depth with learned sigma, fused: sensors/frame -> depth/stereo, depth/fused"),
    "mapping": ("services.mapping.service", "occupancy submapping: depth + estimator poses -> map/submap meshes"),
    "map": ("services.app.map_cmd", "saved maps: info DIR (what a map holds), merge A B OUT (one map of two)"),
    "eval": ("services.app.eval_cmd", "evaluations against ground truth: ate, mesh, depth, hilti, ablation (Table IV), suite"),
}


def add_module_commands(p: argparse.ArgumentParser, table: dict[str, tuple[str, str]], dest: str,
                        metavar: str) -> None:
    """Sub-subcommands of ``p`` from a table name -> (module, help), as ``eval`` and ``bench`` have; each module
    provides ``add_arguments(parser)`` and ``main(args)``. :func:`run_module_command` calls the chosen one."""
    sub = p.add_subparsers(dest=dest, metavar=metavar, required=True)
    for name, (module, help_text) in table.items():
        q = sub.add_parser(name, help=help_text, description=help_text)
        q.set_defaults(_sub_module=module)
        importlib.import_module(module).add_arguments(q)


def run_module_command(args: argparse.Namespace) -> int:
    return int(importlib.import_module(args._sub_module).main(args) or 0)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="sigmaslam", description="Uncertainty-aware visual-inertial SLAM over Zenoh")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    chosen = next((a for a in argv if not a.startswith("-")), None)
    for name, (module, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        if name == chosen:
            importlib.import_module(module).add_arguments(p)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not args.command:
        parser.print_help()
        return 2
    from shared.config import ConfigError

    try:
        return int(importlib.import_module(args._module).main(args) or 0)
    except ConfigError as exc:
        print(f"sigmaslam {args.command}: config error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
