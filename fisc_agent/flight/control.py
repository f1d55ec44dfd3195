"""Onboard control core (pure): position -> CV -> command -> clamped velocity setpoint.

``ScalarField`` is the single-agent fast path of ``lookup.CommandField`` (plain Python floats
and lists, no numpy calls per step: an onboard computer flies one vehicle, and numpy costs
about a microsecond per call).  It implements the same rules, and the tests check that both
agree on every mode.  ``MapGeometry`` derives the inlet disc, outlet plane and bounding box the
mission needs; ``entry_point`` picks the way into the tunnel (``routes`` plans the waypoints); the
clamp functions bound every setpoint's speed and acceleration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fisc_agent.map.hashing import slot_hash_int
from fisc_agent.map.kinetic import DeviationState, kinetic_deviation
from fisc_agent.map.lookup import (
    COMMAND_MODES,
    FACE_MODES,
    PAPER_SETTINGS,
    RETURN_RADIUS_CELLS,
    CommandField,
    FlightSettings,
    flight_command,
    return_command,
)
from fisc_agent.map.codec import MapError, MapErrorKind
from fisc_agent.map.separation import Separation
from fisc_agent.map.wall import DuctWall, reflect_at_wall
from fisc_agent.flight.tracking import cross_stream
from fisc_agent.flight.spacing import ENTRY_POINTS, HOLD_FLOOR_MARGIN_M, hold_altitude_m, lattice_hold_points

Vec = tuple[float, float, float]
ZERO: Vec = (0.0, 0.0, 0.0)
GOLDEN_ANGLE_RAD = math.pi * (3.0 - math.sqrt(5.0))


class ScalarField:
    """One-point lookups on a ``CommandField`` (map frame), without numpy in the hot path."""

    def __init__(self, field: CommandField, wall: DuctWall | None = None, separation: Separation | None = None) -> None:
        self.field = field
        self.wall = wall
        """The duct's real wall where the map carries it (``fisc_agent.map.wall.map_wall``), else None."""
        self.separation = separation if separation is not None else Separation()
        """The map's separation and budget (``fisc_agent.map.separation.map_separation``): d_min sets the
        duct-adapted wall margin, the budget the default admission (``spacing.entry_schedule``)."""
        self._ox, self._oy, self._oz = (float(v) for v in field.origin_m)
        self._l = float(field.cell_size_m)
        self._nx, self._ny, self._nz = (int(s) for s in field.grid_cv.shape)
        self._grid: list[int] = np.asarray(field.grid_cv, dtype=np.int64).ravel().tolist()
        self._mean: list[Vec] = [tuple(r) for r in np.asarray(field.mean_cmd_m_s, dtype=float).tolist()]
        self._slot: list[list[Vec]] = [[tuple(v) for v in cv] for cv in np.asarray(field.slot_cmd_m_s, dtype=float).tolist()]
        self._n_star: list[int] = np.asarray(field.n_star, dtype=np.int64).tolist()
        self.centers: list[Vec] = [tuple(r) for r in np.asarray(field.centers_m, dtype=float).tolist()]
        self._dev_state: DeviationState | None = None

    def _cell_id(self, i: int, j: int, k: int) -> int:
        if 0 <= i < self._nx and 0 <= j < self._ny and 0 <= k < self._nz:
            return self._grid[(i * self._ny + j) * self._nz + k]
        return -1

    def cv_of(self, x: float, y: float, z: float) -> int:
        """CV id of a map-frame point, -1 outside the map's CVs (as ``CommandField.cv_of``)."""
        l = self._l
        return self._cell_id(math.floor((x - self._ox) / l), math.floor((y - self._oy) / l),
                             math.floor((z - self._oz) / l))

    def command(self, x: float, y: float, z: float, agent_id: int, mode: str = "mean",
                cv: int | None = None) -> Vec | None:
        """Commanded map-frame velocity [m/s] at a point; None outside the map's CVs."""
        if cv is None:
            cv = self.cv_of(x, y, z)
        if cv < 0:
            return None
        if mode == "mean":
            return self._mean[cv]
        if mode == "slot":
            return self._slot[cv][slot_hash_int(agent_id, cv) % self._n_star[cv]]
        if mode == "interpolated":
            return self._interpolate(x, y, z, cv)
        raise ValueError(f"unknown command mode {mode!r}; choose one of {', '.join(COMMAND_MODES)}")

    def settings(self, mode: str | None = None, lookahead_s: float | None = None) -> FlightSettings:
        """Flight settings: the given mode / look-ahead, the map's recommended ones where None."""
        base = self.field.recommended or PAPER_SETTINGS
        return FlightSettings(base.mode if mode is None else mode,
                              base.lookahead_s if lookahead_s is None else float(lookahead_s), base.persistence_s)

    def flight(self, pos: Vec, vel: Vec | None, agent_id: int, t_s: float, mode: str | None = None,
               lookahead_s: float | None = None, cv: int | None = None) -> Vec | None:
        """This vehicle's command: ``fisc_agent.map.lookup.flight_command`` (the simulator's function) for
        one agent; the kinetic-mode state is kept here (one ``ScalarField`` per vehicle).  ``mode`` and
        ``lookahead_s`` None: the map's recommended settings; a look-ahead identified in flight is just
        passed in.  ``vel`` None (no velocity estimate yet) flies without look-ahead.  None outside the map."""
        st = self.settings(mode, lookahead_s)
        if vel is None:
            st = FlightSettings(st.mode, 0.0, st.persistence_s)
            vel = ZERO
        cmd, _, self._dev_state = flight_command(
            self.field, np.array([pos], dtype=float), np.array([vel], dtype=float), np.array([agent_id]),
            t_s, st, self._dev_state, None if cv is None else np.array([cv]))
        if not np.all(np.isfinite(cmd[0])):
            return None
        return (float(cmd[0, 0]), float(cmd[0, 1]), float(cmd[0, 2]))

    def deviation(self, pos: Vec, vel: Vec | None, agent_id: int, t_s: float,
                  wall_margin_m: float | None = None, stream: Vec | None = None) -> Vec:
        """This vehicle's ``kinetic`` deviation at ``pos`` [m/s]: the CV's fitted spread times the
        persistent, wall-reflected direction of ``fisc_agent.map.kinetic.kinetic_deviation`` (the
        simulator's rule; its state is kept here, shared with ``flight``).  Zero outside the CVs or
        on a map without a fitted spread.  Streamline tracking adds it to its parcel
        (``fisc_agent.flight.tracking.ParcelTracker.step``).  ``wall_margin_m`` given and the map carrying
        the duct's real wall: the outward radial part is mirrored within that margin of it
        (``fisc_agent.map.wall.reflect_at_wall``).  ``stream`` given (the field's unit direction at ``pos``,
        ``KineticAxes.CROSS_STREAM``): the deviation is turned across it at its full magnitude
        (``fisc_agent.flight.tracking.cross_stream``) before that mirror, which then sees the turned
        deviation: turned after it, a mostly upstream deviation beside a diverging wall (whose stream tilts
        outward) became a full-speed outward one and took a real PX4 out of the map."""
        cv = self.cv_of(*pos)
        spread = self.field.spread_m_s
        if cv < 0 or spread is None:
            return ZERO
        st = self._dev_state if self._dev_state is not None else DeviationState.new(1)
        point = np.array([pos], dtype=float)
        d, self._dev_state = kinetic_deviation(
            self.field, point, np.array([agent_id]), t_s, self.settings().persistence_s, st,
            None if vel is None else np.array([vel], dtype=float))
        if stream is not None:
            d = np.array([cross_stream((float(d[0, 0]), float(d[0, 1]), float(d[0, 2])), stream)])
        if wall_margin_m is not None and self.wall is not None:
            # the fixed margin onboard: the duct-adapted one (``effective_margin_m`` with the map's d_min,
            # 0.46 m at the throat) took one real PX4 0.43 m beyond the wall by SIH's ground truth (PX4's
            # altitude estimate errs by up to 0.9 m), over the 0.3 m bound; it stays for the simulator
            # and the studies until issue 37's real-swarm flights settle the margin
            d = reflect_at_wall(point, d, self.wall, wall_margin_m, None)
        s = float(spread[cv])
        return (s * float(d[0, 0]), s * float(d[0, 1]), s * float(d[0, 2]))

    def _interpolate(self, x: float, y: float, z: float, cv: int) -> Vec:
        l = self._l
        fx, fy, fz = (x - self._ox) / l - 0.5, (y - self._oy) / l - 0.5, (z - self._oz) / l - 0.5
        ix, iy, iz = math.floor(fx), math.floor(fy), math.floor(fz)
        tx, ty, tz = fx - ix, fy - iy, fz - iz
        ax = ay = az = wsum = 0.0
        for dx in (0, 1):
            wx = tx if dx else 1.0 - tx
            for dy in (0, 1):
                wy = ty if dy else 1.0 - ty
                for dz in (0, 1):
                    cid = self._cell_id(ix + dx, iy + dy, iz + dz)
                    if cid < 0:
                        continue
                    w = wx * wy * (tz if dz else 1.0 - tz)
                    m = self._mean[cid]
                    ax += w * m[0]
                    ay += w * m[1]
                    az += w * m[2]
                    wsum += w
        if wsum > 1e-12:
            return (ax / wsum, ay / wsum, az / wsum)
        return self._mean[cv]

    def return_command(self, pos: Vec) -> Vec | None:
        """The geofence ``return`` command at a point outside the CVs (``fisc_agent.map.lookup.return_command``,
        the simulator's rule): rejoin the flow of the nearest CV within ``RETURN_RADIUS_CELLS`` cells,
        passing over stagnant ones (``CommandField.return_cv_within``); None when no CV is that close
        (the caller flies straight back instead)."""
        near = self.field.return_cv_within(np.array([pos], dtype=float), RETURN_RADIUS_CELLS)
        if near[0] < 0:
            return None
        cmd = return_command(self.field, np.array([pos], dtype=float), near)[0]
        return (float(cmd[0]), float(cmd[1]), float(cmd[2]))

    def nearest_cv(self, x: float, y: float, z: float, radius_cells: int = 2) -> int:
        """Nearest CV: within ``radius_cells`` via ``nearest_cv_within``, else the global nearest centre."""
        j = int(self.field.nearest_cv_within(np.array([[x, y, z]]), radius_cells)[0])
        if j >= 0:
            return j
        d2 = np.sum((np.asarray(self.field.centers_m) - np.array([x, y, z])) ** 2, axis=1)
        return int(np.argmin(d2))


# ---- clamps and simple guidance --------------------------------------------------------
def clamp_speed(v: Vec, max_speed_m_s: float) -> Vec:
    """Scale ``v`` down so that |v| <= max_speed; non-finite input -> zero vector."""
    vx, vy, vz = v
    n2 = vx * vx + vy * vy + vz * vz
    if not math.isfinite(n2):
        return ZERO
    if n2 > max_speed_m_s * max_speed_m_s:
        k = max_speed_m_s / math.sqrt(n2)
        return (vx * k, vy * k, vz * k)
    return (vx, vy, vz)


def clamp_velocity(v: Vec, v_prev: Vec, dt_s: float, max_speed_m_s: float, max_accel_m_s2: float) -> Vec:
    """Speed clamp |v| <= max_speed, then acceleration clamp |v - v_prev| / dt <= max_accel.

    With ``v_prev`` itself within the speed limit the result is too (the ball is convex).
    """
    vx, vy, vz = clamp_speed(v, max_speed_m_s)
    dx, dy, dz = vx - v_prev[0], vy - v_prev[1], vz - v_prev[2]
    dv2 = dx * dx + dy * dy + dz * dz
    dv_max = max_accel_m_s2 * max(dt_s, 0.0)
    if dv2 > dv_max * dv_max:
        k = dv_max / math.sqrt(dv2)
        return (v_prev[0] + dx * k, v_prev[1] + dy * k, v_prev[2] + dz * k)
    return (vx, vy, vz)


def goto_velocity(pos: Vec, target: Vec, speed_m_s: float, gain_1_s: float = 1.0) -> Vec:
    """Proportional approach: ``gain * (target - pos)``, capped at ``speed_m_s``."""
    return clamp_speed(((target[0] - pos[0]) * gain_1_s, (target[1] - pos[1]) * gain_1_s,
                        (target[2] - pos[2]) * gain_1_s), speed_m_s)


def approach_time_s(distance_m: float, speed_m_s: float, radius_m: float, gain_1_s: float = 1.0) -> float:
    """Time ``goto_velocity`` takes to bring a vehicle that follows it exactly from ``distance_m`` to
    within ``radius_m`` of its target: at ``speed_m_s`` down to speed / gain, then exponentially [s]."""
    if distance_m <= radius_m:
        return 0.0
    knee_m = speed_m_s / gain_1_s
    cruise_s = max(distance_m - knee_m, 0.0) / speed_m_s
    return cruise_s + max(math.log(min(distance_m, knee_m) / radius_m), 0.0) / gain_1_s


def speed_for_arrival(legs_m: list[float], time_s: float, radius_m: float, lo_m_s: float, hi_m_s: float,
                      gain_1_s: float = 1.0) -> float:
    """The ``goto_velocity`` speed cap that flies the legs ``legs_m`` (the first from the vehicle to
    its next waypoint) in ``time_s`` by ``approach_time_s``, within [``lo_m_s``, ``hi_m_s``]: ``hi``
    when even it arrives late (or ``time_s`` <= 0), ``lo`` when even it arrives early (bisection).
    Re-solved every tick, it closes the loop on the arrival time: at the join speed, stock PX4 (lag
    0.9 s, gain 0.84) arrived 2-3 s late, in the next window; two entered 0.14 s apart (0.10 m)."""
    def total(v: float) -> float:
        return sum(approach_time_s(d, v, radius_m, gain_1_s) for d in legs_m)

    if not (0.0 < lo_m_s <= hi_m_s):
        raise ValueError(f"speed_for_arrival: need 0 < lo <= hi, got {lo_m_s!r}, {hi_m_s!r}")
    if time_s <= 0.0 or total(hi_m_s) >= time_s:
        return hi_m_s
    if total(lo_m_s) <= time_s:
        return lo_m_s
    a, b = lo_m_s, hi_m_s
    for _ in range(30):
        m = 0.5 * (a + b)
        a, b = (m, b) if total(m) > time_s else (a, m)
    return 0.5 * (a + b)


def distance(a: Vec, b: Vec) -> float:
    """Euclidean distance between two 3-vectors [m]."""
    return math.sqrt((a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2 + (a[2] - b[2]) ** 2)


# ---- map geometry, entry point, join path ----------------------------------------------
@dataclass(frozen=True)
class MapGeometry:
    """Where the tunnel is, derived from a map's CVs (map frame)."""

    x_inlet_m: float
    """Inlet plane: lower x face of the first CV slice [m]."""
    x_outlet_m: float
    """Outlet plane: upper x face of the last CV slice [m]."""
    lo_m: Vec
    """Lower corner of the CVs' bounding box [m]."""
    hi_m: Vec
    """Upper corner of the CVs' bounding box [m]."""
    inlet_center_yz_m: tuple[float, float]
    """(y, z) centre of the inlet disc [m]."""
    inlet_radius_m: float
    """Radius of the inlet disc: the first slice's CV centres, plus half a cell [m]."""
    cell_size_m: float
    """CV edge length [m]."""

    @classmethod
    def from_field(cls, field: CommandField) -> "MapGeometry":
        """Inlet/outlet planes, axis, inlet radius and bounding box of a command field's CVs."""
        c = np.asarray(field.centers_m, dtype=float)
        h = 0.5 * float(field.cell_size_m)
        first = c[np.asarray(field.centers_m)[:, 0] <= c[:, 0].min() + 1e-9]
        cy, cz = float(first[:, 1].mean()), float(first[:, 2].mean())
        r = float(np.max(np.hypot(first[:, 1] - cy, first[:, 2] - cz))) + h
        lo, hi = c.min(axis=0) - h, c.max(axis=0) + h
        return cls(x_inlet_m=float(lo[0]), x_outlet_m=float(hi[0]), lo_m=tuple(lo.tolist()),
                   hi_m=tuple(hi.tolist()), inlet_center_yz_m=(cy, cz), inlet_radius_m=r,
                   cell_size_m=float(field.cell_size_m))

    def in_box(self, p: Vec, margin_m: float = 0.0) -> bool:
        """True when ``p`` lies in the CVs' bounding box grown by ``margin_m``."""
        return all(self.lo_m[i] - margin_m <= p[i] <= self.hi_m[i] + margin_m for i in range(3))


def entry_points(geom: MapGeometry, sfield: ScalarField, radius_fraction: float = 0.6,
                 n_points: int = ENTRY_POINTS) -> list[Vec]:
    """The entry points of the inlet disc (first CV slice, map frame), ``entry_point``'s table.

    Points of a Vogel (golden-angle) spiral, area-uniform over ``radius_fraction`` of the inlet
    radius, of which the first ``n_points`` that lie in an inlet CV are kept (points outside
    the staircase are skipped, so ``radius_fraction`` 1 spreads the entries evenly over every inlet
    CV, as the simulator's reservoir does).  If the disc holds no inlet CV at all, each of
    ``n_points`` spiral points is moved to the nearest inlet CV centre.
    """
    x = geom.x_inlet_m + 0.5 * geom.cell_size_m

    def spiral(n: int) -> list[Vec]:
        out = []
        for k in range(n):
            r = radius_fraction * geom.inlet_radius_m * math.sqrt((k + 0.5) / n)
            out.append((x, geom.inlet_center_yz_m[0] + r * math.cos(k * GOLDEN_ANGLE_RAD),
                        geom.inlet_center_yz_m[1] + r * math.sin(k * GOLDEN_ANGLE_RAD)))
        return out

    n_total = n_points
    while True:  # more spiral points until n_points of them lie in inlet CVs
        kept = [p for p in spiral(n_total) if sfield.cv_of(*p) >= 0]
        if len(kept) >= n_points or n_total > 16 * n_points:
            break
        n_total = max(n_total + 1, math.ceil(n_total * n_points / max(len(kept), 1)))
    if kept:
        return kept[:n_points]
    first = [c for c in sfield.centers if c[0] <= geom.x_inlet_m + geom.cell_size_m]
    return [(x, *min(first, key=lambda c: (c[1] - p[1]) ** 2 + (c[2] - p[2]) ** 2)[1:]) for p in spiral(n_points)]


def entry_point(agent_id: int, geom: MapGeometry, sfield: ScalarField, radius_fraction: float = 0.6,
                n_points: int = ENTRY_POINTS) -> Vec:
    """Deterministic entry point of an agent: point ``agent_id mod len`` of ``entry_points``.

    With the default 64 points, ids 0..63 each have their own point (whatever their entry windows);
    id 64 shares id 0's point, id 64 + k id k's (and, with 8 windows, its window too)."""
    pts = entry_points(geom, sfield, radius_fraction, n_points)
    return pts[int(agent_id) % len(pts)]


def hold_points(n: int, geom: MapGeometry, x_m: float, spacing_m: float, min_z_m: float | None = None,
                floor_margin_m: float = HOLD_FLOOR_MARGIN_M) -> np.ndarray:
    """(n, 3) the exit hold spots of agents 0..n-1 (map frame), ``fisc_agent.flight.spacing``'s layout:
    a square lattice of pitch ``spacing_m`` in the horizontal plane, from ``x = x_m`` downstream, filled
    as a half disc around the tunnel's axis; any two spots at least ``spacing_m`` apart horizontally
    (so are the landing spots below them), whatever the ids.  Their altitude: the axis height, raised to
    ``floor_margin_m`` above the tunnel's lowest CV face and to ``min_z_m`` where given
    (``spacing.hold_altitude_m``).

    Agents leave the outlet within a few decimetres of each other; held where they left it, two PX4
    SITL vehicles hovered 0.11-0.30 m apart (SIH ground truth).  The layout depends only on the map,
    so every agent computes the same one.
    """
    z = hold_altitude_m(geom.inlet_center_yz_m[1], geom.lo_m[2], min_z_m, floor_margin_m)
    return lattice_hold_points(n, x_m, geom.inlet_center_yz_m[0], z, spacing_m)


def hold_point(agent_id: int, geom: MapGeometry, x_m: float, spacing_m: float, min_z_m: float | None = None,
               floor_margin_m: float = HOLD_FLOOR_MARGIN_M) -> Vec:
    """Agent ``agent_id``'s own hold spot: row ``agent_id`` of ``hold_points``.  ``min_z_m``: the
    least altitude (map z), e.g. the vehicle's home z plus its take-off height."""
    if int(agent_id) < 0:
        raise ValueError(f"hold_point: agent id must be >= 0, got {agent_id}")
    x, y, z = hold_points(int(agent_id) + 1, geom, x_m, spacing_m, min_z_m, floor_margin_m)[-1]
    return (float(x), float(y), float(z))


def check_map(field: CommandField, mode: str | None) -> list[str]:
    """Agent-side checks of a decoded map's commands; raises ``MapError`` naming the check.

    ``mode`` None: the map's recommended mode.  Returns warnings (strings) that do not prevent flight.
    """
    if mode is None:
        mode = (field.recommended or PAPER_SETTINGS).mode
    if mode not in COMMAND_MODES:
        raise MapError(MapErrorKind.MODE, f"unknown command mode {mode!r}")
    n = field.n_cv
    if n < 1:
        raise MapError(MapErrorKind.N_CV, "the map has no control volumes")
    if not (math.isfinite(field.cell_size_m) and field.cell_size_m > 0):
        raise MapError(MapErrorKind.GRID, f"cell_size_m must be positive, is {field.cell_size_m}")
    g = np.asarray(field.grid_cv)
    if g.size and (g.min() < -1 or g.max() >= n):
        raise MapError(MapErrorKind.GRID_CV, "CV ids out of range")
    bad = np.flatnonzero(~np.all(np.isfinite(field.mean_cmd_m_s), axis=1))
    if bad.size:
        raise MapError(MapErrorKind.COMMANDS, f"non-finite mean command in CV {int(bad[0])}")
    ns = np.asarray(field.n_star)
    n_max = field.slot_cmd_m_s.shape[1]
    if np.any(ns < 1) or np.any(ns > n_max):
        raise MapError(MapErrorKind.N_STAR, f"values must lie in 1..{n_max}")
    if mode in FACE_MODES and field.face_u_m_s is None:
        raise MapError(MapErrorKind.MODE, f"{mode!r} needs a schema-2 map with the staggered face field")
    if mode in FACE_MODES and not all(np.all(np.isfinite(f)) for f in field.face_u_m_s):
        raise MapError(MapErrorKind.COMMANDS, "non-finite face velocity")
    if mode == "slot":
        k = np.arange(n_max)[None, :] < ns[:, None]
        if not np.all(np.isfinite(field.slot_cmd_m_s[k])):
            raise MapError(MapErrorKind.COMMANDS, "non-finite fitted slot vector within N*")
    warnings = []
    ids = g[g >= 0]
    if ids.size and np.unique(ids).size != n:
        warnings.append("grid_cv does not reference every CV")
    return warnings


def max_command_speed(field: CommandField, mode: str | None) -> float:
    """Largest commanded speed the map can ask for in ``mode`` [m/s] (None: the map's recommended mode)."""
    if mode is None:
        mode = (field.recommended or PAPER_SETTINGS).mode
    if mode in FACE_MODES:
        # each component is linear between its cube's two faces: bounded per cube by the larger face
        i, j, k = np.floor((np.asarray(field.centers_m) - field.origin_m) / field.cell_size_m).astype(np.int64).T
        fx, fy, fz = field.face_u_m_s
        ax = np.maximum(np.abs(fx[i, j, k]), np.abs(fx[i + 1, j, k]))
        ay = np.maximum(np.abs(fy[i, j, k]), np.abs(fy[i, j + 1, k]))
        az = np.maximum(np.abs(fz[i, j, k]), np.abs(fz[i, j, k + 1]))
        v = float(np.max(np.sqrt(ax * ax + ay * ay + az * az)))
        if mode == "kinetic" and field.spread_m_s is not None:
            v += float(np.max(field.spread_m_s))
        return v
    if mode == "slot":
        v = np.asarray(field.slot_cmd_m_s)
        return float(np.nanmax(np.linalg.norm(v, axis=2)))
    return float(np.max(np.linalg.norm(field.mean_cmd_m_s, axis=1)))
