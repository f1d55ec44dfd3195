"""The ``kinetic`` command mode of :class:`sim.swarm.Swarm` in one numba pass per step.

The glue between the swarm's buffers and ``sim.kernels.kinetic_commands_kernel``: the map's tables
gathered once, the step's commands and the new agents' start velocities.  The numpy reference is
``fisc_agent.map.lookup.flight_command`` (``Swarm`` flies it when numba is off); both give the same
bits (tests/sim/test_kinetic_kernel.py).
"""

from __future__ import annotations

import numpy as np

from fisc_agent.map.kinetic import BRAKE_S, WALL_ZONE, deviation_direction, deviation_phase
from fisc_agent.map.lookup import CommandField
from sim.kernels import jit_kernels, kinetic_commands_kernel

_MAP_TO_NED = np.array([1.0, 1.0, -1.0])
"""``sim.swarm.MAP_TO_NED`` (not imported: ``sim.swarm`` imports this module)."""


class KineticStep:
    """The kinetic commands of a swarm from one kernel (``make`` returns None without numba)."""

    def __init__(self, kernel, field: CommandField, persistence_s: float, lookahead_s: float) -> None:
        self._kernel = kernel
        self.persistence_s = float(persistence_s)
        self.lookahead_s = float(lookahead_s)
        hi, strides, offset = field._padded_rows
        lower, upper = field._cell_faces
        self.tables = (np.asarray(field.origin_m, dtype=float), float(field.cell_size_m), hi, strides, offset,
                        field._padded_cv, lower, upper, field.kinetic_codes, field._spread_xyz, WALL_ZONE,
                        BRAKE_S, _MAP_TO_NED)
        """The map's tables the kinetic kernels take after the agents' rows (the fused step passes them too)."""

    @classmethod
    def make(cls, field: CommandField, persistence_s: float, lookahead_s: float) -> "KineticStep | None":
        """The step for ``field`` (a schema-2 map), or None when numba is not installed."""
        kernel = kinetic_commands_kernel()
        return None if kernel is None else cls(kernel, field, persistence_s, lookahead_s)

    def commands(self, pos_m: np.ndarray, vel_ned_m_s: np.ndarray, ids: np.ndarray, cv: np.ndarray, t_s: float,
                 epoch: np.ndarray, sign: np.ndarray, direction: np.ndarray, phase: np.ndarray,
                 cmd_ned: np.ndarray) -> None:
        """Fill ``cmd_ned`` (n, 3) with the NED commands at ``t_s`` of agents in CVs ``cv`` (0 where the
        look-up point has no CV) and update their deviation state (``epoch``, ``sign``, ``direction``)
        in place, as ``flight_command`` with the look-ahead."""
        self._kernel(pos_m, vel_ned_m_s, ids, cv, True, float(t_s) / self.persistence_s, self.lookahead_s,
                     epoch, sign, direction, phase, *self.tables, cmd_ned)

    def start_velocity(self, pos_m: np.ndarray, ids: np.ndarray, t_s: float,
                       phase: np.ndarray | None = None) -> np.ndarray:
        """(k, 3) map-frame start velocities of new agents: ``flight_command`` at rest, without
        look-ahead, from a fresh deviation state (then dropped), rows outside the CVs 0.  ``phase``:
        ``deviation_phase(ids)`` if already computed."""
        k = pos_m.shape[0]
        cmd = np.empty((k, 3))
        self._kernel(pos_m, np.zeros((k, 3)), ids, np.empty(0, dtype=np.int64), False,
                     float(t_s) / self.persistence_s, 0.0, np.full(k, -1, dtype=np.int64), np.ones((k, 3)),
                     np.zeros((k, 3)), deviation_phase(ids) if phase is None else phase, *self.tables, cmd)
        return cmd * _MAP_TO_NED

    def enter(self, pos_m: np.ndarray, ids: np.ndarray, t_s: float, co, n: int, rows: tuple) -> None:
        """Write new agents (``pos_m`` (k, 3) float64, ``ids`` (k,) int64, contiguous) into a swarm's row
        buffers ``rows`` = (pos, vel, thr, ids, out_s, epoch, sign, phase) at ``n .. n + k`` (capacity there):
        the rows ``Swarm.add_agents`` writes, its start velocity from ``start_velocity`` and the trim thrust of
        ``sim.entry.entry_thrust``, in one kernel call (``sim.kinetic_jit.enter_agents``; ``co`` fleet-wide
        plant coefficients)."""
        from sim import kinetic_jit

        kinetic_jit.enter_agents(pos_m, ids, float(t_s) / self.persistence_s, *self.tables,
                                 co.drag_k[0], float(co.g[0]), float(co.accel_max[0]), float(co.tan_tilt[0]),
                                 n, *rows)


def deviation_x(ids: np.ndarray, t_s: float, persistence_s: float) -> np.ndarray:
    """(k,) the x component of ``fisc_agent.map.kinetic.deviation_direction`` of agents ``ids`` at
    ``t_s``: one numba pass when numba is installed (the same bits), else the numpy function."""
    ids = np.asarray(ids, dtype=np.int64).reshape(-1)
    if jit_kernels() is None:
        return deviation_direction(ids, t_s, persistence_s)[0][:, 0]
    from sim import kinetic_jit

    out = np.empty(ids.size)
    kinetic_jit.deviation_x(ids, float(t_s) / persistence_s, out)
    return out


class BatchAdmission:
    """A kinetic reservoir's batches in one numba pass each (``sim.kinetic_jit.admit_batch``; numba must be
    installed), its tables made contiguous once (a reservoir admits a batch every few steps, and the
    conversions cost more than the kernel)."""

    def __init__(self, inlet_cvs: np.ndarray, field: CommandField, entry_x_m_s: np.ndarray, interval_s: float,
                 entry_u_m_s: np.ndarray, spread_m_s: np.ndarray) -> None:
        from sim import kinetic_jit

        self._kernel = kinetic_jit.admit_batch
        self._cvs = np.ascontiguousarray(inlet_cvs, dtype=np.int64)
        self._tables = (np.ascontiguousarray(field.centers_m, dtype=np.float64), float(field.cell_size_m),
                        np.ascontiguousarray(entry_x_m_s, dtype=np.float64), float(interval_s))
        self._entry = (np.ascontiguousarray(entry_u_m_s, dtype=np.float64),
                       np.ascontiguousarray(spread_m_s, dtype=np.float64))

    def __call__(self, counts: np.ndarray, u: np.ndarray, r: np.ndarray, first_id: int,
                 t_over_p: float) -> tuple[np.ndarray, np.ndarray]:
        """``counts[q]`` (int64) candidates in inlet CV ``inlet_cvs[q]`` at the uniform draws ``u`` (k, 3)
        (``Reservoir._batch``), candidate k id ``first_id + k``, admitted when ``r[k] < kinetic_admission`` of
        its deviation at ``t_over_p`` = t / persistence (``Reservoir.admit``).  Returns the admitted positions
        (m, 3) and ids (m,)."""
        k = u.shape[0]
        if not (u.shape == (k, 3) and r.shape == (k,) and counts.shape == self._cvs.shape and int(counts.sum()) == k):
            raise ValueError(f"admit_batch: {int(np.sum(counts))} candidates need u ({k}, 3) and r ({k},), got "
                             f"{u.shape} and {r.shape}")  # the kernel trusts its sizes
        pos, ids = np.empty((k, 3)), np.empty(k, dtype=np.int64)
        m = self._kernel(self._cvs, counts, *self._tables, u, r, np.int64(first_id), float(t_over_p), *self._entry,
                         pos, ids)
        return pos[:m], ids[:m]
