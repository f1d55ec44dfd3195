"""Position integrity (pure, clock injected): is the local position still the track the vehicle flies?

``position_gate`` drops fixes the vehicle cannot have reached, and after a consistent track far away
re-anchors to it.  That keeps bogus fixes out, but a jump the vehicle *could* have made (an EKF reset
of a few metres, a GNSS glitch being corrected) passes it.  ``IntegrityMonitor`` catches those:

- **reset counter step**: the estimator says it reset its position (PX4 ODOMETRY.reset_counter);
- **jump**: a fix ``|p1 - (p0 + dt (v0 + v1) / 2)| > max_unexplained_m + max_accel_m_s2 dt^2 / 2`` away
  from where the previous fix and both velocities put it (dt from the autopilot's clock when both fixes
  carry it);
- **estimator flags**: the autopilot reports its estimator unhealthy (PX4 ESTIMATOR_STATUS, ArduPilot
  EKF_STATUS_REPORT; ``fisc_agent.flight.health.estimator_health``);
- **autopilot reboot**: its boot time went backwards (SYSTEM_TIME), so its local frame may be new.

After any of them the verdict is ``ok=False`` with the typed reason until the fixes have formed a
consistent track (every step explained by the velocity, no new reset, estimator healthy) for
``consistent_s``; then the new place is taken as the reference (re-anchored) and the verdict is ok again.
Every change of verdict is returned as an ``IntegrityEvent`` for the caller to log.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

Vec = tuple[float, float, float]


class DisruptionReason(StrEnum):
    """Why the position is not trusted."""

    RESET_COUNTER = "reset-counter"
    """The estimator reported a position reset (PX4 ODOMETRY.reset_counter stepped)."""
    JUMP = "jump"
    """A fix moved farther than the velocity explains."""
    ESTIMATOR = "estimator"
    """The autopilot reports its estimator unhealthy (status flags)."""
    AUTOPILOT_REBOOT = "autopilot-reboot"
    """The autopilot rebooted: its local frame may have been set up anew."""


@dataclass(frozen=True)
class IntegrityConfig:
    """Thresholds of ``IntegrityMonitor``."""

    max_unexplained_m: float = 0.5
    """Largest distance between a fix and the place its predecessor's and its own velocity predict [m]."""
    max_accel_m_s2: float = 10.0
    """Acceleration allowed between two fixes: adds ``max_accel_m_s2 * dt^2 / 2`` to the allowance [m/s^2]."""
    consistent_s: float = 2.0
    """How long the track must be consistent after a disruption before the position is trusted again [s]."""
    max_gap_s: float = 1.0
    """Fixes farther apart than this are not compared (a gap is the stale-position rule's business) [s]."""

    def __post_init__(self) -> None:
        for name in ("max_unexplained_m", "max_accel_m_s2", "consistent_s", "max_gap_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"IntegrityConfig.{name} must be a finite number > 0, got {value}")


@dataclass(frozen=True)
class IntegrityVerdict:
    """Whether the position may be flown on."""

    ok: bool = True
    """True: the track is consistent (or nothing was seen yet)."""
    reason: DisruptionReason | None = None
    """Why not ok (None when ok)."""
    since_s: float | None = None
    """Monotonic time since which this verdict holds (the disruption, or the re-anchor) [s]; None: from the start."""
    detail: str = ""
    """The disruption in words ("jump of 3.2 m not explained by the velocity"); "" when ok."""


@dataclass(frozen=True)
class IntegrityEvent:
    """One change of verdict, for the log."""

    t_s: float
    """Monotonic time [s]."""
    verdict: IntegrityVerdict
    """The new verdict."""
    reanchored_ned_m: Vec | None = None
    """On recovery: the position the track was re-anchored at [m]; None on a disruption."""


def unexplained_m(p0: Vec, v0: Vec, p1: Vec, v1: Vec, dt_s: float) -> float:
    """Distance between ``p1`` and ``p0`` advanced by the mean velocity over ``dt_s`` [m]."""
    return math.hypot(*(p1[i] - (p0[i] + 0.5 * (v0[i] + v1[i]) * dt_s) for i in range(3)))


class IntegrityMonitor:
    """Stateful judge of a stream of (accepted) fixes, reset counts and estimator flags."""

    def __init__(self, cfg: IntegrityConfig | None = None) -> None:
        self.cfg = cfg or IntegrityConfig()
        self.verdict = IntegrityVerdict()
        """The current verdict."""
        self.disruptions = 0
        """Disruptions seen so far."""
        self._last: tuple[float, float | None, Vec, Vec] | None = None  # (t, autopilot t, pos, vel)
        self._track_start_s: float | None = None
        self._estimator_ok = True
        self._events: list[IntegrityEvent] = []

    def pop_events(self) -> list[IntegrityEvent]:
        """The verdict changes since the last call, oldest first."""
        events, self._events = self._events, []
        return events

    def _disrupt(self, t_s: float, reason: DisruptionReason, detail: str) -> None:
        self.disruptions += 1
        self._track_start_s = t_s
        self.verdict = IntegrityVerdict(False, reason, t_s if self.verdict.ok else self.verdict.since_s, detail)
        self._events.append(IntegrityEvent(t_s, self.verdict))

    def on_reset(self, t_s: float, steps: int) -> None:
        """The estimator reported ``steps`` position resets at ``t_s``."""
        if steps > 0:
            self._disrupt(t_s, DisruptionReason.RESET_COUNTER, f"estimator position reset (counter +{steps})")

    def on_reboot(self, t_s: float) -> None:
        """The autopilot rebooted at ``t_s``."""
        self._disrupt(t_s, DisruptionReason.AUTOPILOT_REBOOT, "autopilot rebooted")

    def on_estimator(self, t_s: float, ok: bool, detail: str = "") -> None:
        """The autopilot's estimator status at ``t_s``: a change to not ok disrupts; while not ok no
        track counts as consistent."""
        if not ok and self._estimator_ok:
            self._disrupt(t_s, DisruptionReason.ESTIMATOR, f"estimator unhealthy: {detail or 'flags'}")
        elif ok and not self._estimator_ok and not self.verdict.ok:
            self._track_start_s = t_s  # the consistent track counts from the estimator's recovery
        self._estimator_ok = bool(ok)

    def on_fix(self, t_s: float, pos_ned_m: Vec, vel_ned_m_s: Vec, autopilot_t_s: float | None = None) -> IntegrityVerdict:
        """Judge one fix received at monotonic ``t_s`` (``autopilot_t_s``: the autopilot's time of it)."""
        last = self._last
        self._last = (t_s, autopilot_t_s, tuple(pos_ned_m), tuple(vel_ned_m_s))
        if last is not None:
            dt = t_s - last[0]
            if autopilot_t_s is not None and last[1] is not None and 0.0 < autopilot_t_s - last[1] <= self.cfg.max_gap_s:
                dt = autopilot_t_s - last[1]
            if 0.0 <= dt <= self.cfg.max_gap_s:
                off = unexplained_m(last[2], last[3], self._last[2], self._last[3], dt)
                allowed = self.cfg.max_unexplained_m + 0.5 * self.cfg.max_accel_m_s2 * dt * dt
                if off > allowed:
                    self._disrupt(t_s, DisruptionReason.JUMP, f"jump of {off:.2f} m not explained by the velocity "
                                  f"(allowed {allowed:.2f} m in {dt:.3f} s)")
                    return self.verdict
        if not self.verdict.ok and self._estimator_ok and self._track_start_s is not None \
                and t_s - self._track_start_s >= self.cfg.consistent_s:
            self.verdict = IntegrityVerdict(True, None, t_s, "")
            self._track_start_s = None
            self._events.append(IntegrityEvent(t_s, self.verdict, self._last[2]))
        return self.verdict
