"""``python -m tools.compose_smoke``: `docker compose up` for real, on the default replica, with host networking.

What it does is what docs/deployment.md ("Docker compose", host networking) tells a user to do:

1. an engine: the one that answers, else ``dockerd --bridge=none --iptables=false`` started here (root), stopped at
   the end (tools/compose_smoke/engine.py);
2. the base image: cached, else pulled, else a stand-in built from Debian packages (base_image.py);
3. ``docker build --network host -f docker/Dockerfile -t sigmaslam:cpu .``, the Dockerfile unmodified; pip in the
   build reaches this machine's pip sources (pip_sources.py); torch from the PyTorch CPU index where it answers,
   else from pip's own sources;
4. the default replica (``sigmaslam synth --default``), the output folders made first and given to the services'
   user, then ``compose -f docker/compose.yaml -f docker/compose.host.yaml up`` under its own project name;
5. checks: every service healthy, the player exits 0, the viewer answers 200 on 127.0.0.1, the back end's final
   trajectory and sparse map, the mapper's mesh and submaps; then Ctrl-C (SIGINT to compose) must stop everything
   with exit code 0, and no container may have been restarted;
6. ``compose down --volumes``: containers, networks and volumes go; images stay cached for the next run.

Exit 0 when it passes, 1 when it fails, 0 with a line saying why when no engine can be had (skipped).
Figures (times, image size, frames) are printed and written to ``out/compose-smoke/summary.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from tools.compose_smoke.run import SmokeFailed, Skipped, smoke


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tools.compose_smoke", description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, default=Path("out/compose-smoke"),
                   help="folder for the run's outputs, recording, logs and summary.json")
    p.add_argument("--timeout-s", type=float, default=900.0, help="longest time from `up` to the player's end [s]")
    p.add_argument("--keep-recording", action="store_true", help="keep the run's MCAP recording (about 0.5 GB)")
    args = p.parse_args(argv)
    t0 = time.monotonic()
    try:
        summary = smoke(args.work.resolve(), args.timeout_s, args.keep_recording)
    except Skipped as exc:
        print(f"[compose-smoke] SKIPPED: {exc}", flush=True)
        return 0
    except SmokeFailed as exc:
        print(f"[compose-smoke] FAILED after {time.monotonic() - t0:.0f} s: {exc}", flush=True)
        return 1
    print(json.dumps(summary, indent=1), flush=True)
    print(f"[compose-smoke] compose smoke test PASSED in {time.monotonic() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
