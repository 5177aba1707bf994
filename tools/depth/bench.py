"""CPU time of the depth stages per 512x384 frame, median over ``--runs`` runs: SGBM, stereo network,
MVS network (as the service runs it: reference encoded, source features cached), fusion.

    .venv/bin/python -m tools.depth.bench --runs 50 --threads 1

Reports process CPU time (what the stage costs on one core, robust on a shared machine) and wall time.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from services.depth import weights
from services.depth.sgbm import sgbm_depth
from services.depth.uncertainty import disparity_to_depth, fuse, logdepth_to_depth
from tools.depth.make_dataset import BASELINE_M, K_RECT


def _time(fn, runs: int) -> dict[str, float]:
    fn()  # warm-up
    cpu, wall = [], []
    for _ in range(runs):
        c, w = time.process_time(), time.perf_counter()
        fn()
        cpu.append(time.process_time() - c)
        wall.append(time.perf_counter() - w)
    return {"cpu_ms": float(np.median(cpu) * 1e3), "wall_ms": float(np.median(wall) * 1e3)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=50)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--sources", type=int, default=4)
    p.add_argument("--stereo-weights", default=str(weights.WEIGHTS_DIR / weights.DEFAULT_STEREO),
                   help="stereo weights to time (an SGBM-guided network's time includes its SGBM)")
    p.add_argument("--precision", choices=("float32", "bfloat16"), default="float32",
                   help="the stereo network's arithmetic (depth.stereo_precision; MVS stays float32)")
    p.add_argument("--out", default="out/depth/bench.json")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    rng = np.random.default_rng(0)
    left = rng.integers(0, 255, (384, 512), dtype=np.uint8)
    right = np.roll(left, -8, axis=1)
    st, st_meta = weights.load(a.stereo_weights)
    mv, mv_meta = weights.load(weights.WEIGHTS_DIR / "mvs.pt")
    t = lambda x: torch.from_numpy(np.asarray(x)).float()
    K = t(K_RECT)[None]
    T = torch.eye(4).repeat(1, a.sources, 1, 1)
    T[0, :, 0, 3] = torch.linspace(-0.1, 0.1, a.sources)
    with torch.inference_mode():
        f_src = torch.cat([mv.encoder(t(left)[None, None])[0] for _ in range(a.sources)])[None]

        def stereo():
            with weights.inference("cpu", a.precision):
                u, su = (x.float() for x in st(t(left)[None, None], t(right)[None, None]))
            return disparity_to_depth(u[0].numpy(), su[0].numpy() * st_meta["gain"], K_RECT[0, 0], BASELINE_M)

        def mvs():
            f_ref, ctx = mv.encoder(t(left)[None, None])
            ld, sl = mv.forward_features(f_ref, ctx, f_src, K, T, None, left.shape)
            return logdepth_to_depth(ld[0].numpy(), sl[0].numpy() * mv_meta["gain"])

        d1, d2 = stereo(), mvs()
        res = {"sgbm": _time(lambda: sgbm_depth(left, right, K_RECT[0, 0], BASELINE_M), a.runs),
               "stereo_net": _time(stereo, a.runs), "mvs_net": _time(mvs, a.runs),
               "fusion": _time(lambda: fuse(*d1, *d2), a.runs)}
    res["total_networks_fusion"] = {k: res["stereo_net"][k] + res["mvs_net"][k] + res["fusion"][k] for k in ("cpu_ms", "wall_ms")}
    res["config"] = {"stereo_weights": a.stereo_weights, "stereo_arch": st_meta["arch"], "runs": a.runs, "threads": a.threads, "precision": a.precision, "sources": a.sources, "size": [512, 384],
                     "torch": torch.__version__}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1))
    for k, v in res.items():
        if k != "config":
            print(f"{k:24s} cpu {v['cpu_ms']:7.1f} ms   wall {v['wall_ms']:7.1f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
