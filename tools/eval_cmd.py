"""``python -m tools eval <what>``: the developers' evaluations (the product's are ``sigmaslam eval``). To add one,
add a line to :data:`EVALS`; the module provides ``add_arguments(parser)`` and ``main(args) -> int``."""

from __future__ import annotations

import argparse

from services.app.cli import add_module_commands, run_module_command

# name -> (module, one-line help)
EVALS: dict[str, tuple[str, str]] = {
    "depth": ("tools.depth.evaluate", "depth + sigma of SGBM, stereo/MVS networks and their fusion against GT: table, "
              "calibration plot, CPU time"),
    "stereo": ("tools.depth.stereo_bench", "stereo network vs SGBM on real photographs with GT (Middlebury folders): "
               "EPE, bad-k, sigma calibration"),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_module_commands(p, EVALS, dest="eval", metavar="WHAT")


def main(args: argparse.Namespace) -> int:
    return run_module_command(args)
