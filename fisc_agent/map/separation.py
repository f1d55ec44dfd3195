"""Separation between vehicles as a designed quantity (issue 37): the minimum spacing d_min a map is
designed for, from a vehicle radius and a position uncertainty, recorded in the map header.

This module is the one home of the rule and its defaults; maps written before it carry no
``separation`` header and read as the defaults.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

DEFAULT_VEHICLE_RADIUS_M = 0.25
"""Half the span of a 0.5 m quadcopter (props included) [m]."""
DEFAULT_POSITION_SIGMA_M = 0.1
"""1-sigma error of one vehicle's horizontal position *relative to its neighbours* on GNSS [m]: nearby
receivers share most of their error (same satellites, same atmosphere), so the relative error is far
below the absolute one (about 1 m)."""
SIGMA_FACTOR = 3.0
"""d_min keeps this many sigmas of the two vehicles' relative position error (sqrt(2) sigma) clear."""


def d_min_m(vehicle_radius_m: float, position_sigma_m: float, k: float = SIGMA_FACTOR) -> float:
    """Minimum centre-to-centre spacing: two radii plus k sigmas of the relative position error,
    ``2 r + k sqrt(2) sigma`` [m]."""
    if not (math.isfinite(vehicle_radius_m) and vehicle_radius_m >= 0):
        raise ValueError(f"vehicle radius must be a finite number >= 0 m, is {vehicle_radius_m!r}")
    if not (math.isfinite(position_sigma_m) and position_sigma_m >= 0):
        raise ValueError(f"position sigma must be a finite number >= 0 m, is {position_sigma_m!r}")
    return 2.0 * vehicle_radius_m + k * math.sqrt(2.0) * position_sigma_m


DEFAULT_D_MIN_M = d_min_m(DEFAULT_VEHICLE_RADIUS_M, DEFAULT_POSITION_SIGMA_M)
"""d_min of the defaults (0.92 m)."""


@dataclass(frozen=True)
class Separation:
    """What a map is designed to keep between its vehicles (header key ``separation``)."""

    vehicle_radius_m: float = DEFAULT_VEHICLE_RADIUS_M
    """Vehicle radius [m]."""
    position_sigma_m: float = DEFAULT_POSITION_SIGMA_M
    """Relative position uncertainty, 1 sigma [m]."""

    @property
    def d_min_m(self) -> float:
        """The minimum spacing (``d_min_m``)."""
        return d_min_m(self.vehicle_radius_m, self.position_sigma_m)


def map_separation(body: Mapping[str, Any]) -> Separation:
    """The ``separation`` a map header records (the defaults for a map without one)."""
    sep = body.get("separation") or {}
    return Separation(float(sep.get("vehicle_radius_m", DEFAULT_VEHICLE_RADIUS_M)),
                      float(sep.get("position_sigma_m", DEFAULT_POSITION_SIGMA_M)))
