"""Recalibrate the sigma gain of trained SGBM-guided stereo weights without training them again.

    python -m tools.depth.recalibrate services/depth/weights/stereo_refine.pt --data data/stereo_train --rule median

The network is run on the validation split of the layered training set (tools/depth/make_stereo_data.py) and
the gain is fitted by ``--rule`` (services.depth.uncertainty.gain_from_ratios: 'mean' |e|/sigma = 1, sec. V-A, or
'median' |e|/sigma = ln 2, robust to the split's gross errors at occlusions). The weights' JSON gets the new gain;
the old one, the rule, this command and the validation figures go into its ``recalibrations`` list, so the
provenance of every gain stays on record. Never pass an evaluation set (Middlebury) here.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from services.depth import weights
from services.depth.uncertainty import GAIN_RULES


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("weights", help="stereo_refine weights (.pt with its .json beside)")
    p.add_argument("--data", default="data/stereo_train", help="layered stereo set (its 'val' split is used)")
    p.add_argument("--rule", choices=GAIN_RULES, default="median")
    p.add_argument("--dry-run", action="store_true", help="print the gain, leave the JSON as it is")
    a = p.parse_args(argv)
    from tools.depth.stereo_shards import load_shards
    from tools.depth.train import REFINE_GAIN_DOMAIN, evaluate_refine

    path = Path(a.weights)
    try:
        net, meta = weights.load(path, "cpu")
    except weights.WeightsError as exc:
        raise SystemExit(str(exc)) from None
    if meta.get("arch") != "stereo_refine":
        raise SystemExit(f"{path}: architecture {meta.get('arch')!r}; only 'stereo_refine' is recalibrated here "
                         f"(the others: tools.depth.train)")
    val = load_shards(a.data, "val")
    if not val:
        raise SystemExit(f"{a.data}: no validation shards (python -m tools.depth.make_stereo_data)")
    torch.set_num_threads(1)
    gain, metrics = evaluate_refine(net, val, "cpu", a.rule)
    old = float(meta.get("gain", 1.0))
    print(f"{path.name}: gain {old:.4f} -> {gain:.4f} (rule {a.rule}, {metrics['frames']} validation frames); "
          f"calibrated mean |e|/sigma {metrics['err_over_sigma_all_calibrated']:.3f}, within 2 sigma "
          f"{metrics['within2s_all_calibrated']:.1f} %")
    if a.dry_run:
        return 0
    js = path.with_suffix(".json")
    doc = json.loads(js.read_text())
    doc.setdefault("recalibrations", []).append({
        "previous_gain": old, "gain": gain, "rule": a.rule, "previous_gain_domain": doc.get("gain_domain"),
        "command": "python -m tools.depth.recalibrate " + " ".join(argv if argv is not None else sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d"), "val_scenes": [s["name"] for s in val], "val_calibrated": metrics})
    doc["gain"] = gain
    doc["gain_domain"] = REFINE_GAIN_DOMAIN if a.rule == "median" else doc.get("gain_domain")
    js.write_text(json.dumps(doc, indent=1))
    print(f"wrote {js}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
