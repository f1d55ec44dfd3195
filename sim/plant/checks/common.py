"""Shared machinery of the plant checks: the sample period, batch simulation, settling times, the linear model."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.plant.model import Backend, PlantParams, VelocityPlant


DT_S = 0.01
"""Control/sample period of the checks [s] (100 Hz)."""


@dataclass(frozen=True)
class Run:
    """Time histories of a simulated batch of agents."""

    t_s: np.ndarray
    """(T+1,) sample times [s], t[0] = 0 the initial state."""
    vel_ned_m_s: np.ndarray
    """(T+1, N, 3) velocity."""
    thrust_accel_ned_m_s2: np.ndarray
    """(T+1, N, 3) realised thrust acceleration."""
    cmd_ned_m_s: np.ndarray
    """(T, N, 3) command held over each interval [t_k, t_k+1)."""


def simulate(
    params: PlantParams,
    cmd_ned_m_s: np.ndarray,
    dt_s: float = DT_S,
    wind_ned_m_s: np.ndarray | None = None,
    wind_ff_ned_m_s: np.ndarray | None = None,
    feedback_noise_ned_m_s: np.ndarray | None = None,
    velocity0_ned_m_s: np.ndarray | None = None,
    thrust0_ned_m_s2: np.ndarray | None = None,
    backend: Backend = "auto",
    process_noise_ned_m_s: np.ndarray | None = None,
) -> Run:
    """Run agents from hover (or the given state) under ``cmd`` of shape (T, N, 3).

    ``feedback_noise`` (T, N, 3): velocity measurement error held over each interval;
    ``process_noise`` (T, N, 3): velocity disturbance added to the state after each interval;
    wind and wind_ff are constant."""
    cmd = np.asarray(cmd_ned_m_s, dtype=np.float64)
    if cmd.ndim != 3 or cmd.shape[2] != 3:
        raise ValueError(f"cmd_ned_m_s: expected (T, N, 3), got {cmd.shape}")
    n_t, n = cmd.shape[:2]
    plant = VelocityPlant(params, n, velocity0_ned_m_s, thrust0_ned_m_s2, backend=backend)
    vel = np.empty((n_t + 1, n, 3))
    thr = np.empty((n_t + 1, n, 3))
    vel[0], thr[0] = plant.velocity, plant.thrust_accel
    for k in range(n_t):
        noise = None if feedback_noise_ned_m_s is None else feedback_noise_ned_m_s[k]
        plant.step(cmd[k], dt_s, wind_ned_m_s, wind_ff_ned_m_s, noise)
        if process_noise_ned_m_s is not None:
            plant.velocity[...] += process_noise_ned_m_s[k]
        vel[k + 1], thr[k + 1] = plant.velocity, plant.thrust_accel
    return Run(np.arange(n_t + 1) * dt_s, vel, thr, cmd)


def settling_time_s(t_s: np.ndarray, y: np.ndarray, target: float, step: float, band: float = 0.02) -> float:
    """Time after which ``|y - target| <= band * |step|`` for good (linear interpolation at the
    last crossing); NaN if the signal ends outside the band."""
    err = np.abs(np.asarray(y) - target) - band * abs(step)
    outside = np.nonzero(err > 0)[0]
    if outside.size == 0:
        return 0.0
    k = outside[-1]
    if k == len(t_s) - 1:
        return math.nan
    frac = err[k] / (err[k] - err[k + 1])
    return float(t_s[k] + frac * (t_s[k + 1] - t_s[k]))


def second_order_settling_time_s(params: PlantParams = PlantParams(), band: float = 0.02) -> float:
    """2 % settling time of the linearised closed loop ``1 / (tau_T tau_v s^2 + tau_v s + 1)``
    (drag and limits ignored): the analytic value the paper's 1.67 s corresponds to."""
    tv, tt = float(params.tau_v_s), float(params.tau_thrust_s)
    disc = 1.0 - 4.0 * tt / tv
    if disc <= 0:
        raise ValueError("second_order_settling_time_s: loop is under-damped for these parameters")
    p1 = (1.0 - math.sqrt(disc)) / (2.0 * tt)  # slow pole |s|
    p2 = (1.0 + math.sqrt(disc)) / (2.0 * tt)
    # step response 1 - p2/(p2-p1) e^{-p1 t} + p1/(p2-p1) e^{-p2 t}; solve by bisection
    f = lambda t: abs(-p2 / (p2 - p1) * math.exp(-p1 * t) + p1 / (p2 - p1) * math.exp(-p2 * t)) - band
    lo, hi = 0.0, 50.0 / p1
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(mid) > 0 else (lo, mid)
    return hi


def closed_loop_response(params: PlantParams, freq_hz: np.ndarray) -> np.ndarray:
    """Complex linearised command-to-velocity response ``1 / (tau_T tau_v s^2 + tau_v s + 1)``."""
    s = 2j * np.pi * np.asarray(freq_hz, dtype=np.float64)
    tv, tt = float(params.tau_v_s), float(params.tau_thrust_s)
    return 1.0 / (tt * tv * s * s + tv * s + 1.0)
