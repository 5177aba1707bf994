"""``sigmaslam config``: show the resolved config (or the documented defaults)."""

from __future__ import annotations

import argparse

from services.system_config import SystemConfig, load_system_config
from shared.config import describe, to_yaml


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="YAML config file (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a field, e.g. transport.namespace=sigmaslam/r2")
    p.add_argument("--defaults", action="store_true", help="print every field with default, unit and docstring")


def main(args: argparse.Namespace) -> int:
    if args.defaults:
        print(describe(SystemConfig))
        return 0
    print(to_yaml(load_system_config(args.config, args.set)), end="")
    return 0
