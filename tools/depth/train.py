"""Train a depth network (stereo: eq. 8-10; MVS: eq. 12) on the rendered set, calibrate its sigma on the
validation split (sec. V-A, one gain in the depth domain) and write weights + provenance JSON.

    nice .venv/bin/python -m tools.depth.train --net stereo --minutes 20 --data data/depth_train \
        --out services/depth/weights/stereo
    nice .venv/bin/python -m tools.depth.train --net mvs --minutes 20 ...
    nice .venv/bin/python -m tools.depth.train --net stereo_refine --data data/stereo_train --crop 256 320 \
        --out services/depth/weights/stereo_refine     # the layered set of tools/depth/make_stereo_data.py

Training stops after ``--minutes`` of process CPU time or ``--max-wall-minutes`` of wall time, whichever
comes first (the learning rate follows a cosine over that progress; on a shared machine CPU time is the
reproducible measure, on a fast machine more steps fit). Runs on CUDA
when present (``--device``). Curves go to ``<out>.curve.csv``.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import torch

from services.depth import weights
from services.depth.losses import mvs_loss, stereo_loss
from services.depth.uncertainty import (calibration_gain, depth_metrics, disparity_to_depth, gain_from_ratios,
                                       logdepth_to_depth)
from services.depth.views import select_sources


def load_split(root: Path, split: str, loaded: list[dict] | None = None) -> list[dict]:
    """The readable scenes of a split; ``loaded``: scenes read before, kept as they are (only new files are read)."""
    files = sorted(f for f in (root / split).glob("scene_*.npz") if not f.name.endswith(".tmp.npz"))
    if not files:
        raise SystemExit(f"{root / split}: no scene_*.npz (render them: python -m tools.depth.make_dataset)")
    scenes = list(loaded or [])
    known = {s["name"] for s in scenes}
    for f in (f for f in files if f.stem not in known):
        try:
            scenes.append(dict(np.load(f)) | {"name": f.stem})
        except (OSError, ValueError, zipfile.BadZipFile) as e:  # half-written by a render still running, or corrupt
            print(f"[train] skipping unreadable {f}: {e}", flush=True)
    if not scenes:
        raise SystemExit(f"{root / split}: no readable scene")
    return scenes


def _crop_box(rng, H, W, ch, cw):
    y = int(rng.integers(0, H - ch + 1)) // 4 * 4
    x = int(rng.integers(0, W - cw + 1)) // 4 * 4
    return y, x


def _photometric(rng, img: np.ndarray) -> np.ndarray:
    return np.clip(img.astype(np.float32) * rng.uniform(0.7, 1.3) + rng.uniform(-20, 20), 0, 255)


def stereo_batch(scenes, rng, batch: int, crop: tuple[int, int]):
    ch, cw = crop
    L, R, U = [], [], []
    for _ in range(batch):
        s = scenes[rng.integers(len(scenes))]
        i = rng.integers(len(s["left"]))
        H, W = s["left"].shape[1:]
        y, x = _crop_box(rng, H, W, ch, cw)
        sl = np.s_[y:y + ch, x:x + cw]
        gain = rng.uniform(0.9, 1.1)  # small left/right exposure difference
        L.append(_photometric(rng, s["left"][i][sl]))
        R.append(np.clip(_photometric(rng, s["right"][i][sl]) * gain, 0, 255))
        d = s["depth"][i][sl]
        U.append(float(s["K"][0, 0]) * float(s["baseline_m"]) / np.where(np.isfinite(d) & (d > 0), d, np.inf))
    t = lambda a: torch.from_numpy(np.stack(a)).float()
    return t(L)[:, None], t(R)[:, None], t(U)


def prior_points(rng, depth: np.ndarray, n: int, rel_noise: float = 0.02) -> np.ndarray:
    """Sparse depth prior like the estimator's landmarks: n random pixels of GT depth with relative noise."""
    prior = np.zeros_like(depth)
    if n <= 0:
        return prior
    ok = np.flatnonzero(np.isfinite(depth.ravel()))
    idx = rng.choice(ok, size=min(n, len(ok)), replace=False)
    prior.ravel()[idx] = depth.ravel()[idx] * (1 + rel_noise * rng.standard_normal(len(idx)))
    return prior


def mvs_sample(s, rng, i: int, n_src: int, crop=None, photometric=True, prior_n=None):
    T = s["T_WC"]
    others = np.array([j for j in range(len(T)) if j != i])
    order = others[np.argsort(np.abs(others - i))[::-1]]  # farthest in time first, nearest last (= "newest")
    chosen = order[select_sources(T[i], T[order], n_src, 0.03, 1.0, 40.0)]
    if len(chosen) == 0:
        chosen = order[-1:]
    K = s["K"].copy()
    H, W = s["left"].shape[1:]
    sl = np.s_[:, :]
    if crop is not None:
        y, x = _crop_box(rng, H, W, *crop)
        sl = np.s_[y:y + crop[0], x:x + crop[1]]
        K[0, 2] -= x
        K[1, 2] -= y
    prep = (lambda a: _photometric(rng, a)) if photometric else (lambda a: a.astype(np.float32))
    ref = prep(s["left"][i][sl])
    src = np.stack([prep(s["left"][j][sl]) for j in chosen])
    T_src_ref = np.stack([np.linalg.inv(T[j]) @ T[i] for j in chosen])
    depth = s["depth"][i][sl]
    n_prior = prior_n if prior_n is not None else (0 if rng.random() < 0.3 else int(rng.integers(20, 300)))
    return ref, src, K, T_src_ref, prior_points(rng, depth, n_prior), depth


def mvs_batch(scenes, rng, batch: int, crop, n_src: int):
    items = []
    for _ in range(batch):
        s = scenes[rng.integers(len(scenes))]
        items.append(mvs_sample(s, rng, int(rng.integers(len(s["left"]))), n_src, crop))
    n = min(len(it[1]) for it in items)
    t = lambda k, sl=None: torch.from_numpy(np.stack([it[k] if sl is None else it[k][:n] for it in items])).float()
    return t(0)[:, None], t(1, True)[:, :, None], t(2), t(3, True), t(4), t(5)


def predict(net, kind, s, i, rng, n_src, device):
    """(depth, sigma) [m] of frame i of scene s at full resolution, uncalibrated."""
    with torch.inference_mode():
        if kind == "stereo":
            u, su = net(torch.from_numpy(s["left"][i]).float()[None, None].to(device),
                        torch.from_numpy(s["right"][i]).float()[None, None].to(device))
            return disparity_to_depth(u[0].cpu().numpy(), su[0].cpu().numpy(), float(s["K"][0, 0]),
                                      float(s["baseline_m"]))
        ref, src, K, T, prior, _ = mvs_sample(s, rng, i, n_src, None, photometric=False, prior_n=150)
        f = lambda a: torch.from_numpy(np.asarray(a)).float()[None].to(device)
        ld, sl = net(f(ref)[:, None], f(src)[:, :, None], f(K), f(T), f(prior))
        return logdepth_to_depth(ld[0].cpu().numpy(), sl[0].cpu().numpy())


def evaluate(net, kind, scenes, n_src, device, gain=1.0, seed=7):
    rng = np.random.default_rng(seed)
    est, sig, gt = [], [], []
    for s in scenes:
        for i in range(0, len(s["left"]), 2):
            d, sd = predict(net, kind, s, i, rng, n_src, device)
            est.append(d)
            sig.append(sd * gain)
            gt.append(s["depth"][i])
    return np.stack(est), np.stack(sig), np.stack(gt)


REFINE_GAIN_DOMAIN = "disparity sigma [px] (median |u - u_gt| / (gain sigma_u) = ln 2 on val, all pixels)"


def check_hole_fill(root: Path, hole_fill: str) -> dict:
    """The data's precomputed hole fill (``fill.json`` of tools/depth/stereo_shards.add_fill) must be the one the
    network is trained for: the weights given by --hole-fill, or none. Returns what to record in the weights' JSON."""
    from tools.depth.stereo_shards import fill_source, same_weights

    data_fill = fill_source(root)
    if hole_fill and not (data_fill and same_weights(data_fill, hole_fill)):
        raise SystemExit(f"--hole-fill {hole_fill}: {root} has {'a fill from ' + data_fill if data_fill else 'no fill'}"
                         f" (python -m tools.depth.stereo_shards {root} --fill-weights {hole_fill})")
    if data_fill and not hole_fill:
        raise SystemExit(f"{root} has SGBM's holes filled by {data_fill}: train with --hole-fill {data_fill}, or use "
                         "data without fill.npy")
    return {"hole_fill_weights": hole_fill} if hole_fill else {}


def evaluate_refine(net, shards, device, rule: str = "median") -> tuple[float, dict]:
    """The SGBM-guided network on validation frames: (disparity-domain gain by ``rule``
    (services.depth.uncertainty.gain_from_ratios), metrics before and after it)."""
    from tools.depth.stereo_bench import disparity_metrics
    from tools.depth.stereo_shards import initial_disparity, validation_frames

    errs, sigmas, rows = [], [], []
    with torch.inference_mode():
        for f in validation_frames(shards):
            t = lambda a: torch.from_numpy(np.ascontiguousarray(a))[None].to(device)
            u, su = net.refine(t(f["left"]).float()[:, None], t(f["right"]).float()[:, None],
                               t(initial_disparity(f)).float(), t(np.isfinite(f["sgbm"])))
            u, su = u[0].cpu().numpy(), su[0].cpu().numpy()
            rows.append(disparity_metrics(u, su, f["disparity"], f["nonocc"]))
            errs.append(np.abs(u - f["disparity"]).ravel())
            sigmas.append(su.ravel())
    e, s = np.concatenate(errs), np.concatenate(sigmas)
    gain = gain_from_ratios(e / s, rule)
    mean = lambda k: float(np.mean([r[k] for r in rows]))
    metrics = {"frames": len(rows), "epe_nonocc": mean("epe"), "bad2_nonocc": mean("bad2"),
               "epe_all": float(e.mean()), "err_over_sigma_all": float(np.mean(e / s)), "gain_rule": rule,
               "err_over_sigma_all_calibrated": float(np.mean(e / (gain * s))),
               "within2s_all_calibrated": float(100 * np.mean(e / (gain * s) < 2))}
    return gain, metrics


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--net", choices=["stereo", "mvs", "stereo_refine"], required=True)
    p.add_argument("--data", default="data/depth_train")
    p.add_argument("--out", required=True, help="weights path without suffix, e.g. services/depth/weights/stereo")
    p.add_argument("--minutes", type=float, default=20.0, help="CPU-time budget of the training loop (process time)")
    p.add_argument("--max-wall-minutes", type=float, default=60.0, help="hard wall-time cap of the training loop")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--crop", type=int, nargs=2, default=[192, 320], metavar=("H", "W"))
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--sources", type=int, default=4, help="MVS source views per sample")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--real-pairs", nargs="*", default=[], help="stereo_refine: unlabelled real pair folders (ETH3D "
                   "two-view, EuRoC) to adapt on with SGBM proxy labels (tools/depth/real_pairs.py); never Middlebury")
    p.add_argument("--real-weight", type=float, default=0.5, help="weight of the real pairs' proxy loss")
    p.add_argument("--checkpoint-minutes", type=float, default=10.0,
                   help="write <out>_partial.pt (uncalibrated) this often while training; 0: never")
    p.add_argument("--hole-fill", default="", help="stereo_refine: the stereo network (weights) whose disparity fills "
                   "SGBM's holes, as precomputed in the data (python -m tools.depth.stereo_shards DATA --fill-weights W)"
                   "; held inside the new weights (arch_args hole_fill: stereo_net). Default: from the background side")
    p.add_argument("--init", default="", help="start from these weights (same architecture), e.g. to fine-tune")
    p.add_argument("--loader-workers", type=int, default=0, help="stereo_refine: processes that cut the training "
                   "crops (0: in the training loop; a GPU needs several). Shards rendered after the start are not used")
    a = p.parse_args(argv)
    torch.manual_seed(a.seed)
    cuda = a.device.startswith("cuda")
    if cuda:
        torch.backends.cudnn.benchmark = True  # fixed crop size: let cuDNN pick its fastest convolutions once
    torch.set_num_threads(a.threads)
    rng = np.random.default_rng(a.seed)
    root = Path(a.data)
    real = []
    if a.net == "stereo_refine":
        from tools.depth.real_pairs import load_real_pairs, proxy_loss, real_batch
        from tools.depth.stereo_shards import RefineBatches, load_shards, refine_batch, shard_dirs

        train = load_shards(root, "train")
        if a.loader_workers > 0:
            loader = iter(torch.utils.data.DataLoader(
                RefineBatches(root, a.batch, tuple(a.crop), a.seed), batch_size=None, num_workers=a.loader_workers,
                pin_memory=cuda, prefetch_factor=4, persistent_workers=True))
        real = load_real_pairs(a.real_pairs) if a.real_pairs else []
        if real:
            print(f"[{a.net}] {len(real)} real pairs for the proxy loss", flush=True)
    elif a.real_pairs:
        raise SystemExit("--real-pairs is for --net stereo_refine")
    else:
        train = load_split(root, "train")
        if a.net == "stereo" and any("right" not in s for s in train):
            raise SystemExit(f"--net stereo: {root}/train has scenes without right views (rendered --left-only, "
                             "for the MVS network)")
    arch_args = {"n_planes": 32, "min_depth": 0.3, "max_depth": 15.0} if a.net == "mvs" else {"max_disparity": 96}
    fill_meta = {}
    if a.net == "stereo_refine":
        fill_meta = check_hole_fill(root, a.hole_fill)
        if a.hole_fill:
            arch_args["hole_fill"] = "stereo_net"
    elif a.hole_fill:
        raise SystemExit("--hole-fill is for --net stereo_refine")
    net = weights.build(a.net, arch_args).to(a.device).train()
    if a.init:
        init, init_meta = weights.load(a.init, a.device)
        if init_meta["arch"] != a.net:
            raise SystemExit(f"--init {a.init}: architecture {init_meta['arch']!r}, not {a.net!r}")
        state = {k: v for k, v in init.state_dict().items() if not k.startswith("filler.")}
        missing, unexpected = net.load_state_dict(state, strict=False)
        if unexpected or any(not k.startswith("filler.") for k in missing):
            raise SystemExit(f"--init {a.init}: weights do not fit ({unexpected or missing})")
    if a.hole_fill:
        filler, _ = weights.load(a.hole_fill, a.device)
        net.filler.load_state_dict(filler.state_dict())
    net.train()
    opt = torch.optim.AdamW(net.parameters(), lr=a.lr, weight_decay=1e-4)
    budget, wall_cap = a.minutes * 60.0, a.max_wall_minutes * 60.0
    curve_path = Path(a.out).with_suffix(".curve.csv")
    curve_path.parent.mkdir(parents=True, exist_ok=True)
    curve = open(curve_path, "w")
    curve.write("step,elapsed_s,lr,loss\n")
    t0, c0, step, smooth = time.time(), time.process_time(), 0, None
    last_ckpt = t0
    # progress: the larger of CPU time over its budget and wall time over its cap (shared, busy machines)
    while (progress := max((time.process_time() - c0) / budget, (time.time() - t0) / wall_cap)) < 1.0:
        elapsed = time.time() - t0
        lr = a.lr * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * progress)))
        for g in opt.param_groups:
            g["lr"] = lr
        if a.net == "stereo_refine":
            batch = next(loader) if a.loader_workers > 0 else refine_batch(train, rng, a.batch, tuple(a.crop))
            left, right, d0, matched, u_gt, valid = (x.to(a.device, non_blocking=True) for x in batch)
            u, su = net.refine(left, right, d0, matched)
            loss = stereo_loss(u, su, u_gt, valid & (u_gt > 0))
            if real:
                rl, rr, rd0, rm, rlabel = (x.to(a.device) for x in real_batch(real, rng, a.batch, tuple(a.crop)))
                ru, _ = net.refine(rl, rr, rd0, rm)
                loss = loss + a.real_weight * proxy_loss(ru, rl, rlabel, rm)
        elif a.net == "stereo":
            left, right, u_gt = (x.to(a.device) for x in stereo_batch(train, rng, a.batch, tuple(a.crop)))
            valid = torch.isfinite(u_gt) & (u_gt > 0.5) & (u_gt < net.max_disparity - 1)
            u, su = net(left, right)
            loss = stereo_loss(u, su, torch.nan_to_num(u_gt, posinf=0.0), valid)
        else:
            ref, src, K, T, prior, d_gt = (x.to(a.device) for x in mvs_batch(train, rng, a.batch, tuple(a.crop), a.sources))
            valid = torch.isfinite(d_gt) & (d_gt > net.min_depth) & (d_gt < net.max_depth)
            ld, sl = net(ref, src, K, T, prior)
            loss = mvs_loss(ld, sl, torch.nan_to_num(d_gt, nan=1.0, posinf=1.0), valid)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 5.0)
        opt.step()
        step += 1
        if step % 200 == 0 and a.net == "stereo_refine" and not a.loader_workers and len(shard_dirs(root, "train")) > len(train):
            train = load_shards(root, "train")  # shards still rendering when training started join in
        elif step % 200 == 0 and a.net != "stereo_refine" and len(list((root / "train").glob("scene_?????.npz"))) > len(train):
            train = load_split(root, "train", train)  # scenes still rendering when training started join in
        smooth = loss.item() if smooth is None else 0.95 * smooth + 0.05 * loss.item()
        curve.write(f"{step},{elapsed:.1f},{lr:.3g},{loss.item():.5f}\n")
        if step % 25 == 0:
            curve.flush()
            print(f"[{a.net}] step {step} wall {elapsed:.0f}s cpu {time.process_time() - c0:.0f}s lr {lr:.2g} "
                  f"loss {smooth:.4f}", flush=True)
        if a.checkpoint_minutes > 0 and time.time() - last_ckpt > 60 * a.checkpoint_minutes:
            last_ckpt = time.time()  # uncalibrated (gain 1) snapshot to look at while training goes on
            weights.save(net, str(a.out) + "_partial", a.net, arch_args, {"gain": 1.0, "steps": step, "partial": True})
            net.train()
    curve.close()
    net.eval()
    if a.net == "stereo_refine":
        val = load_shards(root, "val")
        gain, val_cal = evaluate_refine(net, val, a.device)
        val_raw, domain = {}, REFINE_GAIN_DOMAIN
    else:
        val = load_split(root, "val")  # loaded only now: it may still be rendering when training starts
        est, sig, gt = evaluate(net, a.net, val, a.sources, a.device)
        gain = calibration_gain(est, sig, gt)
        val_raw = depth_metrics(est, sig, gt)
        val_cal = depth_metrics(est, sig * gain, gt)
        domain = "depth sigma [m] (mean |d - d_gt| / (gain sigma) = 1 on val)"
    print(f"[{a.net}] {step} steps in {time.time() - t0:.0f}s; val gain {gain:.4f}; calibrated {val_cal}", flush=True)
    data_meta = json.loads((root / "dataset.json").read_text()) if (root / "dataset.json").is_file() else {}
    weights.save(net.cpu(), a.out, a.net, arch_args, {
        "gain": gain, "gain_domain": domain, "init": a.init or None,
        "command": "python -m tools.depth.train " + " ".join(argv if argv is not None else sys.argv[1:]),
        "seed": a.seed, "steps": step, "train_wall_s": round(time.time() - t0), "train_cpu_s": round(time.process_time() - c0), "device": a.device,
        "device_name": torch.cuda.get_device_name() if cuda else None,
        "batch": a.batch, "loader_workers": a.loader_workers,
        "threads": a.threads, "data": {"root": str(root), "train_scenes": [s["name"] for s in train],
                                       "val_scenes": [s["name"] for s in val], **data_meta, **fill_meta,
                                       "real_pairs": {"folders": a.real_pairs, "pairs": len(real),
                                                      "weight": a.real_weight} if real else None},
        "val_uncalibrated": val_raw, "val_calibrated": val_cal, "curve": curve_path.name,
        "torch": torch.__version__})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
