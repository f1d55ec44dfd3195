"""Cross-axis coupling, frequency response and the actuation constraints of the plant."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.plant.model import Backend, PlantParams, VelocityPlant
from sim.plant.checks.common import DT_S, closed_loop_response, simulate


@dataclass(frozen=True)
class CouplingResult:
    """Cross-axis coupling figures."""

    step_m_s: float
    """Size of the x step [m/s]."""
    max_y_from_hover_m_s: float
    """Largest |v_y| during an x step from hover (y, z commanded 0) [m/s]."""
    max_z_from_hover_m_s: float
    """Largest |v_z| during the same step [m/s]."""
    cruise_y_m_s: float
    """Lateral speed held while x steps [m/s]."""
    max_y_dev_while_cruising_m_s: float
    """Largest |v_y - cruise_y| during an x step made while cruising along y (the tilt limit
    scales the whole horizontal demand, so y borrows from x's saturation) [m/s]."""


def check_coupling(
    params: PlantParams = PlantParams(), step_m_s: float = 8.0, cruise_y_m_s: float = 3.0, backend: Backend = "auto"
) -> CouplingResult:
    """Large x step (tilt-saturating) from hover, and the same step while cruising along y."""
    n_t = round(8.0 / DT_S)
    cmd = np.zeros((n_t, 2, 3))
    cmd[..., 0] = step_m_s
    cmd[:, 1, 1] = cruise_y_m_s
    v0 = np.array([[0.0, 0.0, 0.0], [0.0, cruise_y_m_s, 0.0]])
    run = simulate(params, cmd, velocity0_ned_m_s=v0, backend=backend)
    v = run.vel_ned_m_s
    return CouplingResult(
        step_m_s,
        float(np.abs(v[:, 0, 1]).max()),
        float(np.abs(v[:, 0, 2]).max()),
        cruise_y_m_s,
        float(np.abs(v[:, 1, 1] - cruise_y_m_s).max()),
    )


@dataclass(frozen=True)
class FrequencyResult:
    """Sinusoidal-command frequency response along x."""

    freq_hz: tuple[float, ...]
    """Command frequencies [Hz]."""
    amplitude_m_s: float
    """Command amplitude [m/s]."""
    gain: tuple[float, ...]
    """Measured |V / V_cmd| [-]."""
    phase_deg: tuple[float, ...]
    """Measured phase of V relative to V_cmd [deg] (negative = lag)."""
    model_gain: tuple[float, ...]
    """Linearised closed-loop gain at the same frequencies [-]."""
    model_phase_deg: tuple[float, ...]
    """Linearised closed-loop phase [deg]."""
    bandwidth_hz: float
    """-3 dB bandwidth interpolated from the measured gains [Hz]."""
    model_bandwidth_hz: float
    """-3 dB bandwidth of the linearised loop [Hz]."""
    first_order_bandwidth_hz: float
    """1 / (2 pi tau_v): the bandwidth without the thrust lag [Hz]."""


def check_frequency_response(
    params: PlantParams = PlantParams(),
    freq_hz: tuple[float, ...] = tuple(np.round(np.geomspace(0.05, 2.0, 12), 4)),
    amplitude_m_s: float = 0.5,
    settle_s: float = 6.0,
    cycles: int = 2,
    backend: Backend = "auto",
) -> FrequencyResult:
    """x command ``A sin(2 pi f t)``, one agent per frequency; gain and phase by least squares
    on ``cycles`` whole periods after ``settle_s``."""
    f = np.asarray(freq_hz, dtype=np.float64)
    dur = settle_s + cycles / f
    n_t = int(math.ceil(dur.max() / DT_S))
    t = np.arange(n_t) * DT_S
    cmd = np.zeros((n_t, f.size, 3))
    cmd[..., 0] = amplitude_m_s * np.sin(2 * np.pi * f[None, :] * t[:, None])
    run = simulate(params, cmd, backend=backend)
    gains, phases = [], []
    for i, fi in enumerate(f):
        # velocity sample k+1 is the state at t[k+1]; fit v(t) = a sin + b cos + c on whole cycles
        tk = run.t_s
        sel = (tk >= settle_s) & (tk < settle_s + cycles / fi)
        w = 2 * np.pi * fi * tk[sel]
        basis = np.stack([np.sin(w), np.cos(w), np.ones_like(w)], axis=1)
        (a, b, _), *_ = np.linalg.lstsq(basis, run.vel_ned_m_s[sel, i, 0], rcond=None)
        gains.append(math.hypot(a, b) / amplitude_m_s)
        phases.append(math.degrees(math.atan2(b, a)))
    gains_a = np.asarray(gains)
    model = closed_loop_response(params, f)
    return FrequencyResult(
        tuple(float(x) for x in f),
        amplitude_m_s,
        tuple(float(x) for x in gains_a),
        tuple(float(x) for x in phases),
        tuple(float(x) for x in np.abs(model)),
        tuple(float(x) for x in np.degrees(np.angle(model))),
        _crossing_hz(f, gains_a),
        _model_bandwidth_hz(params),
        1.0 / (2 * np.pi * float(params.tau_v_s)),
    )


def _crossing_hz(f: np.ndarray, gain: np.ndarray, level: float = 1 / math.sqrt(2)) -> float:
    below = np.nonzero(gain < level)[0]
    if below.size == 0 or below[0] == 0:
        return math.nan
    k = below[0]
    lf0, lf1 = math.log(f[k - 1]), math.log(f[k])
    frac = (gain[k - 1] - level) / (gain[k - 1] - gain[k])
    return math.exp(lf0 + frac * (lf1 - lf0))


def _model_bandwidth_hz(params: PlantParams) -> float:
    lo, hi = 1e-4, 100.0
    for _ in range(200):
        mid = math.sqrt(lo * hi)
        if abs(closed_loop_response(params, np.array([mid]))[0]) > 1 / math.sqrt(2):
            lo = mid
        else:
            hi = mid
    return hi


# ---------------------------------------------------------------------------------------------
# Constraints
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ConstraintResult:
    """Constraint audit over random commands, winds and parameters."""

    agents: int
    """Random agents simulated."""
    steps: int
    """Steps per agent."""
    max_tilt_excess_deg: float
    """max(tilt - theta_max) over all samples [deg] (<= 0: never violated)."""
    max_thrust_excess_frac: float
    """max(|a_T| / (T_max/m) - 1) over all samples [-] (<= 0: never violated)."""
    max_tilt_deg: float
    """Largest tilt seen [deg] (reached the limit when close to theta_max)."""


def check_constraints(
    agents: int = 500, steps: int = 300, seed: int = 1, dt_s: float = 0.05, backend: Backend = "auto"
) -> ConstraintResult:
    """Random per-agent T/W (1.2..6) and tilt limits (20..70 deg), random commands up to 40 m/s
    re-drawn every 0.5 s, random wind up to 10 m/s per axis, starting from hover."""
    rng = np.random.default_rng(seed)
    tw = rng.uniform(1.2, 6.0, agents)
    tilt_max = rng.uniform(20.0, 70.0, agents)
    p = PlantParams(thrust_to_weight=tw, tilt_max_deg=tilt_max, mass_kg=rng.uniform(0.3, 3.0, agents))
    plant = VelocityPlant(p, agents, backend=backend)
    wind = rng.uniform(-10.0, 10.0, (agents, 3))
    amax = tw * 9.81
    tilt_ex, thr_ex, tilt_top = -math.inf, -math.inf, 0.0
    cmd = np.zeros((agents, 3))
    for k in range(steps):
        if k % 10 == 0:
            cmd = rng.uniform(-40.0, 40.0, (agents, 3))
        plant.step(cmd, dt_s, wind)
        tl = plant.tilt_deg()
        tilt_ex = max(tilt_ex, float((tl - tilt_max).max()))
        thr_ex = max(thr_ex, float((plant.thrust_accel_norm() / amax - 1.0).max()))
        tilt_top = max(tilt_top, float(tl.max()))
    return ConstraintResult(agents, steps, tilt_ex, thr_ex, tilt_top)
