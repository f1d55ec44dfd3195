"""Link and sensor fault injection for the autopilot emulator.

* packet loss: every incoming and every outgoing MAVLink message is dropped independently with
  probability ``loss_probability`` (seeded, reproducible);
* latency: outgoing messages are held back ``latency_s`` seconds before they are sent
  (:class:`DelayLine`);
* position dropouts: inside each ``(start_s, duration_s)`` window (emulator time since start)
  no position message is sent and the vehicle reports no position estimate.

Pure logic on a clock passed in; no sockets.
"""

from __future__ import annotations

import heapq
import math
import random
from dataclasses import dataclass
from typing import Generic, TypeVar

__all__ = ["FaultConfig", "FaultInjector", "DelayLine", "parse_dropout"]

T = TypeVar("T")


@dataclass(frozen=True)
class FaultConfig:
    """Which faults to inject."""

    loss_probability: float = 0.0
    """Probability in [0, 1] of dropping each incoming and each outgoing message."""
    latency_s: float = 0.0
    """Delay added to every outgoing message [s] (>= 0)."""
    position_dropouts: tuple[tuple[float, float], ...] = ()
    """Windows ``(start_s, duration_s)`` in emulator time without position output."""
    seed: int | None = 0
    """Seed of the loss random stream (None: nondeterministic)."""

    def __post_init__(self) -> None:
        if not (0.0 <= self.loss_probability <= 1.0):
            raise ValueError(f"loss_probability must be in [0, 1], got {self.loss_probability}")
        if not (self.latency_s >= 0.0 and math.isfinite(self.latency_s)):
            raise ValueError(f"latency_s must be a finite number >= 0, got {self.latency_s}")
        for w in self.position_dropouts:
            if len(w) != 2 or not all(math.isfinite(x) for x in w) or w[1] < 0:
                raise ValueError(f"position dropout must be (start_s, duration_s >= 0), got {w!r}")


def parse_dropout(text: str) -> tuple[float, float]:
    """Parse ``"START,DURATION"`` (seconds) into a dropout window."""
    parts = text.split(",")
    try:
        start, duration = (float(p) for p in parts)
    except ValueError:
        raise ValueError(f"position dropout {text!r}: expected START,DURATION in seconds") from None
    if duration < 0 or not (math.isfinite(start) and math.isfinite(duration)):
        raise ValueError(f"position dropout {text!r}: need finite START and DURATION >= 0")
    return start, duration


class FaultInjector:
    """Decides, message by message, what the faults do (seeded random stream)."""

    def __init__(self, config: FaultConfig | None = None) -> None:
        self.config = FaultConfig() if config is None else config
        self._rng = random.Random(self.config.seed)
        self.dropped_in = 0
        """Incoming messages dropped so far."""
        self.dropped_out = 0
        """Outgoing messages dropped so far."""

    def _lost(self) -> bool:
        p = self.config.loss_probability
        return p > 0.0 and self._rng.random() < p

    def drop_incoming(self) -> bool:
        """True if the next incoming message is lost."""
        lost = self._lost()
        self.dropped_in += lost
        return lost

    def drop_outgoing(self) -> bool:
        """True if the next outgoing message is lost."""
        lost = self._lost()
        self.dropped_out += lost
        return lost

    @property
    def latency_s(self) -> float:
        """Delay of outgoing messages [s]."""
        return self.config.latency_s

    def position_dropout(self, t_s: float) -> bool:
        """True if ``t_s`` (emulator time) lies in a position dropout window."""
        return any(start <= t_s < start + dur for start, dur in self.config.position_dropouts)


class DelayLine(Generic[T]):
    """Items released in time order once their due time has come (FIFO for equal times)."""

    def __init__(self) -> None:
        self._heap: list[tuple[float, int, T]] = []
        self._n = 0

    def __len__(self) -> int:
        return len(self._heap)

    def push(self, due_s: float, item: T) -> None:
        """Queue ``item`` for release at ``due_s``."""
        heapq.heappush(self._heap, (due_s, self._n, item))
        self._n += 1

    def pop_due(self, now_s: float) -> list[T]:
        """Remove and return the items due at or before ``now_s``, in due order."""
        out: list[T] = []
        while self._heap and self._heap[0][0] <= now_s:
            out.append(heapq.heappop(self._heap)[2])
        return out

    def next_due(self) -> float:
        """Due time of the earliest item (+inf if empty)."""
        return self._heap[0][0] if self._heap else math.inf
