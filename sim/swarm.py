"""Algorithm 1 of the paper ("Velocity command execution for each agent"), vectorised.

Every step of ``dt`` (paper: 0.05 s), for all agents at once (arrays ``(N, 3)``, no per-agent Python):

1. *Assign control volume* (eq. cv_assignment, nearest CV centre): the CVs are the occupied cells of a
   regular grid, so the nearest centre of a point inside an occupied cell is that cell's CV; the lookup is
   O(1) per agent through a padded copy of the map's ``grid_cv`` table (the same rule as
   ``fisc_agent.map.lookup.CommandField.cv_of``), never a search over CVs.
2. *Retrieve the command* (eq. scaled_command_map, ``S v_{s,d,j}``; ``CommandField`` already applies S)
   in one of the modes ``mean`` (the paper), ``slot`` or ``interpolated``.
3. *Update the velocity* with the quadrotor plant (``sim.plant.model.step_plant``, NED).
4. *Update the position* ``x += u dt`` (semi-implicit: with the new velocity).

Frames.  Positions and commands live in the map (reference) frame: x along the tunnel, z up.  The plant
works in NED with the default deployment axis mapping map x -> North, y -> East, z -> Up, i.e. ``v_NED =
(v_x, v_y, -v_z)``.  The command tables are flipped once at start-up, so the per-step conversion is a single
multiply in the position update.

Agents leaving the map.
* Past the outlet (x beyond the last slice): removed and counted as ``exited`` (outflow).
* Sideways or upstream, into a grid cell without a CV (near the wall, or behind the inlet): the *return*
  policy.  The agent flies the command of the nearest CV within ``return_radius_cells`` cells plus an inward
  correction ``k (x_c - x)`` towards that CV's centre (magnitude capped at ``return_speed_fraction`` of that
  CV's mean command speed), for at most ``escape_grace_s`` seconds in a row.  If it has not re-entered a CV
  by then, or no CV lies within the radius, it is removed and counted as ``escaped``.  This mirrors the
  onboard geofence option "fly back to the nearest CV" (DESIGN.md section 5).

Bookkeeping: ``injected == alive + exited + escaped`` at all times.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fisc_agent.map.hashing import slot_hash
from fisc_agent.map.kinetic import DEFAULT_PERSISTENCE_S, DeviationState
from fisc_agent.map.lookup import (
    COMMAND_MODES,
    RETURN_GAIN_1_S,
    RETURN_RADIUS_CELLS,
    RETURN_SPEED_FRACTION,
    CommandField,
    FlightSettings,
    flight_command,
    lookahead_point,
    return_pull,
)
from sim.cv_lookup import CVLookup, fused_lookup_kernel
from sim.entry import entry_phase, entry_thrust
from sim.fused_step import FusedStep
from sim.kernels import compact_kernel, move_kernel, removal_kernel, return_commands_kernel
from sim.kinetic_step import KineticStep
from sim.plant.model import PlantCoefficients, PlantParams, plant_stepper
from sim.swarm_counters import SwarmCounters

#: Map frame (x fwd, y, z up) -> NED (x north, y east, z down) for the default deployment.
MAP_TO_NED = np.array([1.0, 1.0, -1.0])
#: The per-agent row buffers of ``Swarm`` (``_pos``, ...), copied when the buffers grow and compacted when agents
#: leave: position, velocity, thrust, id, time outside, and the kinetic state (``DeviationState``).
_AGENT_ROWS = ("pos", "vel", "thr", "ids", "out", "epoch", "sign", "dir", "phase")


@dataclass(frozen=True)
class SwarmConfig:
    """Numerical and policy settings of the swarm stepping core."""

    dt_s: float = 0.05
    """Time step of Algorithm 1 [s] (paper: 0.05 s)."""
    mode: str = "mean"
    """Command mode: ``mean`` (paper's Algorithm 1), ``slot`` or ``interpolated``."""
    escape_grace_s: float = 5.0
    """Longest continuous time an agent may spend outside every CV before it is removed as escaped [s]."""
    return_gain_1_s: float = RETURN_GAIN_1_S
    """Gain k of the inward correction k (x_c - x) for agents outside the CVs [1/s]."""
    return_speed_fraction: float = RETURN_SPEED_FRACTION
    """Cap on the magnitude of the inward correction, as a fraction of the nearest CV's mean
    command speed (so the correction never dominates the flow, whatever the scale S) [-]."""
    return_radius_cells: int = RETURN_RADIUS_CELLS
    """How far (in cells) an outside agent looks for the nearest CV; none within -> escaped."""
    plant_backend: str = "auto"
    """Plant kernel: ``auto`` (numba when importable), ``numpy`` or ``numba``."""
    lookup_backend: str = "auto"
    """CV lookup (+ the command gather of modes mean/slot), removals, return commands and position
    update: ``auto`` (fused numba kernels, ``sim.kernels``, when importable), ``numpy`` (the reference
    path) or ``numba``; both give the same trajectories.  The other modes' commands always come from
    ``fisc_agent.map.lookup.flight_command``."""
    lookahead_s: float = 0.0
    """Command look-ahead t_lead [s]: each agent flies the command of the CV at
    ``x + u t_lead`` (its own CV when that point is outside the CVs) instead of the CV at x,
    compensating the plant lag (~0.58 s for the default plant).  0 = the paper's Algorithm 1.
    The CV assignment (exits, escapes, the fields) always uses x itself."""
    persistence_s: float = DEFAULT_PERSISTENCE_S
    """Mode ``kinetic``: how long an agent keeps one deviation direction [s]
    (``fisc_agent.map.kinetic.kinetic_deviation``)."""
    fused: bool = True
    """With the numba kernels: each step in one kernel call where it applies (``sim.fused_step``; no command
    filter, no collider); False: the multi-pass step, its reference (same bits)."""

    @property
    def flight_settings(self) -> FlightSettings:
        """The settings of ``fisc_agent.map.lookup.flight_command`` this configuration flies."""
        return FlightSettings(self.mode, self.lookahead_s, self.persistence_s)

    def __post_init__(self) -> None:
        if not (self.dt_s > 0 and np.isfinite(self.dt_s)):
            raise ValueError(f"SwarmConfig.dt_s must be > 0, got {self.dt_s!r}")
        if self.mode not in COMMAND_MODES:
            raise ValueError(f"SwarmConfig.mode {self.mode!r}: choose one of {', '.join(COMMAND_MODES)}")
        if self.escape_grace_s < 0:
            raise ValueError(f"SwarmConfig.escape_grace_s must be >= 0, got {self.escape_grace_s!r}")
        if self.lookup_backend not in ("auto", "numpy", "numba"):
            raise ValueError(f"SwarmConfig.lookup_backend {self.lookup_backend!r}: choose auto, numpy or numba")
        if self.return_radius_cells < 0:
            raise ValueError(f"SwarmConfig.return_radius_cells must be >= 0, got {self.return_radius_cells!r}")
        if not (self.lookahead_s >= 0 and np.isfinite(self.lookahead_s)):
            raise ValueError(f"SwarmConfig.lookahead_s must be finite and >= 0, got {self.lookahead_s!r}")


class Swarm:
    """N agents flown by a command map (state held here; see the module docstring).

    State (first ``n`` rows of capacity buffers, map frame unless stated): ``pos_m`` (n, 3), ``vel_ned_m_s``
    (n, 3), ``thrust_ned_m_s2`` (n, 3), ``ids`` (n,), ``outside_s`` (n,) time spent outside the CVs.

    ``collider``: optional collision layer with ``apply(pos_m, vel_ned)`` that adjusts the realised velocities
    in place after the plant step (``sim.collisions.CollisionModel``).  ``command_filter``: optional
    ``apply(pos_m, vel_ned_m_s, cmd_ned_m_s, ids)`` that adjusts the step's NED commands in place before the
    plant step (``sim.safety_net.SwarmSafetyNet``).
    """

    def __init__(self, field: CommandField, plant: PlantParams | None = None,
                 config: SwarmConfig | None = None, collider=None, command_filter=None) -> None:
        self.field = field
        self.config = SwarmConfig() if config is None else config
        self.plant = PlantParams() if plant is None else plant
        if not self.plant.is_homogeneous:
            raise ValueError("Swarm needs fleet-wide (homogeneous) PlantParams")
        self._co: PlantCoefficients = self.plant.coefficients()
        self._plant_step = plant_stepper(self._co, self.config.dt_s, self.config.plant_backend)
        self.collider = collider
        self.command_filter = command_filter
        self.lookup = CVLookup(field, self.config.return_radius_cells)
        n_cv = field.n_cv
        # command tables with one extra zero row, so cv = -1 indexes a harmless row
        self._mean_ned = np.zeros((n_cv + 1, 3))
        self._mean_ned[:n_cv] = field.mean_cmd_m_s * MAP_TO_NED
        n_max = field.slot_cmd_m_s.shape[1]
        self._slot_ned = np.zeros((n_cv + 1, n_max, 3))
        self._slot_ned[:n_cv] = np.nan_to_num(field.slot_cmd_m_s) * MAP_TO_NED
        self._mean_speed = np.linalg.norm(self._mean_ned, axis=1)
        self._n_star = np.ones(n_cv + 1, dtype=np.uint64)
        self._n_star[:n_cv] = np.maximum(np.asarray(field.n_star), 1).astype(np.uint64)
        self.x_outlet_m = float(field.origin_m[0] + field.grid_cv.shape[0] * field.cell_size_m)
        self._fdt = MAP_TO_NED * self.config.dt_s
        self._centers_m = np.ascontiguousarray(field.centers_m, dtype=np.float64)
        self.t_s = 0.0
        self.counters = SwarmCounters()
        self._next_id = 0
        self.n = 0
        self._kernel = None
        if self.config.lookup_backend != "numpy":
            self._kernel = fused_lookup_kernel()
            if self._kernel is None and self.config.lookup_backend == "numba":
                raise RuntimeError("lookup_backend='numba' requested but numba is not installed (pip install fisc[jit])")
        self._kinetic = KineticStep.make(field, self.config.persistence_s, self.config.lookahead_s) \
            if self._kernel is not None and self.config.mode == "kinetic" else None  # numba: one pass, same bits
        c = self.config
        self._fused = FusedStep.make(self.lookup, self._centers_m, self._mean_speed, self._mean_ned, self._slot_ned,
                                     self._n_star, c.mode == "slot", self._co, c.dt_s, self.x_outlet_m, c.escape_grace_s,
                                     c.return_gain_1_s, c.return_speed_fraction, MAP_TO_NED, self._kinetic) \
            if self._kernel is not None and c.fused else None
        self._alloc(1024)
        self._cv: np.ndarray | None = None  # assignment of the current positions (cached)
        self._cmd_ready = False  # the fused kernel filled the commands of the current assignment

    # ---------------------------------------------------------------- state buffers
    def _alloc(self, cap: int) -> None:
        n = getattr(self, "n", 0)
        old = {k: getattr(self, "_" + k, None) for k in _AGENT_ROWS}
        self._pos = np.zeros((cap, 3))
        self._vel = np.zeros((cap, 3))
        self._thr = np.zeros((cap, 3))
        self._scratch = np.zeros((cap, 3))
        self._cmd = np.zeros((cap, 3))
        self._ids = np.zeros(cap, dtype=np.int64)
        self._out = np.zeros(cap)
        self._cvbuf = np.zeros(cap, dtype=np.int64)
        self._cellbuf = np.zeros(cap, dtype=np.int64)
        self._epoch = np.full(cap, -1, dtype=np.int64)  # kinetic-mode state (fisc_agent.map.kinetic.DeviationState)
        self._sign = np.ones((cap, 3))
        self._dir = np.zeros((cap, 3))
        self._phase = np.zeros(cap)
        if old["pos"] is not None and n:
            for k in _AGENT_ROWS:
                getattr(self, "_" + k)[:n] = old[k][:n]

    @property
    def pos_m(self) -> np.ndarray:
        """(n, 3) positions in the map frame [m] (live view)."""
        return self._pos[:self.n]

    @property
    def vel_ned_m_s(self) -> np.ndarray:
        """(n, 3) realised velocities in NED [m/s] (live view)."""
        return self._vel[:self.n]

    @property
    def thrust_ned_m_s2(self) -> np.ndarray:
        """(n, 3) realised thrust accelerations in NED [m/s^2] (live view)."""
        return self._thr[:self.n]

    @property
    def ids(self) -> np.ndarray:
        """(n,) agent ids (unique, increasing with injection order)."""
        return self._ids[:self.n]

    @property
    def outside_s(self) -> np.ndarray:
        """(n,) continuous time each agent has spent outside every CV [s]."""
        return self._out[:self.n]

    def velocity_map(self) -> np.ndarray:
        """(n, 3) realised velocities in the map frame [m/s] (a new array)."""
        return self.vel_ned_m_s * MAP_TO_NED

    @property
    def alive(self) -> int:
        """Number of agents alive (= ``n``)."""
        return self.n

    # ---------------------------------------------------------------- commands
    def commands_map(self, points_m: np.ndarray, agent_ids: np.ndarray) -> np.ndarray:
        """(m, 3) command of the configured mode at points (map frame; NaN outside the CVs)."""
        return self.field.command(points_m, agent_ids, self.config.mode)

    def _command_ned(self, cv: np.ndarray, out: np.ndarray) -> None:
        """Fill ``out`` (n, 3) with the NED command of every agent from its CV (rows of cv=-1: 0)."""
        mode = self.config.mode
        if mode == "mean":
            np.take(self._mean_ned, cv, axis=0, out=out)
        elif mode == "slot":
            k = (slot_hash(self.ids, cv) % self._n_star[cv]).astype(np.int64)
            out[...] = self._slot_ned[cv, k]
        else:
            inside = cv >= 0
            out[...] = 0.0
            if inside.any():
                out[inside] = self.field.command(self.pos_m[inside], self.ids[inside], mode,
                                                 cv_ids=cv[inside]) * MAP_TO_NED

    # ---------------------------------------------------------------- population
    @property
    def next_id(self) -> int:
        """The id the next added agent gets unless ``add_agents`` is given ids."""
        return self._next_id

    def add_agents(self, pos_m: np.ndarray, vel_map_m_s: np.ndarray | None = None,
                   ids: np.ndarray | None = None) -> np.ndarray:
        """Add agents at ``pos_m`` (k, 3) flying ``vel_map_m_s`` (k, 3; default: their command).

        ``ids``: their ids, strictly increasing from ``next_id`` on (gaps allowed: a reservoir that
        did not admit some candidates); default the next k.  The thrust state starts at the trim of
        that velocity (steady flight).  Returns their ids.
        """
        pos = np.asarray(pos_m, dtype=float).reshape(-1, 3)
        k = pos.shape[0]
        if ids is None:
            ids = np.arange(self._next_id, self._next_id + k, dtype=np.int64)
        else:
            ids = np.asarray(ids, dtype=np.int64).reshape(-1)
            if ids.size != k or (k and (ids[0] < self._next_id or bool((ids[1:] <= ids[:-1]).any()))):
                raise ValueError(f"ids must be {k} strictly increasing ids from {self._next_id} on")
        if k == 0:
            return ids
        if self.n + k > self._pos.shape[0]:
            self._alloc(max(2 * self._pos.shape[0], self.n + k))
        if vel_map_m_s is None and self._kinetic is not None:  # numba: the rows below in one call, the same bits
            self._kinetic.enter(np.ascontiguousarray(pos), np.ascontiguousarray(ids), self.t_s, self._co, self.n,
                                (self._pos, self._vel, self._thr, self._ids, self._out, self._epoch, self._sign,
                                 self._phase))
        else:
            phase = entry_phase(ids)  # numba when installed: deviation_phase's bits
            if vel_map_m_s is None and self.config.mode not in ("mean", "slot"):
                # start at the command of flight_command without look-ahead (kinetic: with its deviation)
                st = self.config.flight_settings
                cmd, _, _ = flight_command(self.field, pos, np.zeros_like(pos), ids, self.t_s,
                                           FlightSettings(st.mode, 0.0, st.persistence_s))
                vel = np.nan_to_num(cmd)
            elif vel_map_m_s is None:
                vel = np.nan_to_num(self.commands_map(pos, ids))
            else:
                vel = np.asarray(vel_map_m_s, dtype=float).reshape(k, 3)
            s = slice(self.n, self.n + k)
            self._pos[s] = pos
            self._vel[s] = vel * MAP_TO_NED
            self._thr[s] = entry_thrust(self._vel[s], self._co)  # trim_thrust_accel's bits
            self._ids[s] = ids
            self._out[s] = 0.0
            self._epoch[s] = -1
            self._sign[s] = 1.0
            self._phase[s] = phase
        self.n += k
        self._next_id = int(ids[-1]) + 1
        self.counters.injected += k
        self._cv = None
        self._cmd_ready = False
        return ids

    def _keep(self, keep: np.ndarray, cv: np.ndarray) -> np.ndarray:
        """Remove the agents where ``keep`` is False, survivors from the tail into their slots (O(removed)
        copies; agent order is not meaningful).  Returns ``cv`` permuted alike."""
        if self._kernel is not None:  # numba: the same moves in one pass (sim.kernels.compact_kernel)
            rows = (self._pos, self._vel, self._thr, self._sign, self._dir, self._cmd)
            self.n = compact_kernel()(keep, rows, (self._out, self._phase), (self._ids, self._epoch, cv))
            return cv[:self.n]
        m = int(np.count_nonzero(keep))
        holes = np.flatnonzero(~keep[:m])
        src = np.flatnonzero(keep[m:]) + m
        for buf in [getattr(self, "_" + k) for k in _AGENT_ROWS] + ([self._cmd] if self._cmd_ready else []):
            buf[holes] = buf[src]
        cv = cv.copy()
        cv[holes] = cv[src]
        self.n = m
        return cv[:m]

    # ---------------------------------------------------------------- stepping
    def assign(self) -> np.ndarray:
        """Eq. cv_assignment for the current positions, after the outlet/escape removals.

        Returns (n,) CV ids (-1: outside the CVs, under the return policy).  Cached until the
        agents move or the population changes.
        """
        if self._cv is not None:
            return self._cv
        n = self.n
        if self._kernel is not None:
            lk = self.lookup
            cv, cells = self._cvbuf[:n], self._cellbuf[:n]
            self._kernel(self.pos_m, self.ids, lk._origin, lk._inv_l, lk._hi, lk._strides, lk._flat,
                         self._mean_ned, self._slot_ned, self._n_star, self.config.mode == "slot",
                         cv, self._cmd[:n], cells)
            lk._last = cells
            self._cmd_ready = True
        else:
            cv = self.lookup(self.pos_m)
        if self._kernel is not None:  # same rule as below, one numba pass (sim.kernels)
            keep = np.empty(n, dtype=bool)
            n_exit, n_esc = removal_kernel()(self.pos_m, cv, self.lookup._last, self.outside_s, self.lookup._near,
                                             self.x_outlet_m, self.config.escape_grace_s, keep)
        else:
            exited = self.pos_m[:, 0] >= self.x_outlet_m
            outside = (cv < 0) & ~exited
            escaped = outside & (self.outside_s > self.config.escape_grace_s)
            if outside.any():
                # agents with no CV within the return radius cannot be steered back: escaped now
                idx = np.flatnonzero(outside)
                near = self.lookup.nearest_of_last(idx)
                escaped[idx[near < 0]] = True
            n_exit, n_esc = int(np.count_nonzero(exited)), int(np.count_nonzero(escaped))
            keep = ~(exited | escaped) if n_exit or n_esc else None
        if n_exit or n_esc:
            self.counters.exited += n_exit
            self.counters.escaped += n_esc
            cv = self._keep(keep, cv)
        self._cv = cv
        return cv

    def step(self, steps: int = 1) -> None:
        """``steps`` steps of Algorithm 1 for every agent (no agents added in between)."""
        if steps < 1:
            raise ValueError(f"steps must be >= 1, got {steps!r}")
        if self._fused is not None and self.command_filter is None and self.collider is None:
            return self._fused.step(self, steps)  # one kernel call, the bits of the passes below
        for _ in range(steps):
            self._step()

    def _step(self) -> None:
        """One step of Algorithm 1 for every agent (the multi-pass step)."""
        cv = self.assign()
        n = self.n
        self.counters.steps += 1
        self.counters.agent_steps += n
        self.t_s += self.config.dt_s
        if n == 0:
            return
        cmd = self._cmd[:n]
        self._select_commands(cv, cmd, self.t_s - self.config.dt_s, into_buffer=True)
        fused = self._kernel is not None  # numba: sim.kernels, same numbers as the numpy path
        if fused:
            self.counters.returned += self._fused_returns(cv, cmd)
        else:
            outside = cv < 0
            out_s = self.outside_s
            if outside.any():
                self._return_commands(np.flatnonzero(outside), cmd)
                out_s[outside] += self.config.dt_s
                out_s[~outside] = 0.0
                self.counters.returned += int(np.count_nonzero(outside))
            elif self.counters.returned:
                out_s[...] = 0.0
        vel, thr = self.vel_ned_m_s, self.thrust_ned_m_s2
        if self.command_filter is not None:
            self.command_filter.apply(self.pos_m, vel, cmd, self.ids)
        self._plant_step(vel, thr, cmd)  # sim.plant.model.step_plant in place
        if self.collider is not None:
            self.collider.apply(self.pos_m, vel)
        if fused:
            move_kernel()(self.pos_m, vel, self._fdt)
        else:
            dx = self._scratch[:n]
            np.multiply(vel, self._fdt, out=dx)
            self.pos_m[...] += dx
        self._cv = None
        self._cmd_ready = False

    def _select_commands(self, cv: np.ndarray, cmd_ned: np.ndarray, t_s: float, into_buffer: bool) -> None:
        """NED commands of the configured mode for agents with CVs ``cv`` at time ``t_s`` (rows with
        cv = -1 are overwritten by the return policy later).  ``into_buffer``: ``cmd_ned`` is the
        step's own buffer, which the fused lookup kernel may already have filled."""
        if self.config.mode not in ("mean", "slot"):
            self._flight_commands(cv, cmd_ned, t_s)
        elif self.config.lookahead_s > 0:
            self._lookahead_commands(cv, cmd_ned)
        elif self._cmd_ready:
            if not into_buffer:
                cmd_ned[...] = self._cmd[:self.n]
        else:
            self._command_ned(cv, cmd_ned)

    def current_commands_map(self) -> np.ndarray:
        """(n, 3) map-frame commands the next ``step`` flies for agents inside a CV (NaN rows for
        agents outside, which fly the return policy), without changing any state (the kinetic
        mode's deviation state included).  For tests comparing the simulator with the agent."""
        cv = self.assign()
        n = self.n
        epoch, sign, direction = self._epoch[:n].copy(), self._sign[:n].copy(), self._dir[:n].copy()
        cmd = np.zeros((n, 3))
        self._select_commands(cv, cmd, self.t_s, into_buffer=False)
        self._epoch[:n], self._sign[:n], self._dir[:n] = epoch, sign, direction
        out = cmd * MAP_TO_NED
        out[cv < 0] = np.nan
        return out

    def _flight_commands(self, cv: np.ndarray, cmd_ned: np.ndarray, t_s: float) -> None:
        """Commands of every agent from ``fisc_agent.map.lookup.flight_command`` (the onboard agent's
        function, vectorised), rows outside the CVs 0 (the return policy fills them; numba: ``KineticStep``)."""
        n = self.n
        rows = self._epoch[:n], self._sign[:n], self._dir[:n], self._phase[:n]
        if self._kinetic is not None:
            return self._kinetic.commands(self.pos_m, self.vel_ned_m_s, self.ids, cv, t_s, *rows, cmd_ned)
        cmd, _, new = flight_command(self.field, self.pos_m, self.velocity_map(), self.ids, t_s,
                                     self.config.flight_settings, DeviationState(*rows), cv_ids=cv)
        if new is not None:
            self._epoch[:n], self._sign[:n], self._dir[:n] = new.epoch, new.sign, new.direction
        cmd[np.isnan(cmd)] = 0.0
        np.multiply(cmd, MAP_TO_NED, out=cmd_ned)

    def _lookahead_commands(self, cv: np.ndarray, cmd_ned: np.ndarray) -> None:
        """Fill ``cmd_ned`` with the command at the look-ahead point x + u t_lead (``lookahead_point``);
        agents whose look-ahead point has no CV keep their own CV's command."""
        pts = lookahead_point(self.pos_m, self.velocity_map(), self.config.lookahead_s)
        ahead = self.lookup(pts)
        fallback = ahead < 0
        if fallback.any():
            ahead[fallback] = cv[fallback]
            pts[fallback] = self.pos_m[fallback]
        if self.config.mode not in ("mean", "slot"):
            inside = ahead >= 0
            cmd_ned[...] = 0.0
            if inside.any():
                cmd_ned[inside] = self.field.command(pts[inside], self.ids[inside], self.config.mode,
                                                     cv_ids=ahead[inside]) * MAP_TO_NED
        else:
            self._command_ned(ahead, cmd_ned)

    def _fused_returns(self, cv: np.ndarray, cmd_ned: np.ndarray) -> int:
        """``_return_commands`` for every agent with ``cv < 0`` plus the time-outside update, in one
        numba pass (``sim.kernels.return_commands_kernel``); returns the number outside."""
        lk = self.lookup
        return return_commands_kernel()(
            self.pos_m, self.ids, cv, cmd_ned, self.outside_s, self.config.dt_s, lk._origin, lk._inv_l, lk._hi,
            lk._strides, lk._near, self._centers_m, self._mean_speed, self._mean_ned, self._slot_ned, self._n_star,
            self.config.mode == "slot", self.config.return_gain_1_s, self.config.return_speed_fraction, MAP_TO_NED,
        )  # fmt: skip

    def _return_commands(self, idx: np.ndarray, cmd_ned: np.ndarray) -> None:
        """Return policy for agents ``idx`` outside the CVs: ``fisc_agent.map.lookup.return_command`` (the
        nearest CV's command + inward pull; ``slot`` mode: that CV's slot vector + the pull)."""
        pos = self.pos_m[idx]
        near = self.lookup.nearest(pos)
        near = np.where(near < 0, 0, near)  # cannot happen after assign(); keeps indexing safe
        corr = return_pull(self.field, pos, near, self.config.return_gain_1_s, self.config.return_speed_fraction)
        if self.config.mode == "slot":
            base = self._slot_ned[near, (slot_hash(self.ids[idx], near) % self._n_star[near]).astype(np.int64)]
        else:
            base = self._mean_ned[near]
        cmd_ned[idx] = base + corr * MAP_TO_NED
