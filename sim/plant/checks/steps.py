"""Step tracking, hover, the thrust-to-weight sweep and the headwind test of the paper's plant campaign."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from sim.plant.model import Backend, PlantParams, thrust_accel_norm, tilt_deg
from sim.plant.checks.common import DT_S, simulate, settling_time_s, second_order_settling_time_s


@dataclass(frozen=True)
class StepResult:
    """Single-axis step response figures, one entry per axis (x, y, z)."""

    step_m_s: float
    """Step size [m/s] (z steps are climbs, i.e. negative NED)."""
    settling_time_s: tuple[float, float, float]
    """2 % settling time per axis [s]."""
    overshoot_frac: tuple[float, float, float]
    """Overshoot as a fraction of the step per axis [-]."""
    steady_state_error_m_s: tuple[float, float, float]
    """|v_cmd - v| at the end of the run per axis [m/s]."""
    max_off_axis_m_s: tuple[float, float, float]
    """Largest |velocity| on the two other axes during each axis's step [m/s]."""
    analytic_settling_time_s: float
    """2 % settling time of the linearised loop [s]."""


def check_single_axis_step(
    params: PlantParams = PlantParams(), step_m_s: float = 1.0, duration_s: float = 8.0, backend: Backend = "auto"
) -> StepResult:
    """Steps of ``step_m_s`` from hover on x, y and z (z: climb) - paper Fig. "single_axis"."""
    n_t = round(duration_s / DT_S)
    steps = np.diag([step_m_s, step_m_s, -step_m_s])
    cmd = np.broadcast_to(steps, (n_t, 3, 3))
    run = simulate(params, cmd, backend=backend)
    ts, os_, sse, off = [], [], [], []
    for ax in range(3):
        y = run.vel_ned_m_s[:, ax, ax]
        s = steps[ax, ax]
        ts.append(settling_time_s(run.t_s, y, s, s))
        os_.append(max(0.0, float(np.max((y - s) * np.sign(s)) / abs(s))))
        sse.append(float(abs(s - y[-1])))
        others = [o for o in range(3) if o != ax]
        off.append(float(np.max(np.abs(run.vel_ned_m_s[:, ax, others]))))
    return StepResult(step_m_s, tuple(ts), tuple(os_), tuple(sse), tuple(off), second_order_settling_time_s(params))


@dataclass(frozen=True)
class HoverResult:
    """Hover stability figures."""

    max_speed_from_trim_m_s: float
    """Largest |v| over the run for zero command starting at hover trim [m/s]."""
    initial_speed_m_s: float
    """|v0| of the perturbed start [m/s]."""
    final_speed_from_perturbed_m_s: float
    """|v| at the end of the run after starting perturbed [m/s]."""
    max_speed_late_from_perturbed_m_s: float
    """Largest |v| over the second half of the perturbed run [m/s]."""


def check_hover(params: PlantParams = PlantParams(), duration_s: float = 30.0, backend: Backend = "auto") -> HoverResult:
    """Zero command: from trim (must stay exactly still) and from a 1 m/s-per-axis perturbation
    with zero thrust (must return to rest)."""
    n_t = round(duration_s / DT_S)
    v0 = np.array([[0.0, 0.0, 0.0], [1.0, -1.0, 1.0]])
    thr0 = np.array([[0.0, 0.0, -float(np.mean(params.g))], [0.0, 0.0, 0.0]])
    run = simulate(params, np.zeros((n_t, 2, 3)), velocity0_ned_m_s=v0, thrust0_ned_m_s2=thr0, backend=backend)
    speed = np.linalg.norm(run.vel_ned_m_s, axis=2)
    return HoverResult(
        float(speed[:, 0].max()),
        float(np.linalg.norm(v0[1])),
        float(speed[-1, 1]),
        float(speed[n_t // 2 :, 1].max()),
    )


# ---------------------------------------------------------------------------------------------
# Thrust-to-weight sweep
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SweepResult:
    """Thrust-to-weight sweep under a horizontal step command, one entry per T/W value."""

    thrust_to_weight: tuple[float, ...]
    """Swept T_max / (m g)."""
    cmd_speed_m_s: float
    """Commanded horizontal speed (step from hover along x) [m/s]."""
    max_speed_m_s: tuple[float, ...]
    """Largest horizontal speed reached [m/s]."""
    peak_tilt_deg: tuple[float, ...]
    """Largest realised tilt [deg]."""
    peak_thrust_frac: tuple[float, ...]
    """Largest |a_T| / (T_max / m) [-]."""
    active_constraint: tuple[str, ...]
    """'tilt' when the tilt cone bounds the horizontal acceleration at hover thrust, else 'thrust'."""
    tilt_limited_speed_m_s: float
    """Analytic terminal speed at the tilt limit: sqrt(g tan(theta_max) / k_x) [m/s]."""


def check_thrust_to_weight_sweep(
    params: PlantParams = PlantParams(),
    thrust_to_weight: tuple[float, ...] = (1.5, 2.0, 2.2, 3.0, 4.0, 5.0, 6.0),
    cmd_speed_m_s: float = 7.5,
    duration_s: float = 10.0,
    backend: Backend = "auto",
) -> SweepResult:
    """Step to ``cmd_speed_m_s`` along x for each T/W (one agent each, per-agent parameter)."""
    tw = np.asarray(thrust_to_weight, dtype=np.float64)
    p = replace(params, thrust_to_weight=tw)
    n_t = round(duration_s / DT_S)
    cmd = np.zeros((n_t, tw.size, 3))
    cmd[..., 0] = cmd_speed_m_s
    run = simulate(p, cmd, backend=backend)
    g = float(np.mean(params.g))
    theta = math.radians(float(np.mean(params.tilt_max_deg)))
    hspeed = np.linalg.norm(run.vel_ned_m_s[..., :2], axis=2)
    tilt = tilt_deg(run.thrust_accel_ned_m_s2)
    frac = thrust_accel_norm(run.thrust_accel_ned_m_s2) / (tw * g)
    # horizontal acceleration bound at hover thrust: tilt cone g tan(theta) vs thrust g sqrt(TW^2-1)
    active = tuple("tilt" if math.tan(theta) <= math.sqrt(max(x * x - 1.0, 0.0)) else "thrust" for x in tw)
    kx = p.coefficients(tw.size).drag_k[0, 0]
    return SweepResult(
        tuple(float(x) for x in tw),
        cmd_speed_m_s,
        tuple(float(x) for x in hspeed.max(axis=0)),
        tuple(float(x) for x in tilt.max(axis=0)),
        tuple(float(x) for x in frac.max(axis=0)),
        active,
        math.sqrt(g * math.tan(theta) / kx),
    )


# ---------------------------------------------------------------------------------------------
# Headwind with drag feed-forward
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class HeadwindResult:
    """Steady-state error under a constant headwind, one entry per wind speed."""

    cmd_speed_m_s: float
    """Commanded ground speed along x [m/s]."""
    feedforward_gain: float
    """k_ff used."""
    headwind_m_s: tuple[float, ...]
    """Headwind speed (wind = -headwind along x) [m/s]."""
    error_still_air_ff_m_s: tuple[float, ...]
    """v_cmd - v at steady state, feed-forward from the drag at v_cmd in still air (the default) [m/s]."""
    error_wind_aware_ff_m_s: tuple[float, ...]
    """Same, feed-forward from the drag at the commanded airspeed v_cmd - wind (wind known) [m/s]."""
    error_no_ff_m_s: tuple[float, ...]
    """Same, without feed-forward (k_ff = 0) [m/s]."""


def steady_state_error_m_s(params: PlantParams, cmd_m_s: float, wind_m_s: float, wind_ff_m_s: float, axis: int = 0) -> float:
    """Analytic steady-state error e = v_cmd - v on one horizontal axis, from
    ``e / tau_v = k (v - w)|v - w| - k_ff k (v_cmd - w_ff)|v_cmd - w_ff|`` (fixed point)."""
    co = params.coefficients(None)
    k, kff, tv = float(co.drag_k[0, axis]), float(co.ff_gain[0]), 1.0 / float(co.inv_tau_v[0])
    ff = kff * k * (cmd_m_s - wind_ff_m_s) * abs(cmd_m_s - wind_ff_m_s)
    e = 0.0
    for _ in range(200):  # contraction: |d/de| = 2 tau_v k |v - w| << 1 in the envelope
        air = cmd_m_s - e - wind_m_s
        e = tv * (k * air * abs(air) - ff)
    return e


def check_headwind(
    params: PlantParams = PlantParams(),
    cmd_speed_m_s: float = 5.0,
    headwind_m_s: tuple[float, ...] = (0.0, 2.0, 4.0, 6.0, 8.0),
    feedforward_gain: float = 0.8,
    duration_s: float = 15.0,
    backend: Backend = "auto",
) -> HeadwindResult:
    """Constant headwind 0..8 m/s against a ``cmd_speed_m_s`` flight along x (paper: k_ff 0.8)."""
    w = np.asarray(headwind_m_s, dtype=np.float64)
    n = w.size
    wind = np.zeros((n, 3))
    wind[:, 0] = -w
    n_t = round(duration_s / DT_S)
    cmd = np.zeros((n_t, n, 3))
    cmd[..., 0] = cmd_speed_m_s
    v0 = np.zeros((n, 3))
    v0[:, 0] = cmd_speed_m_s

    def final_err(gain: float, wind_ff: np.ndarray | None) -> tuple[float, ...]:
        p = replace(params, drag_feedforward_gain=gain)
        run = simulate(p, cmd, wind_ned_m_s=wind, wind_ff_ned_m_s=wind_ff, velocity0_ned_m_s=v0, backend=backend)
        return tuple(float(x) for x in cmd_speed_m_s - run.vel_ned_m_s[-1, :, 0])

    return HeadwindResult(
        cmd_speed_m_s,
        feedforward_gain,
        tuple(float(x) for x in w),
        final_err(feedforward_gain, None),
        final_err(feedforward_gain, wind),
        final_err(0.0, None),
    )
