"""The numba kernel of the ``kinetic`` command mode: look-ahead, staggered field, persistent deviation
and staircase-wall reflection for every agent in one pass (``sim.kernels.kinetic_commands_kernel``).

The reference is the numpy path the onboard agent flies, ``fisc_agent.map.lookup.flight_command``
(``CommandField.locate``, ``staggered_at`` and ``fisc_agent.map.kinetic.deviation_in_cells``): the
kernel spells the same operations per agent in the same order, so both give the same bits
(tests/sim/test_kinetic_kernel.py).  Imports numba: reach it only through ``sim.kernels``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from sim.jit_kernels import deviation_phases, slot_mix32, trim_thrust

_TWO_PI = 2.0 * np.pi
"""``2.0 * np.pi`` as ``_unit_from_hash`` folds it."""
_INV_2_32 = 1.0 / 4294967296.0
"""The hash's scale onto [0, 1)."""


@numba.njit(cache=True, nogil=True, inline="always")
def _deviate(dk, code, sgn, frac, v, zone0, brake_s, cell):
    """One axis of ``deviation_in_cells`` for the interval's drawn component ``dk``, the cell's wall
    ``code`` and the agent's position ``frac`` in it: (component, new sign).  Selects rather than
    branches where the outcome is a coin toss (the sign of ``dk``): mispredictions dominated."""
    stepped = (code >> (np.int64(dk >= 0.0) + 2)) & 1  # the face it was reflected from steps outward
    sgn = 1.0 if (sgn < 0.0) & (stepped == 1) else sgn
    dk = dk * sgn
    up = dk >= 0.0
    if ((code >> np.int64(up)) & 1) == 0:  # no wall ahead on this axis
        return dk, sgn
    vn = v if up else -v  # a vehicle heading for a face at v_n turns within v_n * brake_s
    vn = 0.0 if vn < 0.0 else vn
    zk = vn * brake_s / cell
    zone = zk if (zk > zone0) | (zk != zk) else zone0  # np.maximum: NaN propagates
    zone = zone if brake_s > 0.0 else zone0
    toward = (frac >= 1.0 - zone) if up else (frac < zone)
    return (-dk if toward else dk), (-sgn if toward else sgn)


@numba.njit(cache=True, nogil=True, inline="always")
def _component(lcv, t, lo, hi, spread, dk, to_ned):
    """One NED component of the command: staggered field at position ``t`` in the cell plus the deviation."""
    if lcv < 0:
        return 0.0
    if t < 0.0:  # clipped into [0, 1], NaN kept (as np.minimum(np.maximum(...)))
        t = 0.0
    elif t > 1.0:
        t = 1.0
    c = (1.0 - t) * lo + t * hi
    c += spread * dk
    if c != c:
        c = 0.0
    return c * to_ned


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _locate_all(n, pos, vel_ned, lead_s, origin, cell, hi, strides, offset, map_to_ned, frac, rows, vel_map):
    """``CommandField.locate`` of the first ``n`` agents' points (``frac[0:3]``, ``rows[0]``) and look-ahead
    points (``frac[3:6]``, ``rows[1]``, exact integers in floating point) and their map-frame velocities
    ``vel_map`` (3, n): one pass per axis over structure-of-arrays buffers, which the compiler
    vectorises (the division and floor dominate)."""
    for k in range(3):
        o, h, s, mk = origin[k], hi[k], strides[k], map_to_ned[k]
        for i in range(n):
            x = pos[i, k]
            v = vel_ned[i, k] * mk
            vel_map[k, i] = v
            f = (x - o) / cell
            c = np.floor(f)
            frac[k, i] = f - c
            c = c if c >= -1.0 else -1.0  # np.fmax(c, -1): NaN reads the lowest border cell
            c = c if c <= h else h
            g = (x + lead_s * v - o) / cell
            d = np.floor(g)
            frac[3 + k, i] = g - d
            d = d if d >= -1.0 else -1.0
            d = d if d <= h else h
            if k == 0:
                rows[0, i] = offset + c * s
                rows[1, i] = offset + d * s
            else:
                rows[0, i] += c * s
                rows[1, i] += d * s


@numba.njit(cache=True, nogil=True, error_model="numpy")
def kinetic_commands(pos, vel_ned, ids, cv, cv_given, t_over_p, lead_s, epoch, sign, direction, phase,
                     origin, cell, hi, strides, offset, padded_cv, lower, upper, codes, spread_xyz,
                     zone0, brake_s, map_to_ned, cmd_out):
    """NED kinetic commands of every agent and its new deviation state (``sim.kernels``)."""
    kinetic_rows(pos.shape[0], pos, vel_ned, ids, cv, cv_given, t_over_p, lead_s, epoch, sign, direction, phase,
                 origin, cell, hi, strides, offset, padded_cv, lower, upper, codes, spread_xyz, zone0, brake_s,
                 map_to_ned, cmd_out)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def kinetic_rows(n, pos, vel_ned, ids, cv, cv_given, t_over_p, lead_s, epoch, sign, direction, phase,
                 origin, cell, hi, strides, offset, padded_cv, lower, upper, codes, spread_xyz,
                 zone0, brake_s, map_to_ned, cmd_out):
    """``kinetic_commands`` of the first ``n`` rows of the arrays (the agents of a swarm's buffers)."""
    fr = np.empty((6, n))
    rw = np.empty((2, n))
    vv = np.empty((3, n))
    _locate_all(n, pos, vel_ned, lead_s, origin, cell, hi, strides, offset, map_to_ned, fr, rw, vv)
    m0, m1, m2 = map_to_ned[0], map_to_ned[1], map_to_ned[2]
    for i in range(n):
        f0, f1, f2 = fr[0, i], fr[1, i], fr[2, i]
        row = np.int64(rw[0, i])
        own = cv[i] if cv_given else padded_cv[row]
        lrow, lcv, g0, g1, g2 = row, own, f0, f1, f2
        if lead_s > 0.0:
            arow = np.int64(rw[1, i])
            acv = padded_cv[arow]
            if acv >= 0:  # else no CV ahead: the agent's own point
                lrow, lcv, g0, g1, g2 = arow, acv, fr[3, i], fr[4, i], fr[5, i]
        # deviation_in_cells: a fresh direction when the agent's interval changes
        e = np.int64(math.floor(t_over_p + phase[i]))
        if e != epoch[i]:
            u1 = slot_mix32(np.uint64(ids[i]), np.uint64(e)) * _INV_2_32
            u2 = slot_mix32(np.uint64(ids[i] ^ 0x5BD1E995), np.uint64(e)) * _INV_2_32
            z = 2.0 * u1 - 1.0
            phi = _TWO_PI * u2
            r = math.sqrt(max(0.0, 1.0 - z * z))
            direction[i, 0] = r * math.cos(phi)
            direction[i, 1] = r * math.sin(phi)
            direction[i, 2] = z
            sign[i, 0] = sign[i, 1] = sign[i, 2] = 1.0
            epoch[i] = e
        d0, sign[i, 0] = _deviate(direction[i, 0], codes[row, 0], sign[i, 0], f0, vv[0, i], zone0, brake_s, cell)
        d1, sign[i, 1] = _deviate(direction[i, 1], codes[row, 1], sign[i, 1], f1, vv[1, i], zone0, brake_s, cell)
        d2, sign[i, 2] = _deviate(direction[i, 2], codes[row, 2], sign[i, 2], f2, vv[2, i], zone0, brake_s, cell)
        # the staggered field at the look-up point plus the deviation at its CV's spread
        j = lcv if lcv > 0 else 0
        cmd_out[i, 0] = _component(lcv, g0, lower[lrow, 0], upper[lrow, 0], spread_xyz[j, 0], d0, m0)
        cmd_out[i, 1] = _component(lcv, g1, lower[lrow, 1], upper[lrow, 1], spread_xyz[j, 1], d1, m1)
        cmd_out[i, 2] = _component(lcv, g2, lower[lrow, 2], upper[lrow, 2], spread_xyz[j, 2], d2, m2)


@numba.njit(cache=True, nogil=True)
def deviation_x(ids, t_over_p, out):
    """``out[i]``: the x component of ``fisc_agent.map.kinetic.deviation_direction`` of agent ``ids[i]``
    at ``t_s / persistence_s = t_over_p`` (phase, interval and hash as there)."""
    for i in range(ids.shape[0]):
        phase = slot_mix32(np.uint64(ids[i]), np.uint64(0x2545F491)) * _INV_2_32
        e = np.int64(math.floor(t_over_p + phase))
        u1 = slot_mix32(np.uint64(ids[i]), np.uint64(e)) * _INV_2_32
        u2 = slot_mix32(np.uint64(ids[i] ^ 0x5BD1E995), np.uint64(e)) * _INV_2_32
        z = 2.0 * u1 - 1.0
        out[i] = math.sqrt(max(0.0, 1.0 - z * z)) * math.cos(_TWO_PI * u2)


@numba.njit(cache=True, nogil=True)
def admit_batch(inlet_cvs, counts, centers, cell, entry_x, interval_s, u, r, first_id, t_over_p, entry_u, spread,
                pos_out, ids_out):
    """One kinetic reservoir batch (``sim.scenarios.Reservoir.entering``): the candidates' positions (``_batch``)
    and their admission (``admit``: ``deviation_x``, ``kinetic_admission``, ``r < p``), the operations of
    the numpy path in its order; writes the admitted rows and returns how many."""
    idx = 0
    m = 0
    for q in range(inlet_cvs.shape[0]):
        j = inlet_cvs[q]
        depth = min(abs(entry_x[q]) * interval_s, cell)
        for _ in range(counts[q]):
            p0 = (centers[j, 0] - 0.5 * cell) + u[idx, 0] * depth
            p1 = (centers[j, 1] - 0.5 * cell) + u[idx, 1] * cell
            p2 = (centers[j, 2] - 0.5 * cell) + u[idx, 2] * cell
            agent = first_id + idx
            phase = slot_mix32(np.uint64(agent), np.uint64(0x2545F491)) * _INV_2_32
            e = np.int64(math.floor(t_over_p + phase))
            u1 = slot_mix32(np.uint64(agent), np.uint64(e)) * _INV_2_32
            u2 = slot_mix32(np.uint64(agent ^ 0x5BD1E995), np.uint64(e)) * _INV_2_32
            z = 2.0 * u1 - 1.0
            d_x = math.sqrt(max(0.0, 1.0 - z * z)) * math.cos(_TWO_PI * u2)
            ua = abs(entry_u[j])
            p = (ua + spread[j] * d_x) / max(ua + spread[j], 1e-12)
            p = min(max(p, 0.0), 1.0)
            if r[idx] < p:
                pos_out[m, 0] = p0
                pos_out[m, 1] = p1
                pos_out[m, 2] = p2
                ids_out[m] = agent
                m += 1
            idx += 1
    return m


@numba.njit(cache=True, nogil=True)
def enter_agents(new_pos, new_ids, t_over_p, origin, cell, hi, strides, offset, padded_cv, lower, upper, codes,
                 spread_xyz, zone0, brake_s, map_to_ned, drag_k, g, accel_max, tan_tilt, n, pos, vel, thr, ids, out_s,
                 epoch, sign, phase):
    """Write agents ``new_ids`` at ``new_pos`` (k, 3) into the swarm's rows ``n .. n + k`` (``Swarm.add_agents``
    of a kinetic swarm, its operations in their order): their deviation phase (``deviation_phases``), their
    start velocity (``kinetic_rows`` at rest, without look-ahead, from a fresh deviation state, through
    the map frame and back: ``sim.kinetic_step.KineticStep.start_velocity``), the trim thrust of it
    (``trim_thrust``, fleet-wide coefficients), time outside 0 and a fresh deviation state."""
    k = new_pos.shape[0]
    ph = np.empty(k)
    deviation_phases(new_ids, ph)
    cmd = np.empty((k, 3))
    no_cv = k < 0  # False, typed bool: a literal False would compile kinetic_rows once more
    kinetic_rows(k, new_pos, np.zeros((k, 3)), new_ids, np.empty(0, dtype=np.int64), no_cv, t_over_p, 0.0,
                 np.full(k, -1, dtype=np.int64), np.ones((k, 3)), np.zeros((k, 3)), ph, origin, cell, hi, strides,
                 offset, padded_cv, lower, upper, codes, spread_xyz, zone0, brake_s, map_to_ned, cmd)
    v = np.empty((k, 3))
    for i in range(k):
        for c in range(3):
            v[i, c] = (cmd[i, c] * map_to_ned[c]) * map_to_ned[c]
    a = np.empty((k, 3))
    trim_thrust(v, drag_k, g, accel_max, tan_tilt, a)  # contiguous (k, 3): the specialisation sim.entry calls
    for i in range(k):
        r = n + i
        for c in range(3):
            pos[r, c] = new_pos[i, c]
            vel[r, c] = v[i, c]
            thr[r, c] = a[i, c]
            sign[r, c] = 1.0
        ids[r] = new_ids[i]
        out_s[r] = 0.0
        epoch[r] = -1
        phase[r] = ph[i]
