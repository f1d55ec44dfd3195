"""Which telemetry stream is due when: per-message intervals, as MAV_CMD_SET_MESSAGE_INTERVAL sets them (pure)."""

from __future__ import annotations

import math
from typing import Callable, Mapping

__all__ = ["StreamSchedule"]

MIN_INTERVAL_S = 0.005
"""Shortest stream interval [s] (200 Hz)."""


class StreamSchedule:
    """Per-message stream intervals and due times on the emulator's clock [s].

    ``default_intervals_s``: message id -> interval [s] (0: not streamed).  The schedule remembers
    the earliest due time of all streams, so :meth:`run` costs one comparison until then."""

    def __init__(self, default_intervals_s: Mapping[int, float]) -> None:
        self._defaults = dict(default_intervals_s)
        self._intervals = dict(default_intervals_s)
        self._next_due: dict[int, float] = {}
        self._due = -math.inf  # earliest next-due time of the streams (-inf: recompute)

    def due_now(self, msg_id: int, now: float) -> None:
        """Send ``msg_id`` on the next :meth:`run` (then its rhythm resumes)."""
        self._next_due[msg_id] = now
        self._due = -math.inf

    def set_interval_us(self, msg_id: int, interval_us: float, now: float) -> None:
        """MAV_CMD_SET_MESSAGE_INTERVAL param2: > 0 interval [us] (at least 5 ms), -1 (< 0) stop,
        0 or NaN back to the default; the message is due at once."""
        if not math.isfinite(interval_us) or interval_us == 0:
            interval = self._defaults.get(msg_id, 0.0)
        elif interval_us < 0:
            interval = 0.0
        else:
            interval = max(interval_us * 1e-6, MIN_INTERVAL_S)
        self._intervals[msg_id] = interval
        self.due_now(msg_id, now)

    def run(self, now: float, send: Callable[[int], object]) -> float:
        """Call ``send(msg_id)`` for each stream due at ``now``; returns the next due time [s]."""
        if now < self._due:
            return self._due
        next_due = math.inf
        for msg_id, interval in self._intervals.items():
            if interval <= 0.0:
                continue
            due = self._next_due.get(msg_id, now)
            if now >= due:
                send(msg_id)
                due = due + interval if now - due < interval else now + interval
                self._next_due[msg_id] = due
            next_due = min(next_due, due)
        self._due = next_due
        return next_due
