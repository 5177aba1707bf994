"""Alias of ``sigmaslam eval ablation`` (services/app/eval/ablation.py), kept for old command lines:

    python -m tools.o2p_ablation [REPLICA ...] [--rows ...] [--seconds S] [--set k=v] [--out DIR]

(``--depth-every N`` is gone: ``--set depth.rate_hz=20/N``, see services/app/eval/ablation.py.)
"""

from __future__ import annotations

import sys

from services.app.cli import main

if __name__ == "__main__":
    sys.exit(main(["eval", "ablation", *sys.argv[1:]]))
