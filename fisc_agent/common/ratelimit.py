"""Rate-limited logging with counters (for refusals a peer can trigger at will).

A hostile or broken peer can make the agent (or the ground) refuse thousands of messages per
second; one log line per refusal fills the disk and costs CPU on the control computer.
``RateLimitedLog`` counts every event under a key (``"map:signature"``, ``"mavlink:foreign"``
...) and logs at most one line per key per ``period_s``; the next line of that key says how
many were suppressed meanwhile.  The counters are exact and bounded (at most ``max_keys`` keys;
further keys are counted under ``"other"``).  Thread-safe; the clock is injectable.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable

OVERFLOW_KEY = "other"


class RateLimitedLog:
    """Per-key counters plus at most one log line per key per ``period_s``."""

    def __init__(self, logger: logging.Logger, period_s: float = 5.0, max_keys: int = 64,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not period_s >= 0:
            raise ValueError(f"period_s must be >= 0, got {period_s}")
        if max_keys < 1:
            raise ValueError(f"max_keys must be >= 1, got {max_keys}")
        self.logger = logger
        self.period_s = float(period_s)
        self.max_keys = int(max_keys)
        self.clock = clock
        self._lock = threading.Lock()
        self._counts: dict[str, int] = {}
        self._last_log_s: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def event(self, key: str, level: int, msg: str, *args: object) -> bool:
        """Count one event under ``key``; log ``msg % args`` at ``level`` unless a line of this
        key was logged less than ``period_s`` ago.  Returns True when a line was logged."""
        now = self.clock()
        with self._lock:
            if key not in self._counts and len(self._counts) >= self.max_keys:
                key = OVERFLOW_KEY
            self._counts[key] = self._counts.get(key, 0) + 1
            last = self._last_log_s.get(key)
            if last is not None and now - last < self.period_s:
                self._suppressed[key] = self._suppressed.get(key, 0) + 1
                return False
            self._last_log_s[key] = now
            suppressed = self._suppressed.pop(key, 0)
            total = self._counts[key]
        if suppressed:
            msg = f"{msg} [{suppressed} more like this in the last {self.period_s:g} s suppressed; {total} in all]"
        self.logger.log(level, msg, *args)
        return True

    def count(self, key: str) -> int:
        """Events counted under ``key`` so far."""
        with self._lock:
            return self._counts.get(key, 0)

    def counts(self) -> dict[str, int]:
        """A copy of every counter."""
        with self._lock:
            return dict(self._counts)

    def total(self, prefix: str = "") -> int:
        """Sum of the counters whose key starts with ``prefix``."""
        with self._lock:
            return sum(v for k, v in self._counts.items() if k.startswith(prefix))
