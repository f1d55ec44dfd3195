"""Fused numba kernels of the swarm step (Algorithm 1) around the plant: numerical cores only.

The numpy code of :class:`sim.swarm.Swarm` is the reference; these kernels compute the same
numbers (same operations in the same order) in one pass over the agents instead of a dozen
masked numpy passes, which dominate the step once the plant kernel is fast:

* :func:`removal_kernel` - the outlet / escape removal rule of ``Swarm.assign``.
* :func:`return_commands_kernel` - the per-step bookkeeping before the plant: for agents
  outside every CV (``cv < 0``) the return-policy command (nearest CV's command plus the capped
  inward pull, ``Swarm._return_commands``) and their time outside; the others' time outside
  reset to 0.
* :func:`compact_kernel` - the removal of agents (survivors from the tail into the holes).
* :func:`move_kernel` - the position update ``x += (MAP_TO_NED * dt) * v_NED`` (step 4).
* :func:`kinetic_commands_kernel` - the ``kinetic`` mode's commands (look-ahead, staggered field,
  deviation, wall reflection) in one pass (``sim.kinetic_jit``, glued in by ``sim.kinetic_step``).

Each factory returns the compiled kernel, or None when numba is not importable.
"""

from __future__ import annotations

import functools
from types import ModuleType


@functools.lru_cache(maxsize=1)
def jit_kernels() -> ModuleType | None:
    """The module of compiled kernels (``sim.jit_kernels``), or None when numba is not installed (looked up
    once: the swarm asks for its kernels every step)."""
    try:
        from sim import jit_kernels as module
    except ModuleNotFoundError as exc:
        if exc.name != "numba":
            raise
        return None
    return module


def cell_and_slot_helpers():
    """``(padded_cell, slot_of)`` jitted helpers shared by the kernels; None without numba.

    ``padded_cell(pos, i, origin, inv_l, hi, strides)``: flat index of agent ``i``'s cell on the
    padded grid, indices clipped to ``[0, hi]`` (as ``CVLookup``).  ``slot_of(agent_id, j,
    n_star_j)``: ``fisc_agent.map.hashing.slot_index`` for one agent, the numba twin of the one pure
    hash ``fisc_agent.map.hashing.slot_mix`` (numba types uint64 arithmetic with integer literals as
    float64, so the mix is spelled with uint64 constants here); tests/fisc_agent/test_contracts.py
    checks the two equal on 10^5 inputs.
    """
    jk = jit_kernels()
    return None if jk is None else (jk.padded_cell, jk.slot_of)


def return_commands_kernel():
    """Kernel ``(pos, ids, cv, cmd, out_s, dt_s, origin, inv_l, hi, strides, near_flat, centers,
    mean_speed, mean_ned, slot_ned, n_star, slot_mode, gain, frac, map_to_ned) -> n_outside``.

    For every agent ``i`` with ``cv[i] < 0``: cell of ``pos[i]`` on the padded grid (as
    ``CVLookup.nearest``), nearest CV ``j = near_flat[cell]`` (-1 -> 0, as the numpy path),
    ``corr = gain (centers[j] - pos[i])`` scaled by ``min(1, frac mean_speed[j] / max(|corr|,
    1e-12))``, ``cmd[i] = base + corr * map_to_ned`` with ``base`` the mean (or slot, hash as
    ``fisc_agent.map.hashing.slot_hash``) NED command of ``j``; ``out_s[i] += dt_s``.  Agents with
    ``cv[i] >= 0`` get ``out_s[i] = 0`` (their command is untouched).  Returns the number outside.
    """
    jk = jit_kernels()
    return None if jk is None else jk.return_commands


def removal_kernel():
    """Kernel ``(pos, cv, cells, out_s, near_flat, x_outlet_m, grace_s, keep) -> (n_exited,
    n_escaped)``: the removal rule of ``Swarm.assign`` in one pass.

    Agent ``i`` has *exited* when ``pos[i, 0] >= x_outlet_m``; otherwise, outside every CV
    (``cv[i] < 0``), it has *escaped* when ``out_s[i] > grace_s`` or its padded-grid cell
    ``cells[i]`` has no CV within the return radius (``near_flat[cells[i]] < 0``).  Writes
    ``keep[i] = not (exited or escaped)``.
    """
    jk = jit_kernels()
    return None if jk is None else jk.removal


def move_kernel():
    """Kernel ``(pos, vel, fdt)``: ``pos[i, k] += vel[i, k] * fdt[k]`` in place (one pass)."""
    jk = jit_kernels()
    return None if jk is None else jk.move


def compact_kernel():
    """Kernel ``(keep, rows3, rows1, rows_int) -> m``: the agent removal of ``Swarm._keep`` in one pass.

    ``keep`` (n,) bool; ``rows3`` a tuple of (>= n, 3) float64 buffers, ``rows1`` of (>= n,) float64 and
    ``rows_int`` of (>= n,) int64 ones.  With ``m`` the number kept, each hole ``i < m`` (``keep[i]``
    False) gets the row of the next kept ``j >= m``, in increasing order of both: the same moves as the
    numpy ``buf[holes] = buf[src]``, so the same state.  Returns ``m``.
    """
    jk = jit_kernels()
    return None if jk is None else jk.compact


def kinetic_commands_kernel():
    """Kernel ``(pos, vel_ned, ids, cv, cv_given, t_over_p, lead_s, epoch, sign, direction, phase, origin,
    cell, hi, strides, offset, padded_cv, lower, upper, codes, spread_xyz, zone0, brake_s, map_to_ned,
    cmd_out)``: the ``kinetic`` mode of ``fisc_agent.map.lookup.flight_command`` for every agent in one pass
    (``sim.kinetic_jit``).

    Per agent: its cell on ``CommandField``'s padded grid (``locate``), the look-ahead point
    ``x + lead_s u`` (u = ``vel_ned * map_to_ned``; its own point when that has no CV), the staggered
    field there, and the deviation of ``fisc_agent.map.kinetic.deviation_in_cells`` at interval
    ``floor(t_over_p + phase)`` with its wall reflections; the state (``epoch``, ``sign``,
    ``direction``) is updated in place.  ``cv``: the agents' own CVs when ``cv_given``, else looked up
    on the padded grid.  ``cmd_out`` gets the NED command (0 where the look-up point has no CV).
    """
    try:
        from sim import kinetic_jit as module
    except ModuleNotFoundError as exc:
        if exc.name != "numba":
            raise
        return None
    return module.kinetic_commands
