"""The numba-compiled kernels of the swarm step, defined at module level so that numba's
on-disk cache (``cache=True``) finds them again in the next process: a kernel that captures
other jitted functions in a closure is compiled anew, and cached anew, by every process.

Imports numba: reach these only through the factories of ``sim.kernels`` and
``sim.cv_lookup``, which return None when numba is not installed (the ``fisc[jit]`` extra).
"""

from __future__ import annotations

import math

import numba
import numpy as np

M32 = np.uint64(0xFFFFFFFF)
"""The 32-bit mask of the slot hash."""


@numba.njit(cache=True, nogil=True, inline="always")
def padded_cell(pos, i, origin, inv_l, hi, strides):
    """Flat index of agent ``i``'s cell on the padded grid, indices clipped to ``[0, hi]`` (as ``CVLookup``)."""
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
def slot_mix32(a, b):
    """``fisc_agent.map.hashing.slot_hash`` of two uint64 values (reduced to 32 bits here): the numba twin
    of ``fisc_agent.map.hashing.slot_mix`` (uint64 constants: numba types integer literals as float64)."""
    a = a & M32
    b = b & M32
    h = ((a * np.uint64(0x9E3779B1)) ^ (b * np.uint64(0x85EBCA77) + np.uint64(0x27D4EB2F))) & M32
    h ^= h >> np.uint64(15)
    h = (h * np.uint64(0x2C1B3C6D)) & M32
    h ^= h >> np.uint64(12)
    return h


@numba.njit(cache=True, nogil=True, inline="always")
def slot_of(agent_id, j, n_star_j):
    """``fisc_agent.map.hashing.slot_index`` for one agent (``slot_mix32``)."""
    return np.int64(slot_mix32(np.uint64(agent_id), np.uint64(j)) % n_star_j)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def return_commands(pos, ids, cv, cmd, out_s, dt_s, origin, inv_l, hi, strides, near_flat, centers,
           mean_speed, mean_ned, slot_ned, n_star, slot_mode, gain, frac, map_to_ned):
    """The return-policy commands and time outside (``sim.kernels.return_commands_kernel``)."""
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


@numba.njit(cache=True, nogil=True)
def removal(pos, cv, cells, out_s, near_flat, x_outlet_m, grace_s, keep):
    """The outlet / escape removal rule (``sim.kernels.removal_kernel``)."""
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


@numba.njit(cache=True, nogil=True)
def move(pos, vel, fdt):
    """``pos += vel * fdt`` in place (``sim.kernels.move_kernel``)."""
    f0, f1, f2 = fdt[0], fdt[1], fdt[2]
    for i in range(pos.shape[0]):
        pos[i, 0] += vel[i, 0] * f0
        pos[i, 1] += vel[i, 1] * f1
        pos[i, 2] += vel[i, 2] * f2


@numba.njit(cache=True, nogil=True)
def fused_lookup(pos, ids, origin, inv_l, hi, strides, flat, mean_ned, slot_ned, n_star, slot_mode,
           cv_out, cmd_out, cell_out):
    """Padded-grid CV lookup and command gather (``sim.cv_lookup.fused_lookup_kernel``)."""
    for i in range(pos.shape[0]):
        c = padded_cell(pos, i, origin, inv_l, hi, strides)
        cell_out[i] = c
        j = flat[c]
        cv_out[i] = j
        if slot_mode and j >= 0:
            kk = slot_of(ids[i], j, n_star[j])
            for k in range(3):
                cmd_out[i, k] = slot_ned[j, kk, k]
        else:
            r = j if j >= 0 else mean_ned.shape[0] - 1  # j = -1: the zero row
            for k in range(3):
                cmd_out[i, k] = mean_ned[r, k]


@numba.njit(cache=True, nogil=True)
def compact(keep, rows3, rows1, rows_int):
    """Remove the rows where ``keep`` is False (``sim.kernels.compact_kernel``); returns the rows kept."""
    n = keep.shape[0]
    m = 0
    for i in range(n):
        m += keep[i]
    j = m
    for i in range(m):
        if keep[i]:
            continue
        while not keep[j]:
            j += 1
        for b in rows3:
            b[i, 0] = b[j, 0]
            b[i, 1] = b[j, 1]
            b[i, 2] = b[j, 2]
        for b in rows1:
            b[i] = b[j]
        for b in rows_int:
            b[i] = b[j]
        j += 1
    return m


@numba.njit(cache=True, nogil=True)
def cv_moment_sums(cv, vel_ned, map_to_ned, mass, ref, count, mass_kg, momentum, m_v2, m_dev2):
    """Per-CV moment sums of one sample (``sim.moments.swarm_moments``), added into the zeroed outputs;
    returns ``(agents whose CV is out of [-1, n_cv), left out; whether every m_v2 sum is finite)``."""
    n_cv = count.shape[0]
    bad = 0
    for i in range(cv.shape[0]):
        j = cv[i]
        if j < 0 or j >= n_cv:
            bad += j < -1 or j >= n_cv
            continue
        v0 = vel_ned[i, 0] * map_to_ned[0]
        v1 = vel_ned[i, 1] * map_to_ned[1]
        v2 = vel_ned[i, 2] * map_to_ned[2]
        count[j] += 1.0
        mass_kg[j] += mass
        momentum[j, 0] += mass * v0
        momentum[j, 1] += mass * v1
        momentum[j, 2] += mass * v2
        # (x^2 + z^2) + y^2: the order of numpy's einsum on this path (as ``return_commands``)
        m_v2[j] += mass * ((v0 * v0 + v2 * v2) + v1 * v1)
        d0 = v0 - ref[j, 0]
        d1 = v1 - ref[j, 1]
        d2 = v2 - ref[j, 2]
        m_dev2[j] += mass * ((d0 * d0 + d2 * d2) + d1 * d1)
    finite = True
    for j in range(n_cv):
        finite &= math.isfinite(m_v2[j])
    return bad, finite



@numba.njit(cache=True, nogil=True)
def deviation_phases(ids, out):
    """``fisc_agent.map.kinetic.deviation_phase`` of agents ``ids`` into ``out`` (``sim.entry``)."""
    for i in range(ids.shape[0]):
        out[i] = slot_mix32(np.uint64(ids[i]), np.uint64(0x2545F491)) * (1.0 / 4294967296.0)


@numba.njit(cache=True, nogil=True)
def trim_thrust(vel_ned, drag_k, g, accel_max, tan_tilt, thr_out):
    """``sim.plant.model.trim_thrust_accel`` for fleet-wide coefficients, its operations in their order
    (``sim.entry``)."""
    amax2 = accel_max * accel_max
    for i in range(vel_ned.shape[0]):
        a0 = -((-drag_k[0] * abs(vel_ned[i, 0])) * vel_ned[i, 0])
        a1 = -((-drag_k[1] * abs(vel_ned[i, 1])) * vel_ned[i, 1])
        a2 = -((-drag_k[2] * abs(vel_ned[i, 2])) * vel_ned[i, 2]) - g
        up = min(max(-a2, 0.0), accel_max)
        h_norm = math.hypot(a0, a1)
        h_max = min(up * tan_tilt, math.sqrt(max(amax2 - up * up, 0.0)))
        scale = h_max / h_norm if h_norm > h_max else 1.0
        thr_out[i, 0] = a0 * scale
        thr_out[i, 1] = a1 * scale
        thr_out[i, 2] = -up
