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
    """The newest report of each vehicle heard on the swarm's telemetry (thread-safe).

    Rows live in growing numpy arrays (one row per agent id ever heard, ``live`` marks the ones in the
    air with a position), so ``reports`` costs a few vectorised operations however many agents share
    the table (an emulator worker's agents share one)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        """Monotonic clock of arrival times and ages [s]."""
        self._lock = threading.Lock()
        self._row_of: dict[int, int] = {}
        self._ids = np.zeros(0, dtype=np.int64)
        self._pos = np.zeros((0, 3))
        self._vel = np.zeros((0, 3))
        self._t0 = np.zeros(0)  # arrival time less the position's age when sent
        self._live = np.zeros(0, dtype=bool)
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

    def _row(self, agent_id: int) -> int:
        row = self._row_of.get(agent_id)
        if row is None:
            row = len(self._row_of)
            if row == self._ids.shape[0]:  # grow by doubling
                cap = max(8, 2 * row)
                self._ids = np.resize(self._ids, cap)
                self._pos, self._vel = np.resize(self._pos, (cap, 3)), np.resize(self._vel, (cap, 3))
                self._t0 = np.resize(self._t0, cap)
                self._live = np.concatenate([self._live, np.zeros(cap - row, dtype=bool)])
            self._row_of[agent_id] = row
            self._ids[row] = agent_id
        return row

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
            row = self._row(t.agent_id)
            if t.landed == "on-ground" or not all(math.isfinite(c) for c in t.position_m):
                self._live[row] = False
                return
            self._pos[row] = t.position_m
            self._vel[row] = [c if math.isfinite(c) else 0.0 for c in t.velocity_m_s]
            self._t0[row] = now - (t.position_age_s if math.isfinite(t.position_age_s) else 0.0)
            self._live[row] = True

    def reports(self, exclude_id: int) -> NeighbourReports:
        """Every other vehicle's newest report with its age now."""
        now = self.clock()
        with self._lock:
            n = len(self._row_of)
            keep = self._live[:n] & (self._ids[:n] != exclude_id)
            return NeighbourReports(self._ids[:n][keep], self._pos[:n][keep], self._vel[:n][keep],
                                    np.maximum(0.0, now - self._t0[:n][keep]))

    def __len__(self) -> int:
        with self._lock:
            return int(np.count_nonzero(self._live[:len(self._row_of)]))
