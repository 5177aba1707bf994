"""The ``sigmaslam`` command. Each subcommand lives in its own module, imported only when used.

Two kinds of subcommand: the application's commands (:data:`APP_COMMANDS`: a module providing
``add_arguments(parser)`` and ``main(args) -> int``; to add one, add a line) and one command per process of the
registry (services/app/processes.py), all run by the one generic entry services/app/process_cmd.py.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

# name -> (module, one-line help)
APP_COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("services.app.run_cmd", "run the pipeline on a dataset; write the trajectory, stats and ATE to --out DIR"),
    "demo": ("services.app.demo_cmd", "the README's main job: the whole pipeline on the bundled replica, with its figures"),
    "up": ("services.app.up_cmd", "run the router and all configured services, restarting failed ones"),
    "router": ("services.app.router", "run the Zenoh router that services connect to"),
    "config": ("services.app.config_cmd", "print the resolved config or the documented defaults"),
    "health": ("services.app.health_cmd", "exit 0 when a service's heartbeat (or the router) is seen on the bus"),
    "eval": ("services.app.eval.cmd", "evaluations against ground truth: ate, mesh, hilti, ablation (Table IV), suite (the "
             "paper's tables), relocalise"),
    "map": ("services.app.map_cmd", "saved maps: info DIR (what a map holds), merge A B OUT (one map of two), grid DIR "
                                    "(2D occupancy grid), export DIR (occupancy voxels)"),
    "synth": ("services.app.synth.synth_cmd", "render a synthetic EuRoC replica (images, GT depth, mesh, IMU) of a real sequence"),
    "convert": ("services.app.datasets.convert_cmd", "convert a dataset: EuRoC ASL folder <-> sigmaslam MCAP recording; ROS "
                "bag -> EuRoC folder"),
}


def command_names() -> list[str]:
    """Every ``sigmaslam`` subcommand: the application's and the processes'."""
    from services.app.processes import PROCESSES

    return [*APP_COMMANDS, *(d.cli_command for d in PROCESSES)]


def add_command_arguments(p: argparse.ArgumentParser, name: str) -> None:
    """The arguments of ``sigmaslam <name>`` on ``p`` (an application command's module, or a process's description)."""
    if name in APP_COMMANDS:
        importlib.import_module(APP_COMMANDS[name][0]).add_arguments(p)
        return
    from services.app import process_cmd
    from services.app.processes import by_command

    d = by_command(name)
    if d is None:
        raise KeyError(f"{name!r} is not a sigmaslam command ({', '.join(command_names())})")
    process_cmd.add_arguments(p, d)


def command_parser(name: str, **kwargs) -> argparse.ArgumentParser:
    """The parser of ``sigmaslam <name>`` alone (``kwargs``: argparse.ArgumentParser's)."""
    p = argparse.ArgumentParser(prog=f"sigmaslam {name}", **kwargs)
    add_command_arguments(p, name)
    return p


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
    from services.app import process_cmd
    from services.app.processes import PROCESSES

    for name, (module, help_text) in APP_COMMANDS.items():
        sub.add_parser(name, help=help_text, description=help_text).set_defaults(_module=module, _process=None)
    for d in PROCESSES:
        sub.add_parser(d.cli_command, help=d.help, description=d.help).set_defaults(_process=d)
    if chosen in sub.choices:
        add_command_arguments(sub.choices[chosen], chosen)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not args.command:
        parser.print_help()
        return 2
    from shared.config import ConfigError

    try:
        if args._process is not None:
            return process_cmd.main(args, args._process)
        return int(importlib.import_module(args._module).main(args) or 0)
    except ConfigError as exc:
        print(f"sigmaslam {args.command}: config error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
