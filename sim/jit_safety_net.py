"""The numba twin of ``fisc_agent.flight.safety_net.keep_apart_pairs`` (the same operations per pair, in
a few loops instead of a dozen numpy passes over the ~10^5 candidate pairs of a dense swarm).

Imports numba: reach it only through ``sim.safety_net.pairs_kernel``, which returns None when numba
is not installed (the ``fisc[jit]`` extra); tests/sim/test_safety_net_sim.py checks it equal to
``keep_apart_pairs``.
"""

from __future__ import annotations

import math

import numba
import numpy as np


_INSERTION_MAX = 24
"""A vehicle's broken limits are sorted by insertion up to this many, by two stable sorts beyond."""


@numba.njit(cache=True, nogil=True, error_model="numpy")
def keep_apart_pairs(pos, vel, cmd, ids, pairs, d_min_m, horizon_s, pass_margin_m, push_gain_1_s, max_push_m_s,
                     coincident_m, limit_tol_m_s, duct, out):
    """``out`` (n, 3) = ``cmd`` after the net for index pairs ``pairs`` (m, 2), every report fresh
    (``fisc_agent.flight.safety_net.keep_apart_pairs``; all arrays float64 but ``ids``, ``pairs`` int64).
    ``horizon_s``: the effective horizon; ``duct``: (x_lo, x_hi, y_axis, z_axis) of the wall rule
    (an empty x range: none)."""
    n = cmd.shape[0]
    m2 = 2 * pairs.shape[0]
    push = np.zeros((n, 3))
    # per directed pair (vehicle ``me`` hears ``nb``): the closing limits that apply, kept in order
    lim_me = np.empty(m2, dtype=np.int64)
    lim_id = np.empty(m2, dtype=np.int64)
    lim_unit = np.empty((m2, 3))
    lim_allowed = np.empty(m2)
    lim_gap = np.empty(m2)
    lim_breaks = np.empty(m2, dtype=np.bool_)
    n_lim = 0
    nv = np.zeros(3)
    for p in range(pairs.shape[0]):
        for side in range(2):
            me = pairs[p, side]
            nb = pairs[p, 1 - side]
            d2 = 0.0
            for k in range(3):
                nv[k] = pos[me, k] - pos[nb, k]
                d2 += nv[k] * nv[k]
            dist = math.sqrt(d2)
            if dist > coincident_m:
                for k in range(3):
                    nv[k] /= dist
            else:
                nv[0] = 1.0 if ids[me] < ids[nb] else -1.0
                nv[1] = 0.0
                nv[2] = 0.0
            away = -(vel[nb, 0] * nv[0] + vel[nb, 1] * nv[1] + vel[nb, 2] * nv[2])
            gap = dist - d_min_m
            if horizon_s > 0:
                allowed = max(0.0, away + max(0.0, gap) / horizon_s)
            elif gap >= 0:
                allowed = math.inf
            else:
                allowed = max(0.0, away)
            depth = push_gain_1_s * max(0.0, -gap)
            for k in range(3):
                push[me, k] += depth * nv[k]
            # passing, not closing: the straight-line closest approach within the horizon
            ww = 0.0
            rw = 0.0
            for k in range(3):
                w = cmd[me, k] - vel[nb, k]
                ww += w * w
                rw += (pos[me, k] - pos[nb, k]) * w
            t = min(max(-rw / ww, 0.0), horizon_s) if ww > 0.0 else 0.0
            c2 = 0.0
            for k in range(3):
                c = pos[me, k] - pos[nb, k] + (cmd[me, k] - vel[nb, k]) * t
                c2 += c * c
            if math.sqrt(c2) < d_min_m + pass_margin_m:
                closing = -(cmd[me, 0] * nv[0] + cmd[me, 1] * nv[1] + cmd[me, 2] * nv[2])
                lim_breaks[n_lim] = closing > allowed
                lim_me[n_lim] = me
                lim_id[n_lim] = ids[nb]
                lim_gap[n_lim] = gap
                lim_allowed[n_lim] = allowed
                for k in range(3):
                    lim_unit[n_lim, k] = nv[k]
                n_lim += 1
    for i in range(n):
        for k in range(3):
            out[i, k] = cmd[i, k]  # the command as the cuts leave it
    # the limits the command breaks, one at a time per vehicle, nearest gap first (ties by id): bucketed by
    # vehicle, then each vehicle's sorted
    start = np.zeros(n + 1, dtype=np.int64)
    for j in range(n_lim):
        if lim_breaks[j]:
            start[lim_me[j] + 1] += 1
    for i in range(n):
        start[i + 1] += start[i]
    fill = start[:n].copy()
    seq = np.empty(start[n], dtype=np.int64)
    for j in range(n_lim):
        if lim_breaks[j]:
            seq[fill[lim_me[j]]] = j
            fill[lim_me[j]] += 1
    for i in range(n):
        mine = seq[start[i]:start[i + 1]]  # a view: sorted in place by (gap, id)
        if mine.size > _INSERTION_MAX:  # a jam: two stable sorts
            mine = mine[np.argsort(lim_id[mine], kind="mergesort")]
            mine = mine[np.argsort(lim_gap[mine], kind="mergesort")]
        else:  # a few: by insertion
            for a in range(1, mine.size):
                j = mine[a]
                b = a - 1
                while b >= 0 and (lim_gap[mine[b]] > lim_gap[j]
                                  or (lim_gap[mine[b]] == lim_gap[j] and lim_id[mine[b]] > lim_id[j])):
                    mine[b + 1] = mine[b]
                    b -= 1
                mine[b + 1] = j
        for j in mine:
            excess = -(out[i, 0] * lim_unit[j, 0] + out[i, 1] * lim_unit[j, 1] + out[i, 2] * lim_unit[j, 2]) \
                - lim_allowed[j]
            if excess > 0.0:
                for k in range(3):
                    out[i, k] += excess * lim_unit[j, k]
    for i in range(n):  # no component against the command
        vv = cmd[i, 0] ** 2 + cmd[i, 1] ** 2 + cmd[i, 2] ** 2
        back = min(0.0, out[i, 0] * cmd[i, 0] + out[i, 1] * cmd[i, 1] + out[i, 2] * cmd[i, 2]) / (vv if vv > 0.0 else 1.0)
        for k in range(3):
            out[i, k] -= back * cmd[i, k]
    scale = np.ones(n)
    for j in range(n_lim):
        me = lim_me[j]
        closing = -(out[me, 0] * lim_unit[j, 0] + out[me, 1] * lim_unit[j, 1] + out[me, 2] * lim_unit[j, 2])
        if closing > lim_allowed[j] + limit_tol_m_s:
            scale[me] = min(scale[me], lim_allowed[j] / closing)
    for i in range(n):
        norm = math.sqrt(push[i, 0] ** 2 + push[i, 1] ** 2 + push[i, 2] ** 2)
        f = min(1.0, max_push_m_s / max(norm, 1e-300))
        for k in range(3):
            out[i, k] = (out[i, k] * scale[i] - cmd[i, k]) + push[i, k] * f  # the correction
        # the wall rule: over the duct, no component away from its axis
        ry = pos[i, 1] - duct[2]
        rz = pos[i, 2] - duct[3]
        r = math.sqrt(ry * ry + rz * rz)
        if duct[0] <= pos[i, 0] <= duct[1] and r > coincident_m:
            outward = max(0.0, (out[i, 1] * ry + out[i, 2] * rz) / r)
            out[i, 1] -= outward * ry / r
            out[i, 2] -= outward * rz / r
        for k in range(3):
            out[i, k] += cmd[i, k]
