"""The duct's real wall from a reference flow's nodes (``fisc_agent.map.wall.DuctWall``).

The duct is taken to be axisymmetric about the reference's x axis (DESIGN.md section 2).  ``fisc-ground
fit`` stores the wall in the maps it writes (array ``duct_wall_m``), where an onboard agent flying the
``kinetic`` mode keeps its deviation inside it; ``fisc_ground.fields.flight_score`` measures a flown pass's
excursion against it.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from fisc_agent.map.wall import DuctWall
from fisc_ground.reference.field import ReferenceField


def duct_wall_from_reference(ref: ReferenceField, dx_m: float = 0.1) -> DuctWall:
    """The wall radius per axial bin of ``dx_m``: the largest radius of the reference's nodes there plus
    half the node spacing (the CFD nodes lie strictly inside the wall)."""
    p = ref.points_m
    r = np.hypot(p[:, 1], p[:, 2])
    x0, x1 = float(p[:, 0].min()), float(p[:, 0].max())
    n = max(1, int(round((x1 - x0) / dx_m)) + 1)
    idx = np.clip(np.rint((p[:, 0] - x0) / dx_m).astype(np.int64), 0, n - 1)
    rmax = np.full(n, -np.inf)
    np.maximum.at(rmax, idx, r)
    ok = np.isfinite(rmax)
    xs = x0 + dx_m * np.arange(n)
    return DuctWall(x_m=xs[ok], radius_m=rmax[ok] + 0.5 * _node_spacing(p))


def _node_spacing(points_m: np.ndarray) -> float:
    """Typical distance between neighbouring nodes (median nearest-neighbour distance)."""
    sample = points_m[:: max(1, len(points_m) // 2000)]
    d, _ = cKDTree(points_m).query(sample, k=2)
    return float(np.median(d[:, 1]))
