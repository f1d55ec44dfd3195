"""Control-volume lookup and velocity commands from a command map (vectorised, numpy only).

The CVs sit on a regular grid, so the nearest CV centre (the paper's CV-assignment equation,
``argmin_j ||x_i - x_j||``) of a point inside an occupied grid cell is that cell's CV: the
lookup is O(1) per agent through the map's dense ``grid_cv`` table, with no search over CVs.
Points in cells without a CV are *outside the map* (id -1); what happens to them is a policy
of the caller (geofence), never an arbitrary far CV.  ``nearest_cv_within`` finds the nearest
existing CV in a bounded neighbourhood for the "return to the map" policy.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from fisc_agent.map.hashing import slot_index
from fisc_agent.map.kinetic import DEFAULT_PERSISTENCE_S, DeviationState, deviation_in_cells, kinetic_spread
from fisc_agent.map.codec import FACE_ARRAYS, CommandMap

#: Command modes (DESIGN.md section 3).  ``mean``: the paper's Algorithm 1; ``slot``: fitted vector
#: h(agent, j) mod N*_j; ``interpolated``: trilinear mean field; ``staggered``: the continuity-consistent
#: face field of a schema-2 map; ``kinetic``: ``staggered`` plus a persistent per-agent deviation whose
#: rms is the CV's fitted spread (``kinetic_deviation``).
COMMAND_MODES = ("mean", "slot", "interpolated", "staggered", "kinetic")
#: Modes that need the face field of a schema-2 map.
FACE_MODES = ("staggered", "kinetic")
POINT_MODES = ("mean", "slot", "interpolated")
"""Modes whose command depends on the point and agent only (``control.ScalarField.command``)."""
#: Geofence ``return`` (``return_command``): gain of the pull towards the nearest CV's centre [1/s] ...
RETURN_GAIN_1_S = 1.0
#: ... capped at this fraction of that CV's mean command speed [-] ...
RETURN_SPEED_FRACTION = 0.25
#: ... for an agent whose nearest CV lies within this many grid cells ...
RETURN_RADIUS_CELLS = 2
#: ... skipping *stagnant* CVs, whose mean command speed is below this fraction of the map's median
#: (a boundary layer, a separation), while another CV lies within the radius (``return_cv_within``) [-].
RETURN_STAGNANT_FRACTION = 0.5


def lookahead_point(points_m: np.ndarray, velocity_m_s: np.ndarray, lead_s: float) -> np.ndarray:
    """Point ``x + u t_lead`` whose command an agent flies to compensate its velocity lag.

    A velocity-controlled multirotor responds to a command with a lag of roughly its time
    constant tau, so an agent that looks up the command at its own position flies the command
    of the point about ``u tau`` behind it.  Looking the command up ``t_lead ~ tau`` ahead
    along the current velocity cancels that to first order.  ``points_m`` and ``velocity_m_s``
    are (m, 3) in the same frame; ``lead_s`` >= 0 (0 returns a copy of the points).
    """
    if not (lead_s >= 0 and np.isfinite(lead_s)):
        raise ValueError(f"lead_s must be finite and >= 0, got {lead_s!r}")
    return np.asarray(points_m, dtype=float) + float(lead_s) * np.asarray(velocity_m_s, dtype=float)


@dataclass(frozen=True)
class CommandField:
    """A map's commands prepared for fast lookup (all arrays in the map/reference frame)."""

    origin_m: np.ndarray
    """(3,) lower corner of grid cell (0, 0, 0) [m]."""
    cell_size_m: float
    """CV edge length l [m]."""
    grid_cv: np.ndarray
    """(nx, ny, nz) CV id per grid cell, -1 where there is none."""
    centers_m: np.ndarray
    """(n_cv, 3) CV centres [m]."""
    mean_cmd_m_s: np.ndarray
    """(n_cv, 3) scaled mean command S * v_{s,d,j} [m/s]."""
    slot_cmd_m_s: np.ndarray
    """(n_cv, n_max, 3) scaled fitted vectors (NaN beyond N*) [m/s]."""
    n_star: np.ndarray
    """(n_cv,) fitted agent count N*_j."""
    spread_m_s: np.ndarray | None = None
    """(n_cv,) scaled per-agent rms deviation of the ``kinetic`` mode [m/s]: the fitted spread
    sqrt(mean_k ||S v_k - S v_mean||^2), on a map with a designed density rho_d (schema 2) times
    sqrt(mean(rho_d) / rho_d) (``kinetic_spread``)."""
    recommended: "FlightSettings | None" = None
    """The map's recommended flight settings (``map_flight_settings``); None for hand-built fields."""
    face_u_m_s: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    """Scaled staggered face-normal velocities (x faces (nx+1, ny, nz), y faces (nx, ny+1, nz), z
    faces (nx, ny, nz+1)) [m/s] of a schema-2 map (``fisc_ground.fit.staggered``); None without."""

    @classmethod
    def from_map(cls, cmap: CommandMap, scale: float | None = None) -> "CommandField":
        """The lookup field of a verified map, commands scaled by ``scale`` (default: the map's S)."""
        s = cmap.scale if scale is None else float(scale)
        faces = None
        if all(k in cmap.arrays for k in FACE_ARRAYS):
            faces = tuple(s * np.asarray(cmap[k], dtype=float) for k in FACE_ARRAYS)
        slots = np.asarray(cmap["fit_velocity_m_s"], dtype=float)
        mean = np.asarray(cmap["fit_mean_velocity_m_s"], dtype=float)
        d2 = np.nansum((slots - mean[:, None, :]) ** 2, axis=2)
        spread = s * np.sqrt(d2.sum(axis=1) / np.maximum(np.asarray(cmap["n_star"]), 1))
        if "cv_design_density" in cmap.arrays:
            spread = kinetic_spread(spread, np.asarray(cmap["cv_design_density"], dtype=float))
        return cls(
            origin_m=cmap.origin_m,
            spread_m_s=spread,
            cell_size_m=cmap.cell_size_m,
            grid_cv=np.asarray(cmap["grid_cv"]),
            centers_m=np.asarray(cmap["cv_center_m"]),
            mean_cmd_m_s=s * np.asarray(cmap["fit_mean_velocity_m_s"]),
            slot_cmd_m_s=s * np.asarray(cmap["fit_velocity_m_s"]),
            n_star=np.asarray(cmap["n_star"]),
            face_u_m_s=faces,
            recommended=map_flight_settings(cmap),
        )

    @property
    def n_cv(self) -> int:
        """Number of control volumes."""
        return int(self.centers_m.shape[0])

    @functools.cached_property
    def wall_faces(self) -> np.ndarray:
        """(nx, ny, nz, 3, 2) bool: face (axis, lower/upper) of a CV's cell has no neighbour CV (a
        staircase wall).  The inlet (lower x of the first slice) and the outlet (upper x of the last)
        are not walls; cells without a CV have none."""
        g = np.asarray(self.grid_cv) >= 0
        pad = np.zeros(tuple(s + 2 for s in g.shape), dtype=bool)
        pad[1:-1, 1:-1, 1:-1] = g
        pad[0, 1:-1, 1:-1] = pad[-1, 1:-1, 1:-1] = True  # inlet and outlet: open
        out = np.zeros(g.shape + (3, 2), dtype=bool)
        core = (slice(1, -1),) * 3
        for a in range(3):
            for side, shift in ((0, -1), (1, 1)):
                nb = np.roll(pad, -shift, axis=a)[core]
                out[..., a, side] = g & ~nb
        return out

    @functools.cached_property
    def stepped_out_faces(self) -> np.ndarray:
        """(nx, ny, nz, 3, 2) bool: a lateral face (axis y or z, lower/upper) of a CV's cell that has a
        neighbour CV where the same face of the CV upstream (x - 1) is a staircase wall: the faces
        where the staircase steps outward (``fisc_agent.map.kinetic.kinetic_deviation``)."""
        w = self.wall_faces
        g = np.asarray(self.grid_cv) >= 0
        out = np.zeros_like(w)
        both = (g[1:] & g[:-1])[..., None, None]
        out[1:, :, :, 1:, :] = both & ~w[1:, :, :, 1:, :] & w[:-1, :, :, 1:, :]
        return out

    @functools.cached_property
    def kinetic_codes(self) -> np.ndarray:
        """(cells of the padded grid, 3) int64 per cell and axis, rows as ``locate`` gives them: bit s
        set where ``wall_faces`` holds for the face on side s (0 lower, 1 upper), bit 2 + s where
        ``stepped_out_faces`` does (one gather and shifts of whole (m, 3) arrays in the kinetic
        deviation)."""
        codes = (self.wall_faces.astype(np.int64) << np.arange(2)).sum(axis=-1) \
            + (self.stepped_out_faces.astype(np.int64) << np.arange(2, 4)).sum(axis=-1)
        return self._on_padded_grid(codes)

    def cell_of(self, points_m: np.ndarray) -> np.ndarray:
        """(m, 3) integer grid cell of each point (half-open cells; may be out of range)."""
        return np.floor((np.asarray(points_m, dtype=float) - self.origin_m) / self.cell_size_m).astype(np.int64)

    @functools.cached_property
    def _padded_shape(self) -> tuple[int, int, int]:
        """Shape of the grid with a border of one cell on every side."""
        return tuple(int(s) + 2 for s in np.shape(self.grid_cv))

    @functools.cached_property
    def _padded_cv(self) -> np.ndarray:
        """``grid_cv`` on the padded grid, flat, its border -1 (no CV beyond the grid)."""
        return np.pad(np.asarray(self.grid_cv, dtype=np.int64), 1, constant_values=-1).ravel()

    def _on_padded_grid(self, per_cell: np.ndarray) -> np.ndarray:
        """A per-cell table (nx, ny, nz, ...) on the padded grid, flat over the cells: the border
        repeats the nearest cell of the grid, so a point beyond it reads the cell it clips to."""
        pad = [(1, 1)] * 3 + [(0, 0)] * (per_cell.ndim - 3)
        return np.pad(per_cell, pad, mode="edge").reshape((-1,) + per_cell.shape[3:])

    @functools.cached_property
    def _row_tiles(self) -> dict[str, np.ndarray]:
        """Memo of ``_tiled``: per-axis constants repeated over rows."""
        return {}

    def _tiled(self, name: str, row: np.ndarray, m: int) -> np.ndarray:
        """(m, 3) ``row`` repeated m times (a view of a memoised table).  Numpy runs a (m, 3) by (3,)
        broadcast as m inner loops of 3 elements, five times slower than two (m, 3) arrays."""
        t = self._row_tiles.get(name)
        if t is None or t.shape[0] < m:
            t = self._row_tiles[name] = np.tile(np.asarray(row, dtype=float), (max(m, 1024), 1))
        return t[:m]

    @functools.cached_property
    def _padded_rows(self) -> tuple[np.ndarray, np.ndarray, float]:
        """``locate``'s flat-index rule in floating point: the highest cell index per axis (the
        border beyond it), the padded grid's strides and the offset of cell (0, 0, 0), so that
        row = min(max(cell, -1), hi) . strides + offset (exact: the rows are far below 2**53)."""
        shape = np.asarray(self._padded_shape, dtype=np.int64)
        strides = np.array([shape[1] * shape[2], shape[2], 1], dtype=float)
        return (shape - 2).astype(float), strides, float(strides.sum())

    def cv_of(self, points_m: np.ndarray) -> np.ndarray:
        """(m,) CV id of each point, -1 outside the map's CVs."""
        return self.locate(points_m)[2]

    def nearest_cv_within(self, points_m: np.ndarray, radius_cells: int = 2) -> np.ndarray:
        """(m,) nearest existing CV (by centre distance) within ``radius_cells`` grid cells, else -1."""
        return self._nearest_within(points_m, radius_cells, None)

    def return_cv_within(self, points_m: np.ndarray, radius_cells: int = RETURN_RADIUS_CELLS) -> np.ndarray:
        """(m,) the CV a vehicle outside the map rejoins (``return_command``): the nearest within
        ``radius_cells`` grid cells that is not ``stagnant``, else the nearest stagnant one, else -1.

        A stagnant CV makes a poor target: its flow carries the vehicle nowhere, and the pull towards
        it is capped by its own speed.  On the RANS nozzle (cd_nozzle) the vehicles that drifted out
        beside its slow wall CVs stayed out: 389 of 12 221 agents escaped, 4 with this rule, while no
        CV of the inviscid references is stagnant (docs/swarm_model.md, "Agents that leave the CVs")."""
        return self._nearest_within(points_m, radius_cells, self.stagnant)

    @functools.cached_property
    def stagnant(self) -> np.ndarray:
        """(n_cv,) bool: the CV's mean command speed is below ``RETURN_STAGNANT_FRACTION`` times the
        median over the map's CVs."""
        speed = np.linalg.norm(np.asarray(self.mean_cmd_m_s, dtype=float), axis=1)
        return speed < RETURN_STAGNANT_FRACTION * float(np.median(speed))

    def _nearest_within(self, points_m: np.ndarray, radius_cells: int, avoid: np.ndarray | None) -> np.ndarray:
        """``nearest_cv_within``, CVs flagged in ``avoid`` (n_cv,) taken only where no other is in reach."""
        pts = np.atleast_2d(np.asarray(points_m, dtype=float))
        cells = self.cell_of(pts)
        r = np.arange(-radius_cells, radius_cells + 1)
        offs = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)
        cand = cells[:, None, :] + offs[None, :, :]  # (m, k, 3)
        shape = np.asarray(self.grid_cv.shape)
        ok = np.all((cand >= 0) & (cand < shape), axis=2)
        ids = np.full(ok.shape, -1, dtype=np.int64)
        cc = cand[ok]
        ids[ok] = self.grid_cv[cc[:, 0], cc[:, 1], cc[:, 2]]
        d2 = np.where(ids >= 0, np.sum((self.centers_m[np.maximum(ids, 0)] - pts[:, None, :]) ** 2, axis=2), np.inf)
        if avoid is not None:
            preferred = np.where(avoid[np.maximum(ids, 0)], np.inf, d2)
            d2 = np.where(np.isfinite(preferred).any(axis=1, keepdims=True), preferred, d2)
        best = np.argmin(d2, axis=1)
        out = ids[np.arange(len(pts)), best]
        out[~np.isfinite(d2[np.arange(len(pts)), best])] = -1
        return out

    def command(self, points_m: np.ndarray, agent_ids: np.ndarray, mode: str = "mean",
                cv_ids: np.ndarray | None = None) -> np.ndarray:
        """(m, 3) commanded velocity [m/s] in the map frame; NaN rows for points outside the map."""
        pts = np.atleast_2d(np.asarray(points_m, dtype=float))
        cv = self.cv_of(pts) if cv_ids is None else np.asarray(cv_ids)
        out = np.full((pts.shape[0], 3), np.nan)
        ok = cv >= 0
        if mode == "mean":
            out[ok] = self.mean_cmd_m_s[cv[ok]]
        elif mode == "slot":
            j = cv[ok]
            ids = np.asarray(agent_ids)[ok] if np.ndim(agent_ids) else agent_ids
            out[ok] = self.slot_cmd_m_s[j, slot_index(ids, j, self.n_star[j])]
        elif mode == "interpolated":
            out[ok] = self._interpolate(pts[ok], cv[ok])
        elif mode in FACE_MODES:
            out = self._staggered(pts)  # rows outside: the clipped cell's faces, NaN below
            out[~ok] = np.nan
        else:
            raise ValueError(f"unknown command mode {mode!r}; choose one of {', '.join(COMMAND_MODES)}")
        return out

    def _interpolate(self, pts: np.ndarray, cv: np.ndarray) -> np.ndarray:
        """Trilinear interpolation of the mean command between CV centres.

        Corners without a CV are left out and the remaining weights renormalised; a point
        with no CV among its 8 corners keeps its own CV's command.
        """
        f = (pts - self.origin_m) / self.cell_size_m - 0.5
        i0 = np.floor(f).astype(np.int64)
        t = f - i0
        acc = np.zeros((pts.shape[0], 3))
        wsum = np.zeros(pts.shape[0])
        shape = np.asarray(self.grid_cv.shape)
        for corner in range(8):
            d = np.array([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1])
            c = i0 + d
            w = np.prod(np.where(d == 1, t, 1.0 - t), axis=1)
            inside = np.all((c >= 0) & (c < shape), axis=1)
            ids = np.full(len(pts), -1, dtype=np.int64)
            ids[inside] = self.grid_cv[c[inside, 0], c[inside, 1], c[inside, 2]]
            w = np.where(ids >= 0, w, 0.0)
            acc += w[:, None] * self.mean_cmd_m_s[np.maximum(ids, 0)]
            wsum += w
        out = self.mean_cmd_m_s[cv].copy()
        good = wsum > 1e-12
        out[good] = acc[good] / wsum[good, None]
        return out

    @functools.cached_property
    def _cell_faces(self) -> tuple[np.ndarray, np.ndarray]:
        """Face velocities of every cell of the padded grid: (cells, 3) on its lower faces and (cells,
        3) on its upper faces, rows as ``locate`` gives them (two contiguous gathers per point in
        ``staggered_at``)."""
        if self.face_u_m_s is None:
            raise ValueError("modes staggered/kinetic need a map with face velocities (schema version 2)")
        fx, fy, fz = (np.asarray(f, dtype=float) for f in self.face_u_m_s)
        return (self._on_padded_grid(np.stack([fx[:-1], fy[:, :-1], fz[:, :, :-1]], axis=-1)),
                self._on_padded_grid(np.stack([fx[1:], fy[:, 1:], fz[:, :, 1:]], axis=-1)))

    @functools.cached_property
    def _spread_xyz(self) -> np.ndarray:
        """(n_cv, 3) ``spread_m_s`` repeated per axis (one contiguous gather per point)."""
        return np.repeat(np.asarray(self.spread_m_s, dtype=float)[:, None], 3, axis=1)

    def locate(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where points (m, 3) lie on the grid, computed once for every lookup that needs it: (m,) the
        row of each point's cell in the per-cell tables (``_cell_faces``, ``kinetic_codes``; a point
        beyond the grid reads the cell it clips to), (m, 3) the point's position within its own cell
        per axis (in [0, 1) for points inside the grid) and (m,) its CV id (-1 outside the CVs, as
        ``cv_of``)."""
        pts = np.atleast_2d(np.asarray(points_m, dtype=float))
        m = pts.shape[0]
        f = pts - self._tiled("origin", self.origin_m, m)
        f /= self.cell_size_m
        c = np.floor(f)
        with np.errstate(invalid="ignore"):  # an infinite coordinate: frac NaN, its cell the border's
            frac = f - c
        hi, strides, offset = self._padded_rows
        np.fmax(c, -1.0, out=c)  # fmax/fmin: a NaN coordinate reads the lowest border cell, as an index clip
        np.fmin(c, self._tiled("hi", hi, m), out=c)
        rows = (c @ strides + offset).astype(np.int64)
        return rows, frac, self._padded_cv.take(rows)

    def staggered_at(self, rows: np.ndarray, frac: np.ndarray) -> np.ndarray:
        """(m, 3) the staggered field at cells ``rows`` and positions ``frac`` within them (``locate``):
        each component linear between the two faces of the cell (the MAC-grid rule), ``frac``
        clipped into [0, 1]."""
        t = np.minimum(np.maximum(frac, 0.0), 1.0)  # np.clip, without its Python-level overhead
        lower, upper = self._cell_faces
        return (1.0 - t) * lower.take(rows, axis=0) + t * upper.take(rows, axis=0)

    def _staggered(self, pts: np.ndarray) -> np.ndarray:
        """``staggered_at`` the points (m, 3)."""
        rows, frac, _ = self.locate(pts)
        return self.staggered_at(rows, frac)


def cube_mean_u_axial_m_s(grid_cv: np.ndarray, face_u_x_m_s: np.ndarray) -> np.ndarray:
    """(n_cv,) each CV's cube-mean axial velocity of the staggered field (``CommandField``'s rule,
    linear between the x faces a, b, averaged over the cube: (a + b) / 2), in the faces' units."""
    grid = np.asarray(grid_cv)
    i, j, k = np.nonzero(grid >= 0)
    out = np.empty(i.size)
    out[grid[i, j, k]] = 0.5 * (face_u_x_m_s[i, j, k] + face_u_x_m_s[i + 1, j, k])
    return out


# ---- the one flight-command function (simulator, emulator and onboard agent) -------------------
@dataclass(frozen=True)
class FlightSettings:
    """How an agent turns the map into velocity commands (a map's recommended flight settings)."""

    mode: str = "mean"
    """Command mode, one of ``COMMAND_MODES``."""
    lookahead_s: float = 0.0
    """Command look-ahead t_lead [s] (``lookahead_point``); 0 = none (the paper)."""
    persistence_s: float = DEFAULT_PERSISTENCE_S
    """``kinetic``: how long an agent keeps one deviation direction [s]."""

    def __post_init__(self) -> None:
        if self.mode not in COMMAND_MODES:
            raise ValueError(f"mode {self.mode!r}: choose one of {', '.join(COMMAND_MODES)}")
        if not (self.lookahead_s >= 0 and math.isfinite(self.lookahead_s)):
            raise ValueError(f"lookahead_s must be finite and >= 0, got {self.lookahead_s!r}")
        if not (self.persistence_s > 0 and math.isfinite(self.persistence_s)):
            raise ValueError(f"persistence_s must be finite and > 0, got {self.persistence_s!r}")


#: The paper's Algorithm 1: mean commands, no look-ahead (``--preset paper``; version-1 maps).
PAPER_SETTINGS = FlightSettings("mean", 0.0)


def map_flight_settings(cmap: CommandMap) -> FlightSettings:
    """A map's recommended flight settings: its ``flight`` table (schema 2), else ``PAPER_SETTINGS``."""
    flight = cmap.body.get("flight")
    if cmap.schema_version < 2 or not isinstance(flight, dict):
        return PAPER_SETTINGS
    return FlightSettings(str(flight["mode"]), float(flight["lookahead_s"]), float(flight["persistence_s"]))


def return_pull(field: CommandField, points_m: np.ndarray, near_cv: np.ndarray,
                gain_1_s: float = RETURN_GAIN_1_S, speed_fraction: float = RETURN_SPEED_FRACTION) -> np.ndarray:
    """(m, 3) inward part of ``return_command``: gain (c - x) towards the centre c of each agent's
    nearest CV ``near_cv`` (m,), its length capped at ``speed_fraction`` times that CV's mean command
    speed (so the pull never dominates the flow, whatever the map's scale)."""
    near = np.asarray(near_cv, dtype=np.int64)
    corr = gain_1_s * (np.asarray(field.centers_m)[near] - np.atleast_2d(np.asarray(points_m, dtype=float)))
    mag = np.sqrt(np.einsum("ij,ij->i", corr, corr))
    cap = speed_fraction * np.linalg.norm(np.asarray(field.mean_cmd_m_s)[near], axis=1)
    return corr * np.minimum(1.0, cap / np.maximum(mag, 1e-12))[:, None]


def return_command(field: CommandField, points_m: np.ndarray, near_cv: np.ndarray,
                   gain_1_s: float = RETURN_GAIN_1_S, speed_fraction: float = RETURN_SPEED_FRACTION) -> np.ndarray:
    """(m, 3) map-frame command of agents just outside the CVs (the geofence ``return`` policy of the
    simulator and of ``fisc-agent`` near the map): the mean command of the CV ``near_cv`` it rejoins
    (``CommandField.return_cv_within``) plus ``return_pull``.  The agent rejoins the flow moving with
    it; flying straight back to a CV centre instead turns a vehicle that overshot a closed staircase
    face round against the flow, and it re-enters slow and backwards (measured in ``fisc-sim
    emulate``: the pressure's top CVs)."""
    near = np.asarray(near_cv, dtype=np.int64)
    return np.asarray(field.mean_cmd_m_s)[near] + return_pull(field, points_m, near, gain_1_s, speed_fraction)


def flight_command(field: CommandField, points_m: np.ndarray, velocity_m_s: np.ndarray, agent_ids: np.ndarray,
                   t_s: float, settings: FlightSettings, state: DeviationState | None = None,
                   cv_ids: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, DeviationState | None]:
    """The velocity command of every agent: the one function the simulator, the emulated swarm and
    the onboard agent share (map frame, vectorised over agents).

    ``points_m``, ``velocity_m_s`` (m, 3) positions and velocities; ``agent_ids`` (m,); ``t_s`` the time
    (kinetic mode; any monotonic clock the caller keeps); ``state`` the kinetic state of these agents
    (``DeviationState.new`` at first; other modes ignore it); ``cv_ids`` the agents' own CVs if known.
    The command is looked up at ``x + u t_lead`` (own position if that point has no CV).
    Returns ``(cmd (m, 3) NaN for agents outside the CVs, own CV ids (m,), new state)``.
    """
    pts = np.atleast_2d(np.asarray(points_m, dtype=float))
    ids = np.asarray(agent_ids, dtype=np.int64).reshape(-1)
    m = len(pts)
    ahead = None if settings.lookahead_s <= 0 else \
        lookahead_point(pts, np.atleast_2d(velocity_m_s), settings.lookahead_s)
    # every point (and its look-ahead point) located once, for the command and the deviation
    located = field.locate(pts if ahead is None else np.concatenate([pts, ahead]))
    rows, frac, own_cv = (a[:m] for a in located)
    cv = own_cv if cv_ids is None else np.asarray(cv_ids, dtype=np.int64)
    look_rows, look_frac, look_cv, keep = rows, frac, cv, None
    if ahead is not None:
        look_rows, look_frac, look_cv = (a[m:] for a in located)
        keep = look_cv < 0  # no CV ahead: the agent's own point
        if keep.any():
            look_rows, look_frac = np.where(keep, rows, look_rows), np.where(keep[:, None], frac, look_frac)
            look_cv = np.where(keep, cv, look_cv)
    if settings.mode not in FACE_MODES:
        look = pts if ahead is None else np.where(keep[:, None], pts, ahead)
        return field.command(look, ids, settings.mode, cv_ids=look_cv), cv, state
    cmd = field.staggered_at(look_rows, look_frac)
    outside = look_cv < 0
    if outside.any():
        cmd[outside] = np.nan
    if settings.mode != "kinetic":
        return cmd, cv, state
    st = DeviationState.new(len(pts)) if state is None else state
    d, st = deviation_in_cells(field, rows, frac, ids, t_s, settings.persistence_s, st, np.atleast_2d(velocity_m_s))
    cmd += field._spread_xyz.take(np.maximum(look_cv, 0), axis=0) * d  # rows outside stay NaN
    return cmd, cv, st
