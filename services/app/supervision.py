"""What a supervised process learns from its supervisor (``sigmaslam up``/``run``, :mod:`services.app.supervisor`)."""

from __future__ import annotations

import os

RESTARTS_ENV = "SIGMASLAM_RESTARTS"  # set in each child: how often the supervisor restarted that service


def restart_count() -> int:
    """In a supervised service: how many times it was restarted (0 at its first start or unsupervised)."""
    try:
        return max(0, int(os.environ.get(RESTARTS_ENV, "0") or 0))
    except ValueError:
        return 0
