"""The plant step kernels: the numpy reference and the one compiled (numba) kernel.

Both advance (v, a_T) in place by ``nsub`` semi-implicit Euler sub-steps of ``h`` (the sub-step
of :func:`sim.plant.model.step_plant`).  :func:`step_numpy` is the reference the tests hold the compiled
kernel to (``tests/sim/test_plant.py``: both against the scalar oracle
:func:`sim.plant.model.step_single_agent` and against each other); :func:`numba_kernel` is the same
arithmetic in the same order, compiled, for any mix of fleet-wide or per-agent coefficients,
wind, wind feed-forward and feedback noise.

The compiled kernel works on blocks of ``BLOCK`` agents: a block's state, its inputs and its
coefficient rows are copied into small (B,) arrays that stay in L1 while the sub-steps loop over
them, and the innermost loop runs over the block's agents, branch-free, so that the compiler
vectorises across agents instead of following one agent's dependency chain.
"""

from __future__ import annotations

import functools
import logging
import math
from typing import Callable

import numpy as np

from sim.plant.params import PlantCoefficients

__all__ = ["BLOCK", "kernel_args", "numba_available", "numba_kernel", "step_numpy"]

_log = logging.getLogger(__name__)

BLOCK = 256
"""Agents per block of the compiled kernel."""


def step_numpy(v, a, cmd, wind, wind_ff, noise, co: PlantCoefficients, h: float, nsub: int) -> None:
    """In-place numpy sub-stepping of (v, a): the tested reference of the plant step.

    ``cmd`` (1, 3) or (N, 3); ``wind``/``wind_ff``/``noise`` None or (1, 3)/(N, 3); ``co`` one
    shared row or N rows; ``h`` the sub-step [s], ``nsub`` the number of sub-steps."""
    kd = co.drag_k
    g = co.g
    # Constant over the step (zero-order hold): feed-forward + gravity bias and shaping reference.
    air_c = cmd if wind_ff is None else cmd - wind_ff
    bias = (np.abs(air_c) * air_c) * (co.ff_gain[:, None] * kd)  # (1, 3) command with per-agent rows: (N, 3)
    bias = np.broadcast_to(bias, v.shape).copy()
    bias[:, 2] -= g
    ref = cmd if noise is None else cmd - noise
    itv = co.inv_tau_v[:, None]
    beta = (h / (co.tau_thrust_s + h))[:, None]
    amax = co.accel_max
    amax2 = amax * amax
    tan2 = co.tan_tilt * co.tan_tilt
    d = np.empty_like(v)
    x = np.empty_like(v)
    for _ in range(nsub):
        # desired thrust acceleration and actuation limits (in place in d)
        np.subtract(ref, v, out=d)
        d *= itv
        d += bias
        up = np.clip(-d[:, 2], 0.0, amax)
        up2 = up * up
        hn2 = d[:, 0] * d[:, 0]
        hn2 += d[:, 1] * d[:, 1]
        hmax2 = np.minimum(up2 * tan2, np.maximum(amax2 - up2, 0.0))
        over = hn2 > hmax2
        if over.any():
            scale = np.sqrt(np.divide(hmax2, hn2, out=np.ones_like(hn2), where=over))
            d[:, 0] *= scale
            d[:, 1] *= scale
        np.negative(up, out=d[:, 2])
        # thrust lag (backward Euler): a += beta (a_c - a)
        d -= a
        d *= beta
        a += d
        # velocity with the new thrust and the drag at the old velocity
        if wind is None:
            np.abs(v, out=x)
            x *= v
        else:
            np.subtract(v, wind, out=d)
            np.abs(d, out=x)
            x *= d
        x *= kd
        np.subtract(a, x, out=x)
        x[:, 2] += g
        x *= h
        v += x


def kernel_args(co: PlantCoefficients, h: float) -> tuple[np.ndarray | None, np.ndarray]:
    """The coefficient arguments ``(rows, shared)`` of :func:`numba_kernel` for sub-step ``h`` [s].

    One row per agent is ``[1/tau_v, beta = h / (tau_T + h), g, drag_k (3), k_ff, T_max/m,
    tan(theta_max)]``: ``rows`` (N, 9) with per-agent coefficients, else None and ``shared`` (9,)."""
    table = np.empty((co.rows, 9))
    table[:, 0] = co.inv_tau_v
    table[:, 1] = h / (co.tau_thrust_s + h)
    table[:, 2] = co.g
    table[:, 3:6] = co.drag_k
    table[:, 6] = co.ff_gain
    table[:, 7] = co.accel_max
    table[:, 8] = co.tan_tilt
    return (None, table[0].copy()) if co.rows == 1 else (table, table[0].copy())


@functools.lru_cache(maxsize=1)
def numba_kernel() -> Callable | None:
    """The compiled plant step, compiled on first use (cached on disk); None without numba.

    ``kernel(v, a, cmd, wind, wind_ff, noise, *kernel_args(co, h), h, nsub)`` with ``v``, ``a``
    (N, 3) stepped in place, ``cmd`` (1, 3) or (N, 3) and ``wind``, ``wind_ff``, ``noise`` (1, 3),
    (N, 3) or None.  numba compiles one specialisation per combination of None arguments and
    prunes the branches of what is None, so the fleet-wide case without wind or noise (the swarm
    simulator's) reads its coefficients as scalars: one source, no hand-written variants."""
    try:
        import numba
    except ImportError:
        _log.info("numba not available; the plant uses its numpy path")
        return None

    @numba.njit(cache=True, nogil=True, error_model="numpy")
    def kernel(v, a, cmd, wind, wind_ff, noise, rows, shared, h, nsub):
        n = v.shape[0]
        bs = BLOCK
        bc = cmd.shape[0] > 1
        s_itv, s_beta, s_g, s_k0, s_k1, s_k2 = shared[0], shared[1], shared[2], shared[3], shared[4], shared[5]
        s_ff, s_am, s_tt = shared[6], shared[7], shared[8]
        r0, r1, r2 = np.empty(bs), np.empty(bs), np.empty(bs)  # shaping reference v_cmd - noise
        b0, b1, b2 = np.empty(bs), np.empty(bs), np.empty(bs)  # drag feed-forward and gravity bias
        v0, v1, v2 = np.empty(bs), np.empty(bs), np.empty(bs)
        a0, a1, a2 = np.empty(bs), np.empty(bs), np.empty(bs)
        w0, w1, w2 = np.empty(bs), np.empty(bs), np.empty(bs)
        k0, k1, k2 = np.empty(bs), np.empty(bs), np.empty(bs)
        ci, cb, cg = np.empty(bs), np.empty(bs), np.empty(bs)
        cm, cm2, ct2 = np.empty(bs), np.empty(bs), np.empty(bs)
        for start in range(0, n, bs):
            m = min(bs, n - start)
            for j in range(m):
                i = start + j
                ic = i if bc else 0
                if rows is None:
                    q0, q1, q2, ff, g = s_k0, s_k1, s_k2, s_ff, s_g
                else:
                    q0, q1, q2, ff, g = rows[i, 3], rows[i, 4], rows[i, 5], rows[i, 6], rows[i, 2]
                    k0[j], k1[j], k2[j] = q0, q1, q2
                    ci[j], cb[j], cg[j] = rows[i, 0], rows[i, 1], g
                    cm[j], cm2[j], ct2[j] = rows[i, 7], rows[i, 7] * rows[i, 7], rows[i, 8] * rows[i, 8]
                c0, c1, c2 = cmd[ic, 0], cmd[ic, 1], cmd[ic, 2]
                x0, x1, x2 = c0, c1, c2
                if wind_ff is not None:
                    jf = i if wind_ff.shape[0] > 1 else 0
                    x0, x1, x2 = c0 - wind_ff[jf, 0], c1 - wind_ff[jf, 1], c2 - wind_ff[jf, 2]
                b0[j] = abs(x0) * x0 * (ff * q0)
                b1[j] = abs(x1) * x1 * (ff * q1)
                b2[j] = abs(x2) * x2 * (ff * q2) - g
                r0[j], r1[j], r2[j] = c0, c1, c2
                if noise is not None:
                    jn = i if noise.shape[0] > 1 else 0
                    r0[j], r1[j], r2[j] = c0 - noise[jn, 0], c1 - noise[jn, 1], c2 - noise[jn, 2]
                if wind is not None:
                    iw = i if wind.shape[0] > 1 else 0
                    w0[j], w1[j], w2[j] = wind[iw, 0], wind[iw, 1], wind[iw, 2]
                v0[j], v1[j], v2[j] = v[i, 0], v[i, 1], v[i, 2]
                a0[j], a1[j], a2[j] = a[i, 0], a[i, 1], a[i, 2]
            for _ in range(nsub):
                for j in range(m):
                    if rows is None:
                        itv, beta, g, am, am2, tt2 = s_itv, s_beta, s_g, s_am, s_am * s_am, s_tt * s_tt
                        q0, q1, q2 = s_k0, s_k1, s_k2
                    else:
                        itv, beta, g, am, am2, tt2 = ci[j], cb[j], cg[j], cm[j], cm2[j], ct2[j]
                        q0, q1, q2 = k0[j], k1[j], k2[j]
                    x0, x1, x2 = v0[j], v1[j], v2[j]
                    d0 = (r0[j] - x0) * itv + b0[j]
                    d1 = (r1[j] - x1) * itv + b1[j]
                    d2 = (r2[j] - x2) * itv + b2[j]
                    up = min(max(-d2, 0.0), am)
                    hn2 = d0 * d0 + d1 * d1
                    hmax2 = min(up * up * tt2, max(am2 - up * up, 0.0))
                    s = math.sqrt(hmax2 / hn2) if hn2 > hmax2 else 1.0
                    y0 = a0[j] + (d0 * s - a0[j]) * beta
                    y1 = a1[j] + (d1 * s - a1[j]) * beta
                    y2 = a2[j] + (-up - a2[j]) * beta
                    a0[j], a1[j], a2[j] = y0, y1, y2
                    e0, e1, e2 = x0, x1, x2
                    if wind is not None:
                        e0, e1, e2 = x0 - w0[j], x1 - w1[j], x2 - w2[j]
                    v0[j] = x0 + (y0 - abs(e0) * e0 * q0) * h
                    v1[j] = x1 + (y1 - abs(e1) * e1 * q1) * h
                    v2[j] = x2 + (y2 - abs(e2) * e2 * q2 + g) * h
            for j in range(m):
                i = start + j
                v[i, 0], v[i, 1], v[i, 2] = v0[j], v1[j], v2[j]
                a[i, 0], a[i, 1], a[i, 2] = a0[j], a1[j], a2[j]

    return kernel


def numba_available() -> bool:
    """True when the optional numba kernel can be used."""
    return numba_kernel() is not None
