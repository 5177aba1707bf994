"""A depth pipeline on the EuRoC rig with untrained networks of fixed seed: the tests of the pipeline's plumbing
share it (what the networks predict does not matter there)."""
from __future__ import annotations

import torch

from services.depth import weights
from services.depth.config import DepthConfig
from services.depth.mvs_net import MVSNet
from services.depth.pipeline import DepthPipeline
from services.depth.stereo_net import StereoNet
from shared.rig import RigConfig, load_rig_config


def random_network_pipeline(tmp_path, stereo_gain: float = 1.0, mvs_gain: float = 1.0, **cfg) -> DepthPipeline:
    """Stereo (96 disparities) and MVS (16 planes) weights saved under tmp_path with these gains; ``cfg``: further
    DepthConfig keys (``max_relative_sigma`` 0 unless given: untrained networks' sigma means nothing)."""
    cfg.setdefault("max_relative_sigma", 0.0)
    torch.manual_seed(0)
    weights.save(StereoNet(96), tmp_path / "stereo", "stereo", {"max_disparity": 96}, {"gain": stereo_gain})
    weights.save(MVSNet(16), tmp_path / "mvs", "mvs", {"n_planes": 16}, {"gain": mvs_gain})
    cams = {c.name: c for c in load_rig_config(RigConfig())}
    dc = DepthConfig(method="network", stereo_weights=str(tmp_path / "stereo.pt"), mvs_weights=str(tmp_path / "mvs.pt"),
                     threads=1, device="cpu", **cfg)
    return DepthPipeline(dc, cams["cam0"], cams["cam1"])
