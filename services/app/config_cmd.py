"""``sigmaslam config``: show the resolved config (or the documented defaults)."""

from __future__ import annotations

import argparse
import os
import sys

from services.app.system_config import SystemConfig, load_system_config
from shared.config import describe, to_yaml


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="YAML config file (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a field, e.g. transport.namespace=sigmaslam/r2")
    p.add_argument("--defaults", action="store_true", help="print every field with default, unit and docstring")


def main(args: argparse.Namespace) -> int:
    text = describe(SystemConfig) + "\n" if args.defaults else to_yaml(load_system_config(args.config, args.set))
    try:
        sys.stdout.write(text)
        sys.stdout.flush()
    except BrokenPipeError:  # e.g. `sigmaslam config --defaults | head`: the reader left, nothing to report
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0
