"""``python -m tools bench <name>``: benchmarks of the system, each in its own module under tools/.

To add one, add a line to :data:`BENCHES`; the module provides ``add_arguments(parser)`` and ``main(args) -> int``.
"""

from __future__ import annotations

import argparse

from services.app.cli import add_module_commands, run_module_command

# name -> (module, one-line help)
BENCHES: dict[str, tuple[str, str]] = {
    "transport": ("tools.bench_transport", "Zenoh round-trip latency and 786 KB frame latency/rate, SHM on and off"),
    "netns": ("tools.bench_netns", "estimator/state and depth/fused latency across network namespaces (via a router) vs one host"),
    "mapping": ("tools.bench_mapping", "occupancy integration ms per 512x384 depth frame, memory, mesh accuracy on a replica"),
    "mapping-ablation": ("tools.mapping_ablation", "map accuracy/completeness from GT, stereo (heuristic/learned sigma) and fused depth at GT poses"),
    "query": ("tools.bench_query", "100 000 occupancy point queries over map/query while the pipeline runs live: round trip and "
              "mapping-side median/p99 (--saved DIR: in-process on a saved map)"),
    "pipeline": ("tools.bench_pipeline", "whole pipeline at sensor rate: per-stage compute, latency to state/depth/map, CPU/RSS, budgets; --max-rate"),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_module_commands(p, BENCHES, dest="bench", metavar="BENCH")


def main(args: argparse.Namespace) -> int:
    return run_module_command(args)
