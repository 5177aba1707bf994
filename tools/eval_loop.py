"""Loop closure and the final bundle adjustment on an EuRoC folder, in one process, no transport.

    python -m tools.eval_loop DATASET [--max-frames N] [--set loop.x=y] [--no-loop] [--out DIR]

Frontend + back end with loop closure (services/app/eval/loop_eval.py: the processes' own nodes on the in-process
runner, in the order of a lockstep run, keyframe descriptors before their frame). Prints the causal ATE of the raw
window estimate and of the published (pose-graph corrected) poses, the non-causal ATE after the final BA, loop
counts, and the back end's per-frame time (median, p99; wall and this thread's CPU). ``--out`` writes trajectory_causal.txt and trajectory_final.txt (TUM)
and eval_loop.json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.app.eval.loop_eval import evaluate_loop
from shared.euroc import write_tum


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset")
    p.add_argument("--set", action="append", default=[])
    p.add_argument("--max-frames", type=int, default=0)
    p.add_argument("--no-loop", action="store_true")
    p.add_argument("--out")
    a = p.parse_args()
    res, trajs = evaluate_loop(a.dataset, a.set, a.max_frames, not a.no_loop)
    print(json.dumps(res, indent=1, default=str), flush=True)
    if a.out:
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        write_tum(out / "trajectory_causal.txt", trajs["causal"])
        if "final" in trajs:
            write_tum(out / "trajectory_final.txt", trajs["final"])
        (out / "eval_loop.json").write_text(json.dumps(res, indent=1, default=str))


if __name__ == "__main__":
    main()
