"""The error of an autopilot's state estimate, as the emulated vehicle reports it (pure).

A real autopilot flies its *estimate*: PX4's velocity loop holds the estimated velocity at the setpoint and
streams the estimated position and velocity (LOCAL_POSITION_NED, GLOBAL_POSITION_INT, ODOMETRY), while its
GNSS receiver's own velocity (GPS_RAW_INT) stays close to the truth.  The error is slow: measured against
SIH's ground truth in the ULogs of eight stock PX4 looping the duct for 320 s (2026-12-07,
``vehicle_local_position`` against ``vehicle_local_position_groundtruth`` while airborne), the velocity error
had standard deviations (north, east, down) of 0.13-0.15, 0.28-0.31 and 0.16-0.18 m/s with 1/e correlation
times of 3.0-4.9 s (down 3.6-5.1 s), the position error 0.10-0.11, 0.20-0.21 and 0.29-0.35 m with 3.3-4.1 s
(down 5.5-7.0 s); the velocity error correlates by 0.3-0.6 with the position error's rate.  The errors are smooth: the position error's rate (over 0.5 s) had a spread of only 0.06, 0.09 and
0.10 m/s.  Each axis is modelled as an independent critically damped second-order Gauss-Markov process (an
Ornstein-Uhlenbeck process through a first-order lag of the same time constant ``T``), with that spread and
1/e correlation time (``T`` = the time / 2.146); its rate's spread is ``sd / T`` (0.06, 0.12, 0.11 m/s for
the position).  A first-order process has rough paths: its rate on the vertical would have been 0.27 m/s,
and an agent reacting to that jitter flew 2.5 times the real fleet's vertical setpoints.

The velocity error is the position error's rate plus an independent part ``w`` (a process of the same kind
with the velocity's correlation time, its spread making up the measured total): as in the estimator, the
reported position then moves as the reported velocity says, but for ``w``.  The measured regression of the
velocity error on the position error's rate is 0.7 (north), 1.2 (east) and 1.0 (down): one.  With
independent errors an agent chased the position error's own wander and flew 1.8 times the real fleet's
vertical setpoints.  A vehicle starts from its stationary distribution (a burn-in of ten time constants).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class EstimateErrorParams:
    """Spread and correlation time of the estimate's error, per NED axis."""

    velocity_sd_ned_m_s: Vec3 = (0.14, 0.30, 0.165)
    """Stationary standard deviation of the velocity estimate's error (north, east, down) [m/s]: the position
    error's rate (``position_sd / T``) and the independent part; an axis below that rate has no independent part."""
    velocity_tau_s: Vec3 = (3.2, 3.2, 4.3)
    """1/e correlation time of the velocity error's independent part per axis [s]."""
    position_sd_ned_m: Vec3 = (0.10, 0.21, 0.33)
    """Stationary standard deviation of the position estimate's error (north, east, down) [m]."""
    position_tau_s: Vec3 = (3.7, 3.7, 6.2)
    """1/e correlation time of the position error per axis [s]."""
    seed: int = 0
    """Seed of the vehicle's error sequence (the emulator gives each vehicle its own)."""

    def __post_init__(self) -> None:
        for name in ("velocity_sd_ned_m_s", "velocity_tau_s", "position_sd_ned_m", "position_tau_s"):
            v = getattr(self, name)
            if len(v) != 3 or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in v):
                raise ValueError(f"estimate error {name} must be 3 finite numbers, is {v!r}")
            if any(x < 0 for x in v) or (name.endswith("tau_s") and any(x <= 0 for x in v)):
                raise ValueError(f"estimate error {name} must be {'> 0' if name.endswith('tau_s') else '>= 0'}, "
                                 f"is {v!r}")


PX4_SIH_ESTIMATE_ERROR = EstimateErrorParams()
"""Stock PX4 on SIH (EKF2 with SIH's simulated sensors), as measured above."""


ACF_E_FOLD = 2.146193220620583
"""The 1/e correlation time of a critically damped second-order Gauss-Markov process in units of its time
constant: the root of ``(1 + s) exp(-s) = exp(-1)``."""


def gauss_markov_step(x: np.ndarray, dt_s: float, tau_s: np.ndarray, sd: np.ndarray,
                      normal: np.ndarray) -> np.ndarray:
    """One exact step of a first-order Gauss-Markov process: ``x a + sd sqrt(1 - a^2) n``, ``a = exp(-dt/tau)``,
    ``n`` standard normal draws (its variance stays ``sd^2`` for any ``dt``)."""
    a = np.exp(-dt_s / tau_s)
    return x * a + sd * np.sqrt(1.0 - a * a) * normal


def smooth_gauss_markov_step(u: np.ndarray, x: np.ndarray, dt_s: float, t_s: np.ndarray, sd: np.ndarray,
                             normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One step of the critically damped second-order process ``x' = u - x / T``, ``u`` first-order
    Gauss-Markov with time constant ``T`` and spread ``sd sqrt(2) / T`` (then ``x`` has spread ``sd``):
    ``u`` exactly, ``x`` exactly for ``u`` held over the step.  Returns (u, x)."""
    a = np.exp(-dt_s / t_s)
    x = x * a + t_s * (1.0 - a) * u
    return gauss_markov_step(u, dt_s, t_s, sd * np.sqrt(2.0) / t_s, normal), x


class EstimateError:
    """One vehicle's estimate error: ``velocity_ned_m_s`` and ``position_ned_m`` (lists of 3 floats)."""

    def __init__(self, params: EstimateErrorParams) -> None:
        self._rng = np.random.default_rng(params.seed)
        self._t = np.array(params.velocity_tau_s + params.position_tau_s, dtype=float) / ACF_E_FOLD
        sd_p = np.array(params.position_sd_ned_m, dtype=float)
        rate_sd = sd_p / self._t[3:]
        sd_w = np.sqrt(np.maximum(np.square(params.velocity_sd_ned_m_s) - rate_sd ** 2, 0.0))
        self._sd = np.concatenate([sd_w, sd_p])  # (w, position)
        self._u, self._x = np.zeros(6), np.zeros(6)
        for _ in range(100):  # ten time constants of burn-in, in steps of T / 10
            self._u, self._x = smooth_gauss_markov_step(self._u, self._x, self._t / 10.0, self._t, self._sd,
                                                        self._rng.standard_normal(6))
        self._split()

    def step(self, dt_s: float) -> None:
        """Advance the error by ``dt_s`` seconds."""
        self._u, self._x = smooth_gauss_markov_step(self._u, self._x, dt_s, self._t, self._sd,
                                                    self._rng.standard_normal(6))
        self._split()

    def _split(self) -> None:
        x, u, t = self._x, self._u, self._t
        self.position_ned_m = x[3:].tolist()
        self.velocity_ned_m_s = (x[:3] + u[3:] - x[3:] / t[3:]).tolist()  # w + the position error's rate
