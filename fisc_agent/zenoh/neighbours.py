"""What an agent hears of its neighbours: the newest telemetry of every other vehicle of the swarm,
for the separation safety net (``fisc_agent.flight.safety_net``).

One ``NeighbourTable`` per process (an agent, or an emulator worker hosting many agents) subscribes
once to ``fisc/<swarm>/agents/*/telemetry``.  Zenoh's callback decodes the message and keeps, per
agent id, the position and velocity it reports and when it arrived (this process's monotonic clock,
so no clock is compared across vehicles).  ``reports(exclude_id)`` returns everyone else's newest
report with its age now: time since arrival plus the position's own age when it was sent.

A vehicle reporting itself on the ground, or reporting no position, is dropped from the table: it
is no obstacle in the air, or nothing is known of where it is.  Messages that do not decode are
counted (``bad_messages``), never raised into Zenoh's thread.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any, Callable

import numpy as np

from fisc_agent.flight.safety_net import NeighbourReports
from fisc_agent.zenoh import telemetry_codec as tc

log = logging.getLogger(__name__)


class NeighbourTable:
    """The newest report of each vehicle heard on the swarm's telemetry (thread-safe)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        """Monotonic clock of arrival times and ages [s]."""
        self._lock = threading.Lock()
        self._rows: dict[int, tuple[float, tuple[float, float, float], tuple[float, float, float], float]] = {}
        self._subscriber: Any = None
        self.messages = 0
        """Telemetry messages taken in."""
        self.bad_messages = 0
        """Messages that did not decode (ignored)."""

    def attach(self, session: Any, key_expr: str) -> Any:
        """Subscribe to ``key_expr`` (the swarm's telemetry wildcard) on ``session`` once; returns the
        subscriber the first time (its owner undeclares it), None when already attached."""
        with self._lock:
            if self._subscriber is not None:
                return None
            self._subscriber = session.declare_subscriber(key_expr, self.on_sample)
            return self._subscriber

    def on_sample(self, sample: Any) -> None:
        """Zenoh callback: take in one telemetry message."""
        self.take(bytes(sample.payload.to_bytes()))

    def take(self, data: bytes) -> None:
        """Take in one encoded telemetry message (arrived now)."""
        now = self.clock()
        try:
            t = tc.decode(data)
        except tc.TelemetryError as exc:
            with self._lock:
                self.bad_messages += 1
            log.debug("neighbour telemetry not decoded: %s", exc)
            return
        with self._lock:
            self.messages += 1
            if t.landed == "on-ground" or not all(math.isfinite(c) for c in t.position_m):
                self._rows.pop(t.agent_id, None)
                return
            vel = tuple(c if math.isfinite(c) else 0.0 for c in t.velocity_m_s)
            pos_age = t.position_age_s if math.isfinite(t.position_age_s) else 0.0
            self._rows[t.agent_id] = (now, t.position_m, vel, pos_age)  # type: ignore[assignment]

    def reports(self, exclude_id: int) -> NeighbourReports:
        """Every other vehicle's newest report with its age now."""
        now = self.clock()
        with self._lock:
            rows = [(aid, r) for aid, r in self._rows.items() if aid != exclude_id]
        if not rows:
            return NeighbourReports.empty()
        ids = np.array([aid for aid, _ in rows], dtype=np.int64)
        pos = np.array([r[1] for _, r in rows], dtype=float)
        vel = np.array([r[2] for _, r in rows], dtype=float)
        age = np.array([max(0.0, now - r[0]) + r[3] for _, r in rows], dtype=float)
        return NeighbourReports(ids, pos, vel, age)

    def __len__(self) -> int:
        with self._lock:
            return len(self._rows)
