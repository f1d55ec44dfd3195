"""The state of agents entering a swarm: their deviation phase and trim thrust, each in one numba pass
when numba is installed (``sim.jit_kernels.deviation_phases`` and ``trim_thrust``, the same bits;
tests/sim/test_fast_paths.py).

The references are ``fisc_agent.map.kinetic.deviation_phase`` and ``sim.plant.model.trim_thrust_accel``:
a reservoir admits a handful of agents every few steps, and their dozen small numpy passes cost more
than the arithmetic.
"""

from __future__ import annotations

import numpy as np

from fisc_agent.map.kinetic import deviation_phase
from sim.kernels import jit_kernels
from sim.plant.model import trim_thrust_accel
from sim.plant.params import PlantCoefficients


def entry_phase(ids: np.ndarray) -> np.ndarray:
    """(k,) ``deviation_phase(ids)`` of agents ``ids`` (k,)."""
    jk = jit_kernels()
    if jk is None:
        return deviation_phase(ids)
    ids = np.ascontiguousarray(ids, dtype=np.int64).reshape(-1)
    out = np.empty(ids.size)
    jk.deviation_phases(ids, out)
    return out


def entry_thrust(vel_ned_m_s: np.ndarray, co: PlantCoefficients) -> np.ndarray:
    """(k, 3) ``trim_thrust_accel(vel_ned_m_s, co)``: the thrust holding NED velocities ``vel_ned_m_s``
    (k, 3) steady, for fleet-wide plant coefficients ``co`` (one row; per-agent rows: the numpy path)."""
    jk = jit_kernels()
    if jk is None or co.rows != 1:
        return trim_thrust_accel(vel_ned_m_s, co)
    vel = np.ascontiguousarray(vel_ned_m_s, dtype=np.float64)
    if vel.ndim != 2 or vel.shape[1] != 3:
        raise ValueError(f"vel_ned_m_s: expected shape (N, 3), got {vel.shape}")
    out = np.empty(vel.shape)
    jk.trim_thrust(vel, np.ascontiguousarray(co.drag_k[0], dtype=np.float64), float(co.g[0]),
                   float(co.accel_max[0]), float(co.tan_tilt[0]), out)
    return out
