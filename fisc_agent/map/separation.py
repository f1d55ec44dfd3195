"""Separation between vehicles as a designed quantity (issue 37): the minimum spacing d_min a map is
designed for, from a vehicle radius and a position uncertainty, recorded in the map header.

This module is the one home of the rule and its defaults; maps written before it carry no
``separation`` header and read as the defaults.  A map fitted since issue 37 also records what the
tunnel allows at that spacing (``fisc_ground.fit.separation_budget``): ``max_in_tunnel`` vehicles at
once and one admission per ``admission_period_s``; agents read them here (``Separation``), and old
maps read as None (no budget: no admission stagger unless one is given).
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

    max_in_tunnel: int | None = None
    """The map's budget: the most vehicles in the tunnel at once at this spacing (None: not recorded)."""
    admission_period_s: float | None = None
    """The map's budget: the inlet admits one vehicle per this period [s] (None: not recorded)."""

    def __post_init__(self) -> None:
        d_min_m(self.vehicle_radius_m, self.position_sigma_m)  # validates
        n, t = self.max_in_tunnel, self.admission_period_s
        if n is not None and not (isinstance(n, int) and not isinstance(n, bool) and n >= 1):
            raise ValueError(f"separation: max_in_tunnel must be an integer >= 1, is {n!r}")
        if t is not None and not (isinstance(t, (int, float)) and math.isfinite(t) and t > 0):
            raise ValueError(f"separation: admission_period_s must be a finite number > 0 s, is {t!r}")

    @property
    def d_min_m(self) -> float:
        """The minimum spacing (``d_min_m``)."""
        return d_min_m(self.vehicle_radius_m, self.position_sigma_m)


def map_separation(body: Mapping[str, Any]) -> Separation:
    """The ``separation`` a map header records (the defaults for a map without one; ``ValueError``
    naming the key for a malformed one: ``fisc_agent.map.codec`` checks it on decoding)."""
    sep = body.get("separation") or {}
    if not isinstance(sep, Mapping):
        raise ValueError(f"separation: must be a table, is {type(sep).__name__}")
    n, t = sep.get("max_in_tunnel"), sep.get("admission_period_s")
    for key in ("vehicle_radius_m", "position_sigma_m", "admission_period_s"):
        v = sep.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
            raise ValueError(f"separation: {key} must be a number, is {v!r}")
    return Separation(float(sep.get("vehicle_radius_m", DEFAULT_VEHICLE_RADIUS_M)),
                      float(sep.get("position_sigma_m", DEFAULT_POSITION_SIGMA_M)),
                      max_in_tunnel=n, admission_period_s=None if t is None else float(t))
