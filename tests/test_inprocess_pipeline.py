"""The whole pipeline in one process (services/app/inprocess.py with depth and mapping: what ``sigmaslam eval
ablation`` runs per row): the services' nodes (with the fast path) on the in-process runner over 2 s of the default replica, depth
paced by its own rate on sensor time, the mapping integrating every posed depth frame and feeding its fields back to
the back end's occupancy-to-point terms, and the heuristic stereo sigma of ``depth.stereo_sigma`` on the wire."""

from __future__ import annotations

import numpy as np
import pytest

from services.app.inprocess import run_in_process
from services.backend.node import BackendNode
from services.depth.node import DepthNode
from services.frontend.node import FrontendNode
from services.mapping.node import MappingNode
from services.app.system_config import load_system_config
from shared import topics


@pytest.mark.e2e
def test_short_row_runs_the_four_nodes_with_depth_and_mapping(default_replica):
    cfg = load_system_config(None, ["loop.synchronous=true", "o2p.enabled=true", "depth.use_mvs=false",
                                    "depth.rate_hz=5", "depth.stereo_sigma=heuristic",
                                    "depth.heuristic_sigma_model=quadratic", "depth.heuristic_sigma_coeff=2"])
    stereo = []
    run = run_in_process(str(default_replica), cfg, depth=True, mapping=True, seconds=2.0,
                         taps=[lambda topic, msg: stereo.append(msg) if topic == topics.DEPTH_STEREO else None])
    nodes = run.nodes
    assert [type(n) for n in nodes.values()] == [FrontendNode, BackendNode, DepthNode, MappingNode]
    assert 35 <= run.frames <= 41 and run.final is not None

    # the depth node's own pacing: at most one frame per 1 / depth.rate_hz of sensor time
    stamps = np.array([m.header.stamp_ns for m in stereo])
    assert 9 <= len(stamps) <= 11 and np.diff(stamps).min() >= 0.199e9, np.diff(stamps)
    assert run.runner.emitted["depth/stereo"] == run.runner.emitted["depth/fused"] == len(stamps)

    # the mapping integrated each posed depth frame; its fields and the depth reached the back end's o2p terms
    mapping = nodes["mapping"]
    posed = sum(not np.allclose(m.T_WC, np.eye(4)) for m in stereo)
    assert posed >= len(stereo) - 1 and mapping.counts["integrated"] == posed, dict(mapping.counts)
    assert run.runner.emitted.get("map/field", 0) >= 1
    calls = len(run.runner.times[("backend", "on_map_input")])
    assert calls == run.runner.emitted["depth/stereo"] + run.runner.emitted["map/field"]
    assert len(run.mesh_causal) > 1000 and len(mapping.mapper.world_mesh()[0]) == len(run.mesh_causal)

    # depth.stereo_sigma=heuristic: the network's depth with sigma_d = d^2 sigma_u / (f b), sigma_u = 2 px
    pipe = nodes["depth"].pipe
    d, s = stereo[-1].depth, stereo[-1].sigma
    ok = np.isfinite(d)
    assert ok.mean() > 0.3
    np.testing.assert_allclose(s[ok], d[ok] ** 2 * 2.0 / (pipe.f_px * pipe.baseline_m), rtol=1e-5)
    assert np.isnan(s[~ok]).all()

    # one loop-closer time per back-end frame call
    assert len(run.loop_s) == len(run.runner.times[("backend", "on_features")])
