"""The ``kinetic`` command mode: a persistent per-agent deviation on top of the staggered field.

Each agent keeps a direction for a persistence interval and flies it at the CV's spread (the
fitted spread at the designed density, ``kinetic_spread``), so the swarm carries the CFD pressure
as the paper's pressure analogue P = 2/3 rho <v'^2> (the kinetic picture of a gas).  Components
heading for a staircase wall are reflected, and the reflection is forgotten where the wall steps
outward.  The state is explicit (``DeviationState``, passed in and returned); time is passed in.
Numpy only: the onboard agent flies the same functions as the simulator.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from fisc_agent.map.hashing import slot_hash


class KineticGrid(Protocol):
    """What the deviation needs of the CV grid (``fisc_agent.map.lookup.CommandField`` is one):
    its cell size, per-cell wall codes and point location.  A Protocol, so this module does not
    import ``lookup`` (which imports it)."""

    cell_size_m: float
    kinetic_codes: np.ndarray

    def locate(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows, frac, cv ids) of ``points_m`` on the grid (``CommandField.locate``)."""


#: Kinetic mode: depth of the zone next to a wall face in which a deviation toward the wall is
#: reflected [cells] (thin, so the reflection itself empties little of the wall cube).
WALL_ZONE = 0.25
#: Kinetic mode: a vehicle heading for a wall face at normal speed v_n reflects once the face is
#: within v_n * BRAKE_S (if that is deeper than ``WALL_ZONE``): the lag-proportional turning
#: distance that keeps the reflection scale-free (a 5 m/s map deviates 2.5x faster than a 2 m/s one).
BRAKE_S = 0.25
#: Default persistence time of the kinetic deviation [s] (several plant time constants of ~0.6 s).
DEFAULT_PERSISTENCE_S = 2.0


def kinetic_spread(fitted_spread_m_s: np.ndarray, design_density: np.ndarray) -> np.ndarray:
    """The ``kinetic`` deviation's rms per CV: the fitted spread sigma_j scaled to the designed density,
    sigma_j sqrt(mean(rho_d) / rho_d,j).

    The fit gives each CV the spread that carries the CFD pressure at the fitted (uniform) agent
    density, P_j = 2/3 rho sigma_j^2 (DESIGN.md section 3).  A swarm designed to be thinner in a CV
    must be hotter there for the same pressure (an ideal gas: sigma^2 ~ P / rho).  Measured (Case 2,
    seeds 0 / 1 / 2 on cd_nozzle_inviscid): pressure nRMSE 0.196 / 0.210 / 0.233 against 0.257 /
    0.249 / 0.239 with the fitted spread alone, density 0.251 / 0.262 / 0.254 against 0.256 / 0.269 /
    0.260 (docs/simulation.md)."""
    rho = np.asarray(design_density, dtype=float)
    if rho.shape != np.shape(fitted_spread_m_s) or not np.all(rho > 0):
        raise ValueError("design density must be > 0 with one value per CV")
    return np.asarray(fitted_spread_m_s, dtype=float) * np.sqrt(rho.mean() / rho)


@dataclass(frozen=True)
class DeviationState:
    """Per-agent state of the ``kinetic`` mode (explicit: passed in and returned, no clocks inside)."""

    epoch: np.ndarray
    """(m,) int64 index of the persistence interval the current direction belongs to (-1: none yet)."""
    sign: np.ndarray
    """(m, 3) float +-1 per axis: wall reflections of the direction within the current interval
    (forgotten where the staircase steps outward)."""
    direction: np.ndarray
    """(m, 3) unit direction of interval ``epoch`` before reflections: a cache of
    ``deviation_direction`` (a function of agent id and interval), hashed again only when the
    interval changes."""
    phase: np.ndarray | None = None
    """(m,) a cache of ``deviation_phase`` of these agents' ids (a function of the id alone); None:
    not hashed yet (the next call hashes it and returns it in the new state)."""

    @classmethod
    def new(cls, m: int) -> "DeviationState":
        """State of ``m`` agents that have not flown yet."""
        return cls(np.full(m, -1, dtype=np.int64), np.ones((m, 3)), np.zeros((m, 3)))

    def take(self, index: np.ndarray) -> "DeviationState":
        """The state of the agents ``index`` (a new object)."""
        return DeviationState(self.epoch[index].copy(), self.sign[index].copy(), self.direction[index].copy(),
                              None if self.phase is None else self.phase[index].copy())


def _unit_from_hash(agent_ids: np.ndarray, epoch: np.ndarray) -> np.ndarray:
    """(m, 3) unit vectors, uniform on the sphere, a deterministic function of (agent id, epoch)."""
    ids = np.asarray(agent_ids, dtype=np.int64).reshape(-1)
    e = np.asarray(epoch).reshape(-1)
    h = slot_hash(np.concatenate([ids, ids ^ 0x5BD1E995]), np.concatenate([e, e])) * (1.0 / 4294967296.0)
    m = ids.size
    z = 2.0 * h[:m] - 1.0
    phi = 2.0 * np.pi * h[m:]
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    out = np.empty((m, 3))
    np.multiply(r, np.cos(phi), out=out[:, 0])
    np.multiply(r, np.sin(phi), out=out[:, 1])
    out[:, 2] = z
    return out


def deviation_direction(agent_ids: np.ndarray, t_s: float, persistence_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(m, 3) unit deviation directions before any wall reflection, and (m,) their interval index.

    Each agent keeps a direction for ``persistence_s``; the intervals are staggered per agent by a
    hashed phase (the swarm does not switch in step) and the direction is uniform on the sphere, a
    hash of (agent id, interval).  Any fixed component of it is uniform on [-1, 1]."""
    ids = np.asarray(agent_ids, dtype=np.int64).reshape(-1)
    epoch = deviation_epoch(ids, t_s, persistence_s)
    return _unit_from_hash(ids, epoch), epoch


def deviation_phase(agent_ids: np.ndarray) -> np.ndarray:
    """(m,) each agent's phase in [0, 1) of its persistence intervals (a hash of its id)."""
    return slot_hash(np.asarray(agent_ids, dtype=np.int64).reshape(-1), 0x2545F491) * (1.0 / 4294967296.0)


def deviation_epoch(agent_ids: np.ndarray, t_s: float, persistence_s: float,
                    phase: np.ndarray | None = None) -> np.ndarray:
    """(m,) index of each agent's persistence interval at ``t_s``: floor(t_s / persistence_s + phase),
    staggered by the hashed ``deviation_phase`` (given: its cached value for these agents)."""
    p = deviation_phase(agent_ids) if phase is None else phase
    return np.floor(float(t_s) / persistence_s + p).astype(np.int64)


def kinetic_deviation(field: KineticGrid, points_m: np.ndarray, agent_ids: np.ndarray, t_s: float,
                      persistence_s: float, state: DeviationState,
                      velocity_m_s: np.ndarray | None = None) -> tuple[np.ndarray, DeviationState]:
    """(m, 3) unit deviation directions at time ``t_s`` and the new state.

    Each agent keeps a direction for ``persistence_s`` (intervals staggered per agent by a hashed
    phase, so the swarm does not switch in step), drawn uniformly on the sphere from a hash of
    (agent id, interval).  A component pointing at a staircase face without a neighbour CV (a wall)
    is reflected while the agent is within ``WALL_ZONE`` cells of that face, or within its turning
    distance v_n ``BRAKE_S`` when ``velocity_m_s`` is given (the zone absorbs the vehicle's lag,
    which would otherwise carry it across): the kinetic picture of a gas whose
    molecules bounce off the walls.  A reflected component keeps its sign for the rest of the
    interval while the wall runs on beside the agent, but where the staircase steps outward
    (``CommandField.stepped_out_faces``: the face the reflection came from now opens onto a newly
    opened cube) the drawn direction returns.  Kept, the reflection would steer the agents of a
    diverging duct away from the cubes that open there: on the default run those held 0.57-0.63 of
    their designed density, and the density's correlation with the CFD rose from 0.55 to 0.62 when
    the reflection was forgotten (docs/simulation.md).  The inlet is an open boundary to the reservoir, not a wall:
    an agent whose deviation carries it upstream out of the first slice leaves the CVs there (the
    simulator's reservoir admits entering agents flux-weighted by their deviation,
    ``sim.scenarios.Reservoir.admit``; a fade-out of upstream components over the first cell, as
    before, made agents stall there: first slices 1.2x their designed density).
    """
    rows, frac, _ = field.locate(points_m)
    return deviation_in_cells(field, rows, frac, agent_ids, t_s, persistence_s, state, velocity_m_s)


def deviation_in_cells(field: KineticGrid, rows: np.ndarray, frac: np.ndarray, agent_ids: np.ndarray, t_s: float,
                       persistence_s: float, state: DeviationState,
                       velocity_m_s: np.ndarray | None = None) -> tuple[np.ndarray, DeviationState]:
    """``kinetic_deviation`` for points already located on the grid (``CommandField.locate``: ``rows``
    (m,) their cells' rows in the per-cell tables, ``frac`` (m, 3) their positions within them).
    ``flight_command`` locates each point once for the command and the deviation."""
    ids = np.asarray(agent_ids, dtype=np.int64).reshape(-1)
    phase = deviation_phase(ids) if state.phase is None else state.phase
    epoch = deviation_epoch(ids, t_s, persistence_s, phase)
    fresh = np.flatnonzero(epoch != state.epoch)
    sign = state.sign.copy()
    direction = state.direction
    if fresh.size:
        direction = direction.copy()
        direction[fresh] = _unit_from_hash(ids[fresh], epoch[fresh])
        sign[fresh] = 1.0
    codes = field.kinetic_codes.take(rows, axis=0)  # (m, 3): wall faces bits 0-1, stepped-out faces 2-3
    # where the wall a component was reflected from steps outward, the drawn direction returns
    stepped = (codes >> ((direction >= 0) + 2)) & 1
    np.copyto(sign, 1.0, where=(sign < 0) & (stepped == 1))
    d = direction * sign
    up = d >= 0
    wall_ahead = ((codes >> up) & 1) == 1
    zone = WALL_ZONE
    if velocity_m_s is not None and BRAKE_S > 0:
        # a vehicle heading for a face at v_n turns once the face is within v_n * BRAKE_S
        v = np.atleast_2d(velocity_m_s)
        v_n = np.where(up, v, -v)
        np.maximum(v_n, 0.0, out=v_n)
        zone = np.maximum(zone, v_n * BRAKE_S / field.cell_size_m)
    toward = np.where(up, frac >= 1.0 - zone, frac < zone)
    flip = toward & wall_ahead
    np.negative(sign, out=sign, where=flip)
    np.negative(d, out=d, where=flip)
    return d, DeviationState(epoch, sign, direction, phase)
