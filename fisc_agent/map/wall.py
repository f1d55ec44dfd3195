"""The duct's real wall as a map carries it, and the ``kinetic`` deviation kept inside it (pure, numpy).

The CV staircase is the simulator's duct, but its outer cubes lie partly outside a real one: the
cubes a fit keeps are those holding any CFD node.  A deviation reflected only at the staircase
therefore carries a real vehicle up to a cube's width outside the real wall.  The map can carry the
wall itself (array ``duct_wall_m``: stations x and radius, the duct axisymmetric about the map's x
axis as DESIGN.md section 2 takes it; ``fisc_ground.maps.duct_wall.duct_wall_from_reference`` derives it
from the CFD nodes), and an onboard agent flying the ``kinetic`` mode keeps its deviation inside it
(``reflect_at_wall``).  The simulator's agents fly the staircase and do not use it.

The margin adapts to the duct (``effective_margin_m``, issue 37): the configured margin (0.8 m, which
covers PX4's estimator excursions) is a cap used where the duct is wide; where it narrows, the margin
shrinks to ``WALL_MARGIN_FRACTION`` of the local radius so the inner part of the cross-section stays
free for the deviations (with 0.8 m at the throat's 0.78 m radius every deviation folded onto the
axis), but never below d_min / 2: the clearance a vehicle keeps from the wall is the one it keeps
from a neighbour's half of the spacing (its radius and its share of the position error).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

#: The map array that carries the wall: (k, 2) float64 rows (x [m], radius [m]), x strictly ascending.
WALL_ARRAY = "duct_wall_m"


@dataclass(frozen=True)
class DuctWall:
    """Axisymmetric wall radius sampled along x (map frame)."""

    x_m: np.ndarray
    """(k,) station positions along the axis [m], strictly ascending, k >= 2."""
    radius_m: np.ndarray
    """(k,) wall radius at each station [m], > 0."""

    def __post_init__(self) -> None:
        x, r = np.asarray(self.x_m, dtype=float), np.asarray(self.radius_m, dtype=float)
        if x.ndim != 1 or x.shape != r.shape or x.size < 2:
            raise ValueError(f"duct wall: need two equal 1-D arrays of >= 2 stations, got {x.shape} and {r.shape}")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(r))):
            raise ValueError("duct wall: stations and radii must be finite")
        if not np.all(np.diff(x) > 0):
            raise ValueError("duct wall: stations must be strictly ascending in x")
        if not np.all(r > 0):
            raise ValueError("duct wall: radii must be > 0")
        object.__setattr__(self, "x_m", x)
        object.__setattr__(self, "radius_m", r)

    @classmethod
    def from_array(cls, rows: np.ndarray) -> "DuctWall":
        """From the map's (k, 2) array ``duct_wall_m``."""
        a = np.asarray(rows, dtype=float)
        if a.ndim != 2 or a.shape[1] != 2:
            raise ValueError(f"duct wall: expected (k, 2) rows of x, radius, got shape {a.shape}")
        return cls(a[:, 0].copy(), a[:, 1].copy())

    def as_array(self) -> np.ndarray:
        """The (k, 2) array ``duct_wall_m`` of a map."""
        return np.column_stack([self.x_m, self.radius_m])

    def radius_at(self, x_m: np.ndarray | float) -> np.ndarray:
        """Wall radius at axial positions ``x_m`` [m] (linear between stations, the end radius beyond)."""
        return np.interp(x_m, self.x_m, self.radius_m)


def map_wall(arrays: Mapping[str, np.ndarray]) -> DuctWall | None:
    """The wall a map's arrays carry (``duct_wall_m``, checked when the map was decoded); None without."""
    rows = arrays.get(WALL_ARRAY)
    return None if rows is None else DuctWall.from_array(rows)


WALL_MARGIN_FRACTION = 0.5
"""Where the duct is narrower than margin / this, the margin is this fraction of the local radius
(``effective_margin_m``): the deviations turn in the outer half of the radius and fly free in the inner
half."""


def effective_margin_m(radius_m: np.ndarray | float, margin_m: float, d_min_m: float | None,
                       fraction: float = WALL_MARGIN_FRACTION) -> np.ndarray:
    """The wall margin at a station of local duct radius ``radius_m`` [m]:
    ``min(margin, max(d_min / 2, fraction x R))``.

    ``margin_m`` (the configured margin) is the cap, used where ``fraction x R >= margin``; narrower,
    the margin is ``fraction x R``, never below ``d_min / 2`` (a vehicle's share of the spacing), and
    never above the configured margin (a smaller one, e.g. with motion capture, is kept).  ``d_min_m``
    None: the configured margin everywhere (the rule before issue 37).  Where d_min / 2 >= R the whole
    cross-section turns outward deviations inward: the duct is too narrow to deviate in, and the vehicle
    flies the axis."""
    r = np.asarray(radius_m, dtype=float)
    if not (np.isfinite(margin_m) and margin_m >= 0):
        raise ValueError(f"wall margin must be a finite number >= 0 m, is {margin_m!r}")
    if d_min_m is None:
        return np.full_like(r, float(margin_m))
    if not (np.isfinite(d_min_m) and d_min_m >= 0) or not (0.0 < fraction <= 1.0):
        raise ValueError(f"effective_margin_m: d_min {d_min_m!r} must be >= 0 m and the fraction {fraction!r} in (0, 1]")
    return np.minimum(float(margin_m), np.maximum(0.5 * float(d_min_m), fraction * r))


def reflect_at_wall(points_m: np.ndarray, deviation_m_s: np.ndarray, wall: DuctWall, margin_m: float,
                    d_min_m: float | None = None) -> np.ndarray:
    """(m, 3) deviations with the radial component mirrored where it heads outward within the margin
    of the wall (radius >= wall radius - margin at the point's x); the others unchanged.  The margin is
    ``margin_m``, or with ``d_min_m`` given the duct-adapted ``effective_margin_m`` at the point's x.

    Map frame, the axis along x.  Stateless: a deviation that keeps pointing outward is mirrored at every
    call inside the zone, so a point moved by it stays near the zone's inner edge instead of crossing
    the wall.  On the axis (radius 0) nothing is mirrored."""
    p = np.atleast_2d(np.asarray(points_m, dtype=float))
    d = np.array(np.atleast_2d(deviation_m_s), dtype=float)
    r = np.hypot(p[:, 1], p[:, 2])
    safe = np.where(r > 0, r, 1.0)
    ny, nz = p[:, 1] / safe, p[:, 2] / safe
    radial = d[:, 1] * ny + d[:, 2] * nz
    R = wall.radius_at(p[:, 0])
    mirror = (r > 0) & (radial > 0) & (r >= R - effective_margin_m(R, margin_m, d_min_m))
    k = np.where(mirror, 2.0 * radial, 0.0)
    d[:, 1] -= k * ny
    d[:, 2] -= k * nz
    return d


def rejoin_inset_m(radius_m: float, margin_m: float) -> float:
    """How far inside the wall, at a station of local radius ``radius_m`` [m], a vehicle rejoining the flow
    must be before it flows again (a fleet resume, the end of a geofence RETURN) [m]: the wall margin
    ``margin_m``, at most ``WALL_MARGIN_FRACTION`` of the radius (so the inner part of a narrow section
    always qualifies).

    Without it a vehicle that a hold left at the wall (stock PX4 SIH drifts up to 1.2 m in a 4 s hold on
    its biased velocity estimate) flowed again from the edge of the map and left it within 0.2-6 s,
    and the geofence held it to the end of the flight (tests/faults, docs/zenoh.md)."""
    return min(float(margin_m), WALL_MARGIN_FRACTION * float(radius_m))


def rejoin_point(wall: DuctWall, pos_m: tuple[float, float, float], margin_m: float) -> tuple[float, float, float] | None:
    """Where a vehicle at ``pos_m`` (map frame) heads to rejoin the flow clear of the wall, or None when it is
    clear already (its radius at most the wall's minus ``rejoin_inset_m``).  The point keeps the axial
    station and the bearing and lies twice the inset inside the wall (on the axis at worst), so that a
    proportional approach crosses the inset line at speed instead of creeping up to it."""
    x, y, z = (float(v) for v in pos_m)
    R = float(wall.radius_at(x))
    inset = rejoin_inset_m(R, margin_m)
    r = math.hypot(y, z)
    if r <= R - inset:
        return None
    target_r = max(R - 2.0 * inset, 0.0)
    return (x, y * target_r / r, z * target_r / r)
