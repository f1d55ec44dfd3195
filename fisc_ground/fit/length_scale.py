"""A tunnel sized for the vehicles (issue 37): the same flow in an airspace L times larger (pure).

``fisc-ground fit --length-scale L`` multiplies every length of the reference (its node positions,
hence the duct's wall) and the CV edge by L: the map's grid is the unscaled map's grid, each cube L
times larger, its CV centres L times the unscaled ones.

Similarity.  A vehicle cannot fly faster because the tunnel is larger, so the velocities are kept
(ratio ``VELOCITY_RATIO`` = 1: the speed scaling S is chosen within ``--max-speed`` exactly as at
L = 1) and the times grow with the lengths (ratio L): the swarm flies the same streamlines, with the
same velocity field in units of the peak speed, in L times the time.  The flow's own time scale
(cube edge / speed) and every flow-related time of the map grow by L: the kinetic mode's persistence
(a deviation keeps its direction over the same fraction of a cube).  The vehicle's own times (its
velocity lag, hence the look-ahead) do not: relative to the flow, a vehicle of fixed lag tracks an L
times larger tunnel L times more closely, one source of the fidelity a larger tunnel buys.  The
pressure the fit realises is a velocity spread, kept too; its kinetic pressure (per unit volume) falls
as L^-3, which ``kappa`` (chosen by the build from the spread) absorbs.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any, Mapping

from fisc_ground.reference.field import ReferenceField

VELOCITY_RATIO = 1.0
"""Velocities of the scaled map over the unscaled map's (times scale by L / this)."""


def check_length_scale(length_scale: float) -> float:
    """``length_scale`` as a float; ``ValueError`` naming it unless finite and > 0."""
    if isinstance(length_scale, bool) or not isinstance(length_scale, (int, float)):
        raise ValueError(f"length scale must be a number > 0, is {length_scale!r}")
    v = float(length_scale)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"length scale must be a finite number > 0, is {length_scale!r}")
    return v


def time_ratio(length_scale: float) -> float:
    """Times of the scaled map over the unscaled map's: L / ``VELOCITY_RATIO``."""
    return check_length_scale(length_scale) / VELOCITY_RATIO


def scale_reference(field: ReferenceField, length_scale: float) -> ReferenceField:
    """``field`` with its node positions times L (velocities x ``VELOCITY_RATIO``, pressure and
    density as they are); L = 1 returns ``field`` itself."""
    L = check_length_scale(length_scale)
    if L == 1.0:
        return field
    return replace(field, points_m=field.points_m * L, velocity_m_s=field.velocity_m_s * VELOCITY_RATIO,
                   extras={**field.extras, "length_scale": L})


def map_length_scale(body: Mapping[str, Any]) -> float:
    """The ``length_scale`` a map header records (1 for a map without one)."""
    return float(body.get("length_scale", 1.0))
