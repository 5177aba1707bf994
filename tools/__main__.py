"""Developer commands, run from a checkout (tools/ is not installed with the product):

    python -m tools bench pipeline|transport|netns|mapping|mapping-ablation|query ...   # benchmarks (tools/bench_cmd.py)
    python -m tools eval depth|stereo ...                                          # depth network evaluations

Each other developer script runs as its own module (``python -m tools.depth.train``, ``python -m tools.vio.offline``,
...: tools/README.md). The product's commands are ``sigmaslam ...`` (services/app/cli.py).
"""

from __future__ import annotations

import argparse
import logging
import sys

from services.app.cli import add_module_commands, run_module_command

# name -> (module, one-line help); each module provides add_arguments(parser) and main(args) -> int
COMMANDS: dict[str, tuple[str, str]] = {
    "bench": ("tools.bench_cmd", "benchmarks: transport, netns, mapping, mapping-ablation, query, pipeline (live budgets)"),
    "eval": ("tools.eval_cmd", "developer evaluations: depth (networks against GT), stereo (real photographs)"),
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools", description="sigmaslam's developer commands")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    add_module_commands(parser, COMMANDS, dest="command", metavar="COMMAND")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return run_module_command(args)


if __name__ == "__main__":
    sys.exit(main())
