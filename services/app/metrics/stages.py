"""The per-item stage logs a measured run leaves (``$SIGMASLAM_STAGE_LOG``, transport/stats.py): every process logs the
end time, wall and CPU time of each item of each of its stages."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def stage_items(stage_dir: Path) -> dict[str, np.ndarray]:
    """'service.stage' -> per-item records (end_ns, seconds, cpu_seconds) from the stage logs in ``stage_dir``."""
    from transport.stats import read_stage_log

    return {p.name[:-4]: read_stage_log(p) for p in sorted(Path(stage_dir).glob("*.bin"))}
