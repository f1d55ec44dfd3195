"""The fused numba kernel of the swarm step: CV lookup, command, removal flags, return policy, plant
sub-steps and position update in ONE pass over the agents (``sim.fused_step`` is its glue).

The passes of ``sim.jit_kernels`` (``fused_lookup``, ``removal``, ``return_commands``, ``move``) and the
plant kernel (``sim.plant.kernel.numba_kernel``, fleet-wide coefficients, no wind, no noise) are the
reference: every number here comes from the same operations in the same order, so the trajectories are
the same bit for bit (tests/sim/test_fused_step.py).  Agents work in blocks of ``BLOCK`` as the plant
kernel does: the block's state is copied into small arrays that stay in L1 while the sub-steps loop
over them, so the inner loop vectorises across agents.

Agents flagged for removal are stepped too (their rows are junk afterwards): the kernel then compacts the
rows with ``keep`` (``sim.jit_kernels.compact``), which leaves the survivors exactly as the
reference's removal-then-step does, since no agent's step depends on another's.

Imports numba: reach it through ``sim.fused_step.FusedStep.make`` (None without numba).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from sim.jit_kernels import compact, padded_cell, slot_of
from sim.kinetic_jit import kinetic_rows
from sim.plant.kernel import BLOCK


@numba.njit(cache=True, nogil=True, error_model="numpy")
def fused_step(pos, vel, thr, ids, out_s, cmd, cv, keep, assigned, origin, inv_l, hi, strides, flat, near_flat,
               centers, mean_speed, mean_ned, slot_ned, n_star, slot_mode, x_outlet_m, grace_s, dt_s, gain, frac,
               map_to_ned, shared, h, nsub, fdt, kin, t_s, persistence_s, lead_s, epoch, sign, direction, phase,
               k_origin, k_cell, k_hi, k_strides, k_offset, padded_cv, lower, upper, codes, spread_xyz, zone0, brake_s,
               n_steps):
    """``n_steps`` swarm steps of every agent in place, from time ``t_s``; returns the sums over the steps of
    the agents exited, escaped, outside and stepped (alive after each step's removals), and the agents left.

    Each step: ``assigned`` False (or a step after the first): look up each agent's CV and its mean/slot
    command (held in the block, ``cv`` and ``cmd`` neither read nor written) and apply the outlet/escape
    removal rule (``keep`` out; removed agents are not counted outside).  ``assigned`` True (the first step
    only): ``cv`` and ``cmd`` are given (the removals done), every agent is kept, ``cmd`` is read only.
    Then for each kept agent outside the CVs the return-policy command and its time outside, then the
    plant sub-steps and ``pos += vel * fdt``; last the removed agents' rows are dropped (the rows of
    ``Swarm._keep``: the survivors in the first ``n_kept``).

    Between steps the time advances as ``Swarm.t_s`` does (``t + dt_s``).

    ``kin``: the commands are the ``kinetic`` mode's, ``sim.kinetic_jit.kinetic_commands`` of every agent
    with its CV given (at t / ``persistence_s`` and look-ahead ``lead_s``; the deviation state
    ``epoch``, ``sign``, ``direction`` updated in place, the ``k_*`` and following arguments its tables)
    written into ``cmd`` first; with ``assigned`` False the CVs are looked up into ``cv`` before (0 for the
    agents removed, which fly junk).  (Flags handed on to other kernels are variables, never literals: numba
    compiles a kernel anew for each literal.)"""
    n = pos.shape[0]
    bs = BLOCK
    s_itv, s_beta, s_g, s_k0, s_k1, s_k2 = shared[0], shared[1], shared[2], shared[3], shared[4], shared[5]
    s_ff, s_am, s_tt = shared[6], shared[7], shared[8]
    zero_row = mean_ned.shape[0] - 1
    r0, r1, r2 = np.empty(bs), np.empty(bs), np.empty(bs)
    b0, b1, b2 = np.empty(bs), np.empty(bs), np.empty(bs)
    v0, v1, v2 = np.empty(bs), np.empty(bs), np.empty(bs)
    a0, a1, a2 = np.empty(bs), np.empty(bs), np.empty(bs)
    e0, e1, eu = np.empty(bs), np.empty(bs), np.empty(bs)  # a sub-step's desired thrust (horizontal, up)
    hn, hm, hs = np.empty(bs), np.empty(bs), np.empty(bs)  # its horizontal norm^2, limit^2, scale
    jv = np.empty(bs, dtype=np.int64)  # the block's CVs (0 for agents removed: they are stepped as junk)
    tot_exit = 0
    tot_esc = 0
    tot_out = 0
    agent_steps = 0
    t = t_s
    for step in range(n_steps):
        given = assigned and step == 0
        n_exit = 0
        n_esc = 0
        n_out = 0
        if kin:
            if not given:  # sim.jit_kernels.fused_lookup and removal, the CVs into cv (0: removed, as below)
                for i in range(n):
                    c = padded_cell(pos, i, origin, inv_l, hi, strides)
                    j = flat[c]
                    if pos[i, 0] >= x_outlet_m:
                        n_exit += 1
                        keep[i] = False
                        j = 0
                    elif j < 0 and (out_s[i] > grace_s or near_flat[c] < 0):
                        n_esc += 1
                        keep[i] = False
                        j = 0
                    else:
                        keep[i] = True
                    cv[i] = j
            kinetic_rows(n, pos, vel, ids, cv, kin, t / persistence_s, lead_s, epoch, sign, direction, phase, k_origin,
                         k_cell, k_hi, k_strides, k_offset, padded_cv, lower, upper, codes, spread_xyz, zone0, brake_s,
                         map_to_ned, cmd)
        for start in range(0, n, bs):
            m = min(bs, n - start)
            if given or kin:
                for jb in range(m):
                    i = start + jb
                    jv[jb] = cv[i]
                    r0[jb], r1[jb], r2[jb] = cmd[i, 0], cmd[i, 1], cmd[i, 2]
            else:
                for jb in range(m):  # sim.jit_kernels.fused_lookup
                    i = start + jb
                    j = flat[padded_cell(pos, i, origin, inv_l, hi, strides)]
                    jv[jb] = j
                    if slot_mode and j >= 0:
                        kk = slot_of(ids[i], j, n_star[j])
                        r0[jb], r1[jb], r2[jb] = slot_ned[j, kk, 0], slot_ned[j, kk, 1], slot_ned[j, kk, 2]
                    else:
                        rr = j if j >= 0 else zero_row
                        r0[jb], r1[jb], r2[jb] = mean_ned[rr, 0], mean_ned[rr, 1], mean_ned[rr, 2]
                for jb in range(m):  # sim.jit_kernels.removal
                    i = start + jb
                    if pos[i, 0] >= x_outlet_m:
                        n_exit += 1
                        keep[i] = False
                        jv[jb] = 0  # not flown back, not counted outside
                    elif jv[jb] < 0 and (out_s[i] > grace_s
                                         or near_flat[padded_cell(pos, i, origin, inv_l, hi, strides)] < 0):
                        n_esc += 1
                        keep[i] = False
                        jv[jb] = 0
                    else:
                        keep[i] = True
            for jb in range(m):  # sim.jit_kernels.return_commands (kept agents)
                i = start + jb
                if jv[jb] >= 0:
                    out_s[i] = 0.0
                    continue
                n_out += 1
                out_s[i] += dt_s
                q = near_flat[padded_cell(pos, i, origin, inv_l, hi, strides)]
                if q < 0:
                    q = 0
                q0 = gain * (centers[q, 0] - pos[i, 0])
                q1 = gain * (centers[q, 1] - pos[i, 1])
                q2 = gain * (centers[q, 2] - pos[i, 2])
                mag = math.sqrt((q0 * q0 + q2 * q2) + q1 * q1)
                s = min(1.0, frac * mean_speed[q] / max(mag, 1e-12))
                q0 *= s
                q1 *= s
                q2 *= s
                if slot_mode:
                    kk = slot_of(ids[i], q, n_star[q])
                    r0[jb] = slot_ned[q, kk, 0] + q0 * map_to_ned[0]
                    r1[jb] = slot_ned[q, kk, 1] + q1 * map_to_ned[1]
                    r2[jb] = slot_ned[q, kk, 2] + q2 * map_to_ned[2]
                else:
                    r0[jb] = mean_ned[q, 0] + q0 * map_to_ned[0]
                    r1[jb] = mean_ned[q, 1] + q1 * map_to_ned[1]
                    r2[jb] = mean_ned[q, 2] + q2 * map_to_ned[2]
            for jb in range(m):  # sim.plant.kernel.numba_kernel: fleet-wide coefficients, no wind, no noise
                i = start + jb
                c0, c1, c2 = r0[jb], r1[jb], r2[jb]
                b0[jb] = abs(c0) * c0 * (s_ff * s_k0)
                b1[jb] = abs(c1) * c1 * (s_ff * s_k1)
                b2[jb] = abs(c2) * c2 * (s_ff * s_k2) - s_g
                v0[jb], v1[jb], v2[jb] = vel[i, 0], vel[i, 1], vel[i, 2]
                a0[jb], a1[jb], a2[jb] = thr[i, 0], thr[i, 1], thr[i, 2]
            itv, beta, g, am, am2, tt2 = s_itv, s_beta, s_g, s_am, s_am * s_am, s_tt * s_tt
            for _ in range(nsub):
                # the thrust limit acts on few agents: the block skips its square root and division when it
                # acts on none (s = 1 exactly, as the reference's ``s = 1.0`` branch, so the same bits)
                n_over = 0
                for jb in range(m):
                    x0, x1 = v0[jb], v1[jb]
                    d0 = (r0[jb] - x0) * itv + b0[jb]
                    d1 = (r1[jb] - x1) * itv + b1[jb]
                    d2 = (r2[jb] - v2[jb]) * itv + b2[jb]
                    up = min(max(-d2, 0.0), am)
                    hn2 = d0 * d0 + d1 * d1
                    hmax2 = min(up * up * tt2, max(am2 - up * up, 0.0))
                    e0[jb], e1[jb], eu[jb] = d0, d1, up
                    hn[jb], hm[jb] = hn2, hmax2
                    n_over += hn2 > hmax2
                if n_over:
                    for jb in range(m):
                        hs[jb] = math.sqrt(hm[jb] / hn[jb]) if hn[jb] > hm[jb] else 1.0
                    for jb in range(m):
                        e0[jb] *= hs[jb]
                        e1[jb] *= hs[jb]
                for jb in range(m):
                    x0, x1, x2 = v0[jb], v1[jb], v2[jb]
                    y0 = a0[jb] + (e0[jb] - a0[jb]) * beta
                    y1 = a1[jb] + (e1[jb] - a1[jb]) * beta
                    y2 = a2[jb] + (-eu[jb] - a2[jb]) * beta
                    a0[jb], a1[jb], a2[jb] = y0, y1, y2
                    v0[jb] = x0 + (y0 - abs(x0) * x0 * s_k0) * h
                    v1[jb] = x1 + (y1 - abs(x1) * x1 * s_k1) * h
                    v2[jb] = x2 + (y2 - abs(x2) * x2 * s_k2 + g) * h
            for jb in range(m):
                i = start + jb
                vel[i, 0], vel[i, 1], vel[i, 2] = v0[jb], v1[jb], v2[jb]
                thr[i, 0], thr[i, 1], thr[i, 2] = a0[jb], a1[jb], a2[jb]
            for i in range(start, start + m):  # sim.jit_kernels.move (a loop of its own: it vectorises)
                for k in range(3):
                    pos[i, k] += vel[i, k] * fdt[k]
        if n_exit + n_esc:  # sim.jit_kernels.compact: the rows of Swarm._keep
            n = compact(keep[:n], (pos, vel, thr, sign, direction, cmd), (out_s, phase), (ids, epoch, cv))
        tot_exit += n_exit
        tot_esc += n_esc
        tot_out += n_out
        agent_steps += n
        t = t + dt_s  # Swarm.t_s's sum
    return tot_exit, tot_esc, tot_out, agent_steps, n
