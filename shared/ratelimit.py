"""A logger wrapper for problems that recur at a high rate (bad messages, failed draws): one line per period."""

from __future__ import annotations

import logging
import threading
import time


class RateLimitedLog:
    """Log a recurring problem at most once per ``period_s``, with the number suppressed in between."""

    def __init__(self, logger: logging.Logger, period_s: float = 5.0) -> None:
        self._log = logger
        self._period = period_s
        self._last = -float("inf")
        self._suppressed = 0
        self._lock = threading.Lock()

    def warning(self, msg: str, *args: object) -> None:
        now = time.monotonic()
        with self._lock:
            if now - self._last < self._period:
                self._suppressed += 1
                return
            suppressed, self._suppressed, self._last = self._suppressed, 0, now
        if suppressed:
            msg += f" ({suppressed} similar suppressed)"
        self._log.warning(msg, *args)
