"""The map's command at one point, for the streamline tracker's many lookups per tick (pure, no numpy
per call).

``point_command(field, mode, agent_id)`` returns a function ``(x, y, z) -> Vec | None`` (map frame, None
outside the map's CVs) that gives, bit for bit, what ``ScalarField.command`` gives for the point modes
(``mean``, ``slot``, ``interpolated``) and what ``ScalarField.flight`` gives for ``staggered`` without
look-ahead (``fisc_agent.map.lookup.flight_command``: each component linear between the two faces of
the point's cell, ``CommandField.staggered_at``).  It is built once per map and agent: the grid and the
face velocities as Python lists, the ``slot`` choice of each CV remembered once computed (issue 40: a
flying agent's tick samples the field six to eight times; through numpy each sample cost ~40 us).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from fisc_agent.flight.control import ScalarField, Vec
from fisc_agent.map.hashing import slot_hash_int

PointCommand = Callable[[float, float, float], "Vec | None"]
"""Map-frame command at a point, None outside the map's CVs."""


def tracked_mode(resolved_mode: str, explicit_mode: str | None, wall_known: bool) -> tuple[str, bool]:
    """(the field a streamline-tracking agent samples, whether it flies the kinetic deviations) for the
    command mode it resolved (``ScalarField.settings``), the mode it was given (None: the map's
    recommendation) and whether it can turn the deviations before the duct's real wall (``wall_known``: the
    map carries ``duct_wall_m`` and ``AgentConfig.wall_margin_m`` is set).  ``kinetic`` is flown on the
    ``staggered`` field, its deviations carried by the parcel (across the stream by default,
    ``TrackingConfig.kinetic_axes``) when asked for explicitly, or recommended by a map that carries the
    wall: without it they would turn only at the CV staircase, whose outer cubes lie partly outside a real
    duct, so a recommendation alone then flies the staggered field."""
    kinetic = resolved_mode == "kinetic"
    return ("staggered" if kinetic else resolved_mode), kinetic and (explicit_mode == "kinetic" or wall_known)


def point_command(sfield: ScalarField, mode: str, agent_id: int) -> PointCommand:
    """The command of agent ``agent_id`` in ``mode`` (a point mode or ``staggered``) at a map-frame point."""
    if mode == "staggered":
        return _staggered(sfield)
    if mode == "slot":
        return _slot(sfield, agent_id)
    if mode == "mean":
        return _mean(sfield)
    return lambda x, y, z: sfield.command(x, y, z, agent_id, mode)


class _Grid:
    """The CV grid as flat Python lists (``ScalarField.cv_of``'s arithmetic)."""

    def __init__(self, sfield: ScalarField) -> None:
        f = sfield.field
        self.ox, self.oy, self.oz = (float(v) for v in f.origin_m)
        self.l = float(f.cell_size_m)
        self.nx, self.ny, self.nz = (int(s) for s in f.grid_cv.shape)
        self.grid: list[int] = np.asarray(f.grid_cv, dtype=np.int64).ravel().tolist()


def _mean(sfield: ScalarField) -> PointCommand:
    g = _Grid(sfield)
    ox, oy, oz, l, nx, ny, nz, grid = g.ox, g.oy, g.oz, g.l, g.nx, g.ny, g.nz, g.grid
    mean: list[Vec] = [tuple(r) for r in np.asarray(sfield.field.mean_cmd_m_s, dtype=float).tolist()]
    floor = math.floor

    def command(x: float, y: float, z: float) -> Vec | None:
        i, j, k = floor((x - ox) / l), floor((y - oy) / l), floor((z - oz) / l)
        if 0 <= i < nx and 0 <= j < ny and 0 <= k < nz:
            cv = grid[(i * ny + j) * nz + k]
            if cv >= 0:
                return mean[cv]
        return None

    return command


def _slot(sfield: ScalarField, agent_id: int) -> PointCommand:
    g = _Grid(sfield)
    ox, oy, oz, l, nx, ny, nz, grid = g.ox, g.oy, g.oz, g.l, g.nx, g.ny, g.nz, g.grid
    f = sfield.field
    slot = np.asarray(f.slot_cmd_m_s, dtype=float)
    n_star = np.asarray(f.n_star, dtype=np.int64).tolist()
    chosen: dict[int, Vec] = {}
    floor = math.floor

    def command(x: float, y: float, z: float) -> Vec | None:
        i, j, k = floor((x - ox) / l), floor((y - oy) / l), floor((z - oz) / l)
        if 0 <= i < nx and 0 <= j < ny and 0 <= k < nz:
            cv = grid[(i * ny + j) * nz + k]
            if cv >= 0:
                v = chosen.get(cv)
                if v is None:
                    v = chosen[cv] = tuple(slot[cv, slot_hash_int(agent_id, cv) % n_star[cv]].tolist())
                return v
        return None

    return command


def _staggered(sfield: ScalarField) -> PointCommand:
    g = _Grid(sfield)
    ox, oy, oz, l, nx, ny, nz, grid = g.ox, g.oy, g.oz, g.l, g.nx, g.ny, g.nz, g.grid
    f = sfield.field
    if f.face_u_m_s is None:
        raise ValueError("modes staggered/kinetic need a map with face velocities (schema version 2)")
    fx, fy, fz = (np.asarray(a, dtype=float) for a in f.face_u_m_s)
    ii, jj, kk = np.nonzero(np.asarray(f.grid_cv) >= 0)
    cvs = np.asarray(f.grid_cv)[ii, jj, kk]
    n = int(cvs.max()) + 1 if cvs.size else 0
    lower = np.zeros((n, 3))
    upper = np.zeros((n, 3))
    lower[cvs] = np.stack([fx[ii, jj, kk], fy[ii, jj, kk], fz[ii, jj, kk]], axis=1)
    upper[cvs] = np.stack([fx[ii + 1, jj, kk], fy[ii, jj + 1, kk], fz[ii, jj, kk + 1]], axis=1)
    faces: list[tuple[float, float, float, float, float, float]] = [
        (a[0], a[1], a[2], b[0], b[1], b[2]) for a, b in zip(lower.tolist(), upper.tolist())]
    floor, isfinite = math.floor, math.isfinite

    def command(x: float, y: float, z: float) -> Vec | None:
        px, py, pz = (x - ox) / l, (y - oy) / l, (z - oz) / l
        i, j, k = floor(px), floor(py), floor(pz)
        if 0 <= i < nx and 0 <= j < ny and 0 <= k < nz:
            cv = grid[(i * ny + j) * nz + k]
            if cv >= 0:
                tx, ty, tz = px - i, py - j, pz - k
                lx, ly, lz, ux, uy, uz = faces[cv]
                v = ((1.0 - tx) * lx + tx * ux, (1.0 - ty) * ly + ty * uy, (1.0 - tz) * lz + tz * uz)
                if isfinite(v[0]) and isfinite(v[1]) and isfinite(v[2]):
                    return v
        return None

    return command
