"""How many of camera 0's features the tracker also finds in camera 1, frame by frame, with and without
``frontend.match_gain_cross`` (the camera-to-camera KLT on gain-matched images), on any EuRoC-layout folder: the
real frames in $SIGMASLAM_SHARED/data/real/euroc_V1_01_micro or a replica. No gyro prediction, no estimator.

    python -m tools.eval.cross_matches ../shared/data/real/euroc_V1_01_micro
"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np


def cross_match_shares(dataset: str, frames: int = 0) -> dict:
    """{'frames', 'brightness_ratio' (median cam0/cam1 mean grey), 'off' / 'on': (camera 0 landmarks per frame, share
    of them also in camera 1)} for match_gain_cross off and on."""
    from services.frontend.config import FrontendConfig
    from services.frontend.tracker import MultiCameraTracker
    from shared.camera import load_rig
    from shared.euroc_reader import EurocDataset

    ds = EurocDataset(dataset)
    if len(ds.camera_names) < 2:
        raise SystemExit(f"{dataset}: needs two cameras, has {ds.camera_names}")
    loaded = [(int(s), ds.load_frame(int(s))) for s in ds.frame_stamps_ns[:frames or None]]
    loaded = [(s, im) for s, im in loaded if im is not None]
    ratio = [float(im[0].mean()) / max(1.0, float(im[1].mean())) for _, im in loaded]
    out = {"frames": len(loaded), "brightness_ratio": float(np.median(ratio)),
           "brightness_ratio_range": (float(min(ratio)), float(max(ratio)))}
    cams = load_rig(ds.root)
    for on in (False, True):
        tracker = MultiCameraTracker(dataclasses.replace(FrontendConfig(), match_gain_cross=on), cams)
        in0, in_both = 0, 0
        for s, im in loaded:
            o = tracker.process(s, im, None)
            ids0 = o.landmark_ids[o.camera_index == 0]
            in0 += len(ids0)
            in_both += int(np.isin(o.landmark_ids[o.camera_index == 1], ids0).sum())
        out["on" if on else "off"] = (in0 / len(loaded), in_both / max(1, in0))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset")
    p.add_argument("--frames", type=int, default=0, help="first N frames (0: all)")
    a = p.parse_args(argv)
    r = cross_match_shares(a.dataset, a.frames)
    lo, hi = r["brightness_ratio_range"]
    print(f"{r['frames']} frames; cam0/cam1 mean brightness ratio median {r['brightness_ratio']:.3f} "
          f"(range {lo:.3f}-{hi:.3f})")
    for k in ("off", "on"):
        n, share = r[k]
        print(f"match_gain_cross {k:3s}: camera 0 landmarks per frame {n:.1f}, also in camera 1 {100 * share:.1f} %")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
