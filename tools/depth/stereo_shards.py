"""The layered stereo set on disk (tools/depth/make_stereo_data.py): memory-mapped shards, training crops and
validation frames for the SGBM-guided network (services/depth/refine_net.py)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from services.depth.refine_net import initial_disparity as refine_initial_disparity

KEYS = ("left", "right", "disparity", "nonocc", "sgbm", "u_max", "sgbm_range")
OPTIONAL = ("fill",)  # (N,H,W) uint16 in 1/16 px: a network's disparity for SGBM's holes (add_fill)


def shard_dirs(root: str | Path, split: str) -> list[Path]:
    """The complete shards of ``split``: layered ``shard_NNNN`` and procedural-room ``rooms_NNNN`` folders."""
    d = Path(root) / split
    return [s for s in sorted([*d.glob("shard_????"), *d.glob("rooms_????")])
            if all((s / f"{k}.npy").is_file() for k in KEYS)]


def load_shards(root: str | Path, split: str) -> list[dict[str, np.ndarray]]:
    """Every complete shard of ``split`` (:func:`shard_dirs`) as a dict of memory-mapped arrays (plus 'name')."""
    d = Path(root) / split
    shards = [{k: np.load(s / f"{k}.npy", mmap_mode="r") for k in (*KEYS, *OPTIONAL) if (s / f"{k}.npy").is_file()}
              | {"name": s.name} for s in shard_dirs(root, split)]
    if not shards:
        raise SystemExit(f"{d}: no complete shard (render them: python -m tools.depth.make_stereo_data)")
    return shards


def frame(shard: dict, i: int) -> dict[str, np.ndarray]:
    """Frame i of a shard decoded: disparity and SGBM in px (SGBM NaN where it found no match)."""
    sg = shard["sgbm"][i].astype(np.float32) / 16.0
    f = {"left": np.asarray(shard["left"][i]), "right": np.asarray(shard["right"][i]),
         "disparity": shard["disparity"][i].astype(np.float32) / 256.0, "nonocc": shard["nonocc"][i] > 0,
         "sgbm": np.where(sg > 0, sg, np.nan).astype(np.float32), "u_max": float(shard["u_max"][i])}
    if "fill" in shard:
        f["fill"] = shard["fill"][i].astype(np.float32) / 16.0
    return f


def initial_disparity(f: dict) -> np.ndarray:
    """The network's d0 for a decoded frame (:func:`services.depth.refine_net.initial_disparity`), its holes from
    the frame's ``fill`` (:func:`add_fill`) when the shard has one."""
    return refine_initial_disparity(f["sgbm"], f.get("fill"))


def fill_source(root: str | Path) -> str:
    """The weights whose disparity fills SGBM's holes in the data under ``root`` (its ``fill.json``), '' if none."""
    meta = Path(root) / "fill.json"
    return json.loads(meta.read_text())["weights"] if meta.is_file() else ""


def same_weights(a: str | Path, b: str | Path) -> bool:
    return Path(a).resolve() == Path(b).resolve()


def add_fill(root: str | Path, weights_path: str | Path, threads: int = 2) -> int:
    """Writes ``fill.npy`` (the given stereo network's disparity of every frame) into every shard under ``root``
    that has none; returns the number of frames run."""
    from services.depth import weights
    from services.depth.stereo_net import predict_disparity

    source = fill_source(root)
    if source and not same_weights(source, weights_path):
        raise SystemExit(f"{root}: its fill came from {source}, not {weights_path} "
                         "(delete the fill.npy files and fill.json first)")
    torch.set_num_threads(threads)
    net, _ = weights.load(weights_path)
    (Path(root) / "fill.json").write_text(json.dumps({"weights": str(weights_path)}))
    done = 0
    for split in ("train", "val"):
        for d in shard_dirs(root, split):
            if (d / "fill.npy").is_file():
                continue
            left, right = np.load(d / "left.npy", mmap_mode="r"), np.load(d / "right.npy", mmap_mode="r")
            fill = np.stack([np.clip(np.rint(predict_disparity(net, lt, rt)[0] * 16), 0, 65535).astype(np.uint16)
                             for lt, rt in zip(left, right)])
            np.save(d / "fill.tmp.npy", fill)
            (d / "fill.tmp.npy").rename(d / "fill.npy")
            done += len(fill)
            print(f"[stereo_shards] {d}: fill from {Path(weights_path).name} ({done} frames)", flush=True)
    return done


def refine_batch(shards: list[dict], rng: np.random.Generator, batch: int, crop: tuple[int, int]):
    """(left, right (B,1,h,w), d0 (B,h,w) filled SGBM, matched (B,h,w) bool, u_gt (B,h,w), valid (B,h,w) bool).
    The hole filling runs on the whole frame (as at inference) before the crop; photometric jitter is a gain and
    offset common to both images plus a small left/right gain difference (the images are standardised anyway)."""
    ch, cw = crop
    out = {k: [] for k in ("left", "right", "d0", "matched", "u", "valid")}
    for _ in range(batch):
        sh = shards[int(rng.integers(len(shards)))]
        f = frame(sh, int(rng.integers(len(sh["u_max"]))))
        h, w = f["left"].shape
        y, x = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
        sl = np.s_[y:y + ch, x:x + cw]
        d0 = initial_disparity(f)[sl]
        gain, off = rng.uniform(0.8, 1.2), rng.uniform(-15, 15)
        lr = rng.uniform(0.95, 1.05)
        left = np.clip(f["left"][sl] * gain + off, 0, 255)
        right = np.clip(f["right"][sl] * gain * lr + off, 0, 255)
        u, matched = f["disparity"][sl], np.isfinite(f["sgbm"][sl])
        if rng.random() < 0.5:  # an upside-down pair is still a rectified pair
            left, right, d0, u, matched = (a[::-1] for a in (left, right, d0, u, matched))
        out["left"].append(left)
        out["right"].append(right)
        out["d0"].append(d0)
        out["matched"].append(matched)
        out["u"].append(u)
        out["valid"].append(np.ones_like(matched))
    t = lambda k: torch.from_numpy(np.ascontiguousarray(np.stack(out[k])))
    return (t("left").float()[:, None], t("right").float()[:, None], t("d0").float(), t("matched"), t("u").float(),
            t("valid"))


class RefineBatches(torch.utils.data.IterableDataset):
    """Endless :func:`refine_batch` batches of the complete ``train`` shards under ``root``, for a
    ``torch.utils.data.DataLoader(..., batch_size=None, num_workers=N)``: each loader process draws from its own
    generator, seeded by (seed, worker index), so a run is a function of the seed and the number of workers. The
    crops cost ~4.5 ms per sample on one core (the hole filling runs on whole frames), which alone would starve a GPU."""

    def __init__(self, root: str | Path, batch: int, crop: tuple[int, int], seed: int) -> None:
        super().__init__()
        self.root, self.batch, self.crop, self.seed = Path(root), batch, tuple(crop), seed

    def __iter__(self):
        info = torch.utils.data.get_worker_info()
        rng = np.random.default_rng([self.seed, 7_000 + (info.id if info is not None else 0)])
        shards = load_shards(self.root, "train")
        while True:
            yield refine_batch(shards, rng, self.batch, self.crop)


def validation_frames(shards: list[dict], per_shard: int = 8):
    """(frame dict) for the first ``per_shard`` frames of every validation shard, cropped to multiples of 16."""
    for sh in shards:
        for i in range(min(per_shard, len(sh["u_max"]))):
            f = frame(sh, i)
            h, w = f["left"].shape
            yield {k: (v[: h // 16 * 16, : w // 16 * 16] if isinstance(v, np.ndarray) else v) for k, v in f.items()}


if __name__ == "__main__":
    import argparse

    p = argparse.ArgumentParser(description="add a stereo network's disparity (fill.npy) to every shard")
    p.add_argument("data", help="folder of make_stereo_data")
    p.add_argument("--fill-weights", default="services/depth/weights/stereo.pt")
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args()
    add_fill(a.data, a.fill_weights, a.threads)
