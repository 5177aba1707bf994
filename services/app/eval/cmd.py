"""``sigmaslam eval <what>``: evaluations against ground truth, the paper's tables among them. To add one, add a line
to :data:`EVALS`; the module provides ``add_arguments(parser)`` and ``main(args) -> int``. The developers' own
evaluations (depth networks, real-photograph stereo) are ``python -m tools eval ...``."""

from __future__ import annotations

import argparse

from services.app.cli import add_module_commands, run_module_command

# name -> (module, one-line help)
EVALS: dict[str, tuple[str, str]] = {
    "ate": ("services.app.eval.ate_cmd", "ATE RMSE after SE(3)/Sim(3)/position+yaw alignment: --gt GT --est EST (TUM or EuRoC CSV)"),
    "mesh": ("services.app.eval.mesh_cmd", "mesh accuracy (mean est->GT distance) and completeness (GT within 0.2 m), paper sec. V"),
    "hilti": ("services.app.eval.hilti_cmd", "Hilti 2022 score from sparse control points (--control CSV, or sampled from --dataset GT)"),
    "occupancy": ("services.app.eval.occupancy_cmd", "false free and free recall of a run's occupancy map and 2D grid "
                  "against its replica's scene mesh: RUN_DIR --replica R"),
    "ablation": ("services.app.eval.ablation", "the paper's Table IV (o2p factors, depth sigma, fusion) + mono-inertial rows on replicas, in one process: markdown table"),
    "relocalise": ("services.app.eval.relocalise", "map one replica, localise another in its saved map: share localised, time to "
                   "relocalise, ATE in the map's frame"),
    "suite": ("services.app.eval.suite", "the paper's tables I, II, V on replicas (runs the pipeline per sequence): markdown + PNG report"),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_module_commands(p, EVALS, dest="eval", metavar="WHAT")


def main(args: argparse.Namespace) -> int:
    return run_module_command(args)
