"""Is the vehicle fit to arm and to start a pass? (pure; the autopilot's own health as input)

``arming_blockers`` lists what forbids arming now; ``battery_low`` is the ``--min-battery`` rule;
``health_problems`` is the short list telemetry carries.  An unknown value (the autopilot does not
report it) blocks nothing: the autopilot's own pre-arm checks still apply to it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

from fisc_agent.config import AgentConfig
from fisc_agent.flight.control import MapGeometry, Vec
from fisc_agent.flight.health import BAD_SYSTEM_STATES, VehicleHealth


class HealthKind(StrEnum):
    """What a health problem is about (telemetry carries one flag per kind: ``telemetry_codec.HEALTH_NAMES``)."""

    ESTIMATOR = "estimator"
    BATTERY = "battery"
    SYSTEM = "system"
    POSITION = "position"
    GPS = "gps"
    ORIGIN = "origin"
    TAKEOFF = "takeoff"
    OTHER = "other"


@dataclass(frozen=True)
class HealthProblem:
    """One thing wrong with the vehicle: its kind, and the phrase a person reads."""

    kind: HealthKind
    """What it is about."""
    text: str
    """The phrase ("battery 18 % < 20 %")."""

    def __str__(self) -> str:
        return self.text


def battery_low(health: VehicleHealth, min_battery_pct: float | None) -> bool:
    """True when the reported battery is strictly below ``min_battery_pct`` (unknown or no rule: False)."""
    return min_battery_pct is not None and health.battery_pct is not None and health.battery_pct < min_battery_pct


def distance_to_box_m(pos: Vec, lo: Vec, hi: Vec) -> float:
    """Euclidean distance from ``pos`` to the axis-aligned box [lo, hi] (0 inside or on it)."""
    return math.sqrt(sum(max(lo[i] - pos[i], 0.0, pos[i] - hi[i]) ** 2 for i in range(3)))


def health_problems(health: VehicleHealth, min_battery_pct: float | None) -> tuple[HealthProblem, ...]:
    """What is wrong with the vehicle by its own report; () when nothing is."""
    out = []
    if battery_low(health, min_battery_pct):
        out.append(HealthProblem(HealthKind.BATTERY, f"battery {health.battery_pct:g} % < {min_battery_pct:g} %"))
    if health.estimator_ok is False:
        out.append(HealthProblem(HealthKind.ESTIMATOR, "estimator: " + (health.estimator_detail or "not healthy")))
    if health.system_state in BAD_SYSTEM_STATES:
        out.append(HealthProblem(HealthKind.SYSTEM, f"autopilot state {health.system_state.value}"))
    return tuple(out)


def arming_blockers(health: VehicleHealth, cfg: AgentConfig, pos: Vec | None, geom: MapGeometry | None) -> list[str]:
    """Why the vehicle must not arm now ([] : it may): a health problem, or a start point farther than
    ``cfg.max_start_distance_m`` from the map's bounding box."""
    out = [p.text for p in health_problems(health, cfg.min_battery_pct)]
    if pos is not None and geom is not None:
        d = distance_to_box_m(pos, geom.lo_m, geom.hi_m)
        if d > cfg.max_start_distance_m:
            out.append(f"start point {d:.0f} m from the map (more than {cfg.max_start_distance_m:.0f} m: "
                       "check --origin / --geodetic-anchor)")
    return out
