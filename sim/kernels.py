"""Fused numba kernels of the swarm step (Algorithm 1) around the plant: numerical cores only.

The numpy code of :class:`sim.swarm.Swarm` is the reference; these kernels compute the same
numbers (same operations in the same order) in one pass over the agents instead of a dozen
masked numpy passes, which dominate the step once the plant kernel is fast:

* :func:`removal_kernel` - the outlet / escape removal rule of ``Swarm.assign``.
* :func:`return_commands_kernel` - the per-step bookkeeping before the plant: for agents
  outside every CV (``cv < 0``) the return-policy command (nearest CV's command plus the capped
  inward pull, ``Swarm._return_commands``) and their time outside; the others' time outside
  reset to 0.
* :func:`move_kernel` - the position update ``x += (MAP_TO_NED * dt) * v_NED`` (step 4).

Each factory returns the compiled kernel, or None when numba is not importable.
"""

from __future__ import annotations

import functools
import math


@functools.lru_cache(maxsize=1)
def cell_and_slot_helpers():
    """``(padded_cell, slot_of)`` jitted helpers shared by the kernels; None without numba.

    ``padded_cell(pos, i, origin, inv_l, hi, strides)``: flat index of agent ``i``'s cell on the
    padded grid, indices clipped to ``[0, hi]`` (as ``CVLookup``).  ``slot_of(agent_id, j,
    n_star_j)``: ``fisc_agent.lookup.slot_index`` for one agent, the numba twin of the one pure
    hash ``fisc_agent.lookup.slot_mix`` (numba types uint64 arithmetic with integer literals as
    float64, so the mix is spelled with uint64 constants here); tests/fisc_agent/test_contracts.py
    checks the two equal on 10^5 inputs.
    """
    try:
        import numba
        import numpy as np
    except ImportError:
        return None
    m32 = np.uint64(0xFFFFFFFF)

    @numba.njit(cache=True, nogil=True, inline="always")
    def padded_cell(pos, i, origin, inv_l, hi, strides):
        c = 0
        for k in range(3):
            f = math.floor((pos[i, k] - origin[k]) * inv_l)
            if f < 0.0:
                f = 0.0
            elif f > hi[k]:
                f = hi[k]
            c += np.int64(f) * strides[k]
        return c

    @numba.njit(cache=True, nogil=True, inline="always")
    def slot_of(agent_id, j, n_star_j):
        a = np.uint64(agent_id) & m32
        b = np.uint64(j) & m32
        h = ((a * np.uint64(0x9E3779B1)) ^ (b * np.uint64(0x85EBCA77) + np.uint64(0x27D4EB2F))) & m32
        h ^= h >> np.uint64(15)
        h = (h * np.uint64(0x2C1B3C6D)) & m32
        h ^= h >> np.uint64(12)
        return np.int64(h % n_star_j)

    return padded_cell, slot_of


@functools.lru_cache(maxsize=1)
def return_commands_kernel():
    """Kernel ``(pos, ids, cv, cmd, out_s, dt_s, origin, inv_l, hi, strides, near_flat, centers,
    mean_speed, mean_ned, slot_ned, n_star, slot_mode, gain, frac, map_to_ned) -> n_outside``.

    For every agent ``i`` with ``cv[i] < 0``: cell of ``pos[i]`` on the padded grid (as
    ``CVLookup.nearest``), nearest CV ``j = near_flat[cell]`` (-1 -> 0, as the numpy path),
    ``corr = gain (centers[j] - pos[i])`` scaled by ``min(1, frac mean_speed[j] / max(|corr|,
    1e-12))``, ``cmd[i] = base + corr * map_to_ned`` with ``base`` the mean (or slot, hash as
    ``fisc_agent.lookup.slot_hash``) NED command of ``j``; ``out_s[i] += dt_s``.  Agents with
    ``cv[i] >= 0`` get ``out_s[i] = 0`` (their command is untouched).  Returns the number outside.
    """
    try:
        import numba
    except ImportError:
        return None
    padded_cell, slot_of = cell_and_slot_helpers()

    @numba.njit(cache=True, nogil=True, error_model="numpy")
    def kernel(pos, ids, cv, cmd, out_s, dt_s, origin, inv_l, hi, strides, near_flat, centers,
               mean_speed, mean_ned, slot_ned, n_star, slot_mode, gain, frac, map_to_ned):
        n_out = 0
        for i in range(cv.shape[0]):
            if cv[i] >= 0:
                out_s[i] = 0.0
                continue
            n_out += 1
            out_s[i] += dt_s
            c = padded_cell(pos, i, origin, inv_l, hi, strides)
            j = near_flat[c]
            if j < 0:
                j = 0
            q0 = gain * (centers[j, 0] - pos[i, 0])
            q1 = gain * (centers[j, 1] - pos[i, 1])
            q2 = gain * (centers[j, 2] - pos[i, 2])
            # (x^2 + z^2) + y^2: the order numpy's einsum sums in on this path, so both paths agree
            # bit for bit (any order is equally correct, to round-off)
            mag = math.sqrt((q0 * q0 + q2 * q2) + q1 * q1)
            s = min(1.0, frac * mean_speed[j] / max(mag, 1e-12))
            q0 *= s
            q1 *= s
            q2 *= s
            if slot_mode:
                kk = slot_of(ids[i], j, n_star[j])
                cmd[i, 0] = slot_ned[j, kk, 0] + q0 * map_to_ned[0]
                cmd[i, 1] = slot_ned[j, kk, 1] + q1 * map_to_ned[1]
                cmd[i, 2] = slot_ned[j, kk, 2] + q2 * map_to_ned[2]
            else:
                cmd[i, 0] = mean_ned[j, 0] + q0 * map_to_ned[0]
                cmd[i, 1] = mean_ned[j, 1] + q1 * map_to_ned[1]
                cmd[i, 2] = mean_ned[j, 2] + q2 * map_to_ned[2]
        return n_out

    return kernel


@functools.lru_cache(maxsize=1)
def removal_kernel():
    """Kernel ``(pos, cv, cells, out_s, near_flat, x_outlet_m, grace_s, keep) -> (n_exited,
    n_escaped)``: the removal rule of ``Swarm.assign`` in one pass.

    Agent ``i`` has *exited* when ``pos[i, 0] >= x_outlet_m``; otherwise, outside every CV
    (``cv[i] < 0``), it has *escaped* when ``out_s[i] > grace_s`` or its padded-grid cell
    ``cells[i]`` has no CV within the return radius (``near_flat[cells[i]] < 0``).  Writes
    ``keep[i] = not (exited or escaped)``.
    """
    try:
        import numba
    except ImportError:
        return None

    @numba.njit(cache=True, nogil=True)
    def kernel(pos, cv, cells, out_s, near_flat, x_outlet_m, grace_s, keep):
        n_exit = 0
        n_esc = 0
        for i in range(cv.shape[0]):
            if pos[i, 0] >= x_outlet_m:
                n_exit += 1
                keep[i] = False
            elif cv[i] < 0 and (out_s[i] > grace_s or near_flat[cells[i]] < 0):
                n_esc += 1
                keep[i] = False
            else:
                keep[i] = True
        return n_exit, n_esc

    return kernel


@functools.lru_cache(maxsize=1)
def move_kernel():
    """Kernel ``(pos, vel, fdt)``: ``pos[i, k] += vel[i, k] * fdt[k]`` in place (one pass)."""
    try:
        import numba
    except ImportError:
        return None

    @numba.njit(cache=True, nogil=True)
    def kernel(pos, vel, fdt):
        f0, f1, f2 = fdt[0], fdt[1], fdt[2]
        for i in range(pos.shape[0]):
            pos[i, 0] += vel[i, 0] * f0
            pos[i, 1] += vel[i, 1] * f1
            pos[i, 2] += vel[i, 2] * f2

    return kernel
