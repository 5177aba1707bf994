"""``sigmaslam eval <what>``: evaluations against ground truth. To add one, add a line to :data:`EVALS`;
the module provides ``add_arguments(parser)`` and ``main(args) -> int``."""

from __future__ import annotations

import argparse

from services.app.cli import add_module_commands, run_module_command

# name -> (module, one-line help)
EVALS: dict[str, tuple[str, str]] = {
    "ate": ("services.app.eval_ate_cmd", "ATE RMSE after SE(3)/Sim(3)/position+yaw alignment: --gt GT --est EST (TUM or EuRoC CSV)"),
    "mesh": ("services.app.eval_mesh_cmd", "mesh accuracy (mean est->GT distance) and completeness (GT within 0.2 m), paper sec. V"),
    "depth": ("tools.depth.evaluate", "depth + sigma of SGBM, stereo/MVS networks and their fusion against GT: table, calibration plot, CPU time"),
    "hilti": ("services.app.eval_hilti_cmd", "Hilti 2022 score from sparse control points (--control CSV, or sampled from --dataset GT)"),
    "ablation": ("tools.eval.ablation", "the paper's Table IV (o2p factors, depth sigma, fusion) + mono-inertial rows on replicas, in one process: markdown table"),
    "stereo": ("tools.depth.stereo_bench", "stereo network vs SGBM on real photographs with GT (Middlebury folders): EPE, bad-k, sigma calibration"),
    "relocalise": ("tools.eval.relocalise", "map one replica, localise another in its saved map: share localised, time to "
                   "relocalise, ATE in the map's frame"),
    "suite": ("tools.eval.suite", "the paper's tables I, II, V on replicas (runs the pipeline per sequence): markdown + PNG report"),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_module_commands(p, EVALS, dest="eval", metavar="WHAT")


def main(args: argparse.Namespace) -> int:
    return run_module_command(args)
