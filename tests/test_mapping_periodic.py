"""The mapping node's periodic jobs (mesh, field, grid, checkpoint) keep their rate when its ticks come late: the
next one falls due a period after the last fell due, not after it ran (services/mapping/node.py, MappingNode._due)."""

from __future__ import annotations

import numpy as np

from services.mapping.config import MappingConfig
from services.mapping.node import make_node


def test_a_job_keeps_its_rate_between_late_ticks_and_does_not_burst_after_a_stall():
    t = [0.0]
    node = make_node(MappingConfig(), clock=lambda: t[0])
    rng = np.random.default_rng(0)
    runs = []
    while t[0] < 60.0:  # ticks between integrations of 0.05-0.35 s, as a busy mapper's
        t[0] += float(rng.uniform(0.05, 0.35))
        if node._due("grid", 1.0, t[0]):
            runs.append(t[0])
    assert 58 <= len(runs) <= 60, len(runs)  # "ran + period" gives 52 here: the 0.7-0.84 Hz measured live
    assert np.diff(runs).min() > 0.6  # never two at once
    # a stall of 5 s: one run when it ends, then one per period again (no five to catch up)
    t[0] += 5.0
    assert node._due("grid", 1.0, t[0])
    assert not node._due("grid", 1.0, t[0] + 0.5) and node._due("grid", 1.0, t[0] + 1.0)
    assert not node._due("field", 0.0, t[0] + 100.0)  # <= 0: never
