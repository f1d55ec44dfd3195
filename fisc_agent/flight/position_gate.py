"""Position plausibility gate (pure): which fixes the mission may see.

A fix reaches the mission only if every position and velocity component is finite (and below
1000 km, or km/s) and it is reachable from the last accepted fix: ``|p - p_ref| <= max_speed_m_s * dt + jump_tolerance_m``
(``dt`` between receive times).  A rejected fix leaves the last accepted one in place, so its
age grows and the usual stale-position hold applies if good fixes stop coming.

A genuine jump (an EKF reset, a GNSS glitch corrected) produces a new track of fixes that are
consistent with each other but not with the reference: once such a track has lasted
``reanchor_after_s`` without any fix near the old reference, it becomes the reference
(``REANCHORED``, logged).  By then the mission has been holding on a stale position for that
long; with the default timings (0.5 s stale, 2 s grace) the hold is escalated and latched and
waits for a fleet ``resume``.  A short burst of bogus fixes (three fixes 1 km away) is simply
dropped while the genuine stream continues.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

Vec = tuple[float, float, float]


@dataclass(frozen=True)
class PositionGateConfig:
    """Limits of ``PositionGate``."""

    max_speed_m_s: float = 15.0
    """Fastest plausible motion between two fixes [m/s] (well above the setpoint clamp)."""
    jump_tolerance_m: float = 1.0
    """Allowance on top of ``max_speed_m_s * dt`` for noise, small EKF corrections and bunched packets [m]."""
    reanchor_after_s: float = 3.0
    """A consistent track of rejected fixes this long becomes the new reference [s]."""
    max_abs_m: float = 1.0e6
    """Largest plausible |component| of a local position or velocity (1000 km; m or m/s)."""

    @classmethod
    def for_speed_clamp(cls, max_speed_m_s: float) -> "PositionGateConfig":
        """The limits for an agent whose setpoints are clamped to ``max_speed_m_s``: three
        times that, at least 15 m/s."""
        return cls(max_speed_m_s=max(15.0, 3.0 * float(max_speed_m_s)))

    def __post_init__(self) -> None:
        for name in ("max_speed_m_s", "jump_tolerance_m", "reanchor_after_s", "max_abs_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"PositionGateConfig.{name} must be a finite number > 0, got {value}")


class GateVerdict(str, Enum):
    """What the gate did with a fix."""

    ACCEPTED = "accepted"
    REANCHORED = "reanchored"
    """Accepted: a consistent track far from the old reference lasted ``reanchor_after_s``."""
    NON_FINITE = "non_finite"
    """Rejected: NaN or infinity in position or velocity."""
    OUT_OF_RANGE = "out_of_range"
    """Rejected: a component beyond ``max_abs_m`` (no local frame is that large)."""
    IMPLAUSIBLE_JUMP = "implausible_jump"
    """Rejected: farther from the last accepted fix than the vehicle can fly."""

    @property
    def accepted(self) -> bool:
        """True when the fix is used (accepted, or re-anchored after a gap)."""
        return self in (GateVerdict.ACCEPTED, GateVerdict.REANCHORED)


def reachable(p: Vec, q: Vec, dt_s: float, cfg: PositionGateConfig) -> bool:
    """True when ``q`` can follow ``p`` after ``dt_s`` seconds."""
    d = math.hypot(q[0] - p[0], q[1] - p[1], q[2] - p[2])  # no overflow: inf for absurd values
    return d <= cfg.max_speed_m_s * max(0.0, dt_s) + cfg.jump_tolerance_m


class PositionGate:
    """Stateful filter over a stream of fixes (times in seconds, any monotonic clock)."""

    def __init__(self, cfg: PositionGateConfig | None = None) -> None:
        self.cfg = cfg or PositionGateConfig()
        self.ref: tuple[float, Vec] | None = None
        """(time, position) of the last accepted fix."""
        self._track_start_s: float | None = None
        self._track_last: tuple[float, Vec] | None = None

    def check(self, t_s: float, pos: Vec, vel: Vec) -> GateVerdict:
        """Judge one fix; an accepted fix becomes the reference."""
        p0, p1, p2 = pos
        v0, v1, v2 = vel
        isfinite = math.isfinite  # written out, not all(...) over a generator: every fix of every tick
        if not (isfinite(p0) and isfinite(p1) and isfinite(p2) and isfinite(v0) and isfinite(v1) and isfinite(v2)
                and isfinite(t_s)):
            return GateVerdict.NON_FINITE
        lim = self.cfg.max_abs_m
        if not (abs(p0) <= lim and abs(p1) <= lim and abs(p2) <= lim and abs(v0) <= lim and abs(v1) <= lim
                and abs(v2) <= lim):
            return GateVerdict.OUT_OF_RANGE
        pos = (float(pos[0]), float(pos[1]), float(pos[2]))
        if self.ref is None or reachable(self.ref[1], pos, t_s - self.ref[0], self.cfg):
            self.ref = (t_s, pos)
            self._track_start_s = self._track_last = None
            return GateVerdict.ACCEPTED
        last = self._track_last
        if last is None or not reachable(last[1], pos, t_s - last[0], self.cfg):
            self._track_start_s = t_s  # a new candidate track starts here
        self._track_last = (t_s, pos)
        if t_s - self._track_start_s >= self.cfg.reanchor_after_s:
            self.ref = (t_s, pos)
            self._track_start_s = self._track_last = None
            return GateVerdict.REANCHORED
        return GateVerdict.IMPLAUSIBLE_JUMP
