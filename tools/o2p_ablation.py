"""Alias of ``sigmaslam eval ablation`` (tools/eval/ablation.py), kept for old command lines:

    python -m tools.o2p_ablation [REPLICA ...] [--rows ...] [--seconds S] [--depth-every N] [--set k=v] [--out DIR]
"""

from __future__ import annotations

import sys

from services.app.cli import main

if __name__ == "__main__":
    sys.exit(main(["eval", "ablation", *sys.argv[1:]]))
