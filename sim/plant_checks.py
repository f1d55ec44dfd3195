"""The paper's plant test campaign, as functions returning the measured figures.

The paper ("Individual-Agent Velocity Plant", "Performance Testing Prior to Swarm Use") reports
a settling time, a thrust-to-weight sweep, a headwind test with drag feed-forward, a Monte Carlo
noise test and an aggressive manoeuvre.  Each ``check_*`` function below runs one of them on
:mod:`sim.plant` (vectorised: a sweep's cases are agents of one plant, with per-agent
parameters where the case varies a parameter) and returns a frozen dataclass of figures.  The
tests (``tests/sim/test_plant.py``) assert on these functions, and ``python -m sim.plant_checks``
prints the "ours vs the paper" table of ``docs/plant.md``, so the docs and the tests agree.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, replace

import numpy as np

from sim.plant import Backend, PlantParams, VelocityPlant, thrust_accel_norm, tilt_deg

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


# ---------------------------------------------------------------------------------------------
# Step tracking and hover
# ---------------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------------
# Aggressive manoeuvre and Monte Carlo noise
# ---------------------------------------------------------------------------------------------


def race_command(t_s: np.ndarray) -> np.ndarray:
    """A racing-style velocity command profile (T, 3) NED over 0..20 s: hover, sprints of
    8 m/s with climbing/descending turns (steps on all axes), a 6 m/s circle (continuous
    turning), a vertical/lateral slalom, and a stop."""
    t = np.asarray(t_s, dtype=np.float64)
    c = np.zeros((t.size, 3))
    segs = [  # (start, end, (vx, vy, vz))
        (1.0, 4.0, (8.0, 0.0, 0.0)),
        (4.0, 6.5, (0.0, 8.0, -3.0)),
        (6.5, 9.0, (-8.0, 0.0, 0.0)),
        (9.0, 11.0, (0.0, -8.0, 3.0)),
    ]
    for a, b, v in segs:
        c[(t >= a) & (t < b)] = v
    circ = (t >= 11.0) & (t < 15.0)
    ph = 2.0 * np.pi * 0.25 * (t[circ] - 11.0)
    c[circ] = np.stack([6.0 * np.cos(ph), 6.0 * np.sin(ph), np.zeros_like(ph)], axis=1)
    sl = (t >= 15.0) & (t < 18.0)
    ph = 2.0 * np.pi * 0.5 * (t[sl] - 15.0)
    c[sl] = np.stack([np.full_like(ph, 5.0), 4.0 * np.sin(ph), -2.0 * np.sin(ph)], axis=1)
    return c


RACE_DURATION_S = 20.0
"""Length of :func:`race_command`'s profile [s]."""


@dataclass(frozen=True)
class RaceResult:
    """Aggressive manoeuvre tracking, one entry per feed-forward gain."""

    feedforward_gain: tuple[float, ...]
    """k_ff values compared."""
    rmse_lateral_m_s: tuple[float, ...]
    """RMSE of (v - v_cmd) over x and y and the whole run [m/s]."""
    rmse_vertical_m_s: tuple[float, ...]
    """RMSE of (v_z - v_cmd,z) [m/s]."""
    cruise_error_m_s: tuple[float, ...]
    """|v - v_cmd| in the last 0.5 s of the first 8 m/s sprint (steady tracking) [m/s]."""
    peak_tilt_deg: tuple[float, ...]
    """Largest realised tilt [deg]."""
    peak_thrust_frac: tuple[float, ...]
    """Largest |a_T| / (T_max / m) [-]."""
    final_speed_m_s: tuple[float, ...]
    """|v| at the end (command zero from 18 s) [m/s]."""


def _rmse(run: Run) -> tuple[np.ndarray, np.ndarray]:
    err = run.vel_ned_m_s[1:] - run.cmd_ned_m_s
    lat = np.sqrt(np.mean(err[..., :2] ** 2, axis=(0, 2)))
    ver = np.sqrt(np.mean(err[..., 2] ** 2, axis=0))
    return lat, ver


def check_race(
    params: PlantParams = PlantParams(), feedforward_gain: tuple[float, ...] = (0.0, 0.8, 1.0), backend: Backend = "auto"
) -> RaceResult:
    """Fly :func:`race_command` with each feed-forward gain (paper Fig. "race")."""
    gains = np.asarray(feedforward_gain, dtype=np.float64)
    p = replace(params, drag_feedforward_gain=gains)
    t = np.arange(round(RACE_DURATION_S / DT_S)) * DT_S
    cmd = np.repeat(race_command(t)[:, None, :], gains.size, axis=1)
    run = simulate(p, cmd, backend=backend)
    lat, ver = _rmse(run)
    k = np.nonzero((run.t_s[1:] > 3.5) & (run.t_s[1:] <= 4.0))[0]
    cruise = np.linalg.norm(run.vel_ned_m_s[1:][k] - cmd[k], axis=2).mean(axis=0)
    g = float(np.mean(params.g))
    amax = np.broadcast_to(np.asarray(params.thrust_to_weight, dtype=np.float64), gains.shape) * g
    return RaceResult(
        tuple(float(x) for x in gains),
        tuple(float(x) for x in lat),
        tuple(float(x) for x in ver),
        tuple(float(x) for x in cruise),
        tuple(float(x) for x in tilt_deg(run.thrust_accel_ned_m_s2).max(axis=0)),
        tuple(float(x) for x in (thrust_accel_norm(run.thrust_accel_ned_m_s2) / amax).max(axis=0)),
        tuple(float(x) for x in np.linalg.norm(run.vel_ned_m_s[-1], axis=1)),
    )


@dataclass(frozen=True)
class NoiseResult:
    """Monte Carlo velocity-measurement noise on the race profile, one entry per noise level."""

    kind: str
    """'measurement': white noise on the velocity fed back to the controller; 'process': white
    velocity disturbance added to the state every control period."""
    noise_rms_m_s: tuple[float, ...]
    """Per-axis RMS of the white noise, one sample per 0.01 s control period [m/s]."""
    runs: int
    """Monte Carlo runs per level."""
    seed: int
    """Seed of the noise generator."""
    rmse_lateral_m_s: tuple[float, ...]
    """Mean over runs of the lateral (x, y) tracking RMSE [m/s]."""
    rmse_vertical_m_s: tuple[float, ...]
    """Mean over runs of the vertical tracking RMSE [m/s]."""
    rmse_lateral_std_m_s: tuple[float, ...]
    """Run-to-run standard deviation of the lateral RMSE [m/s]."""


def check_noise(
    params: PlantParams = PlantParams(),
    noise_rms_m_s: tuple[float, ...] = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5),
    runs: int = 20,
    seed: int = 0,
    kind: str = "measurement",
    backend: Backend = "auto",
) -> NoiseResult:
    """Race profile with white Gaussian velocity noise (one sample per 0.01 s control period),
    either measured (fed back to the controller) or as a process disturbance on the velocity
    state (``kind``); ``runs`` seeded runs per level, all levels and runs agents of one plant."""
    if kind not in ("measurement", "process"):
        raise ValueError(f"check_noise: kind must be 'measurement' or 'process', got {kind!r}")
    sig = np.asarray(noise_rms_m_s, dtype=np.float64)
    n = sig.size * runs
    t = np.arange(round(RACE_DURATION_S / DT_S)) * DT_S
    cmd = np.repeat(race_command(t)[:, None, :], n, axis=1)
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((t.size, n, 3)) * np.repeat(sig, runs)[None, :, None]
    if kind == "measurement":
        run = simulate(params, cmd, feedback_noise_ned_m_s=noise, backend=backend)
    else:
        run = simulate(params, cmd, process_noise_ned_m_s=noise, backend=backend)
    lat, ver = _rmse(run)
    lat, ver = lat.reshape(sig.size, runs), ver.reshape(sig.size, runs)
    return NoiseResult(
        kind,
        tuple(float(x) for x in sig),
        runs,
        seed,
        tuple(float(x) for x in lat.mean(axis=1)),
        tuple(float(x) for x in ver.mean(axis=1)),
        tuple(float(x) for x in lat.std(axis=1)),
    )


# ---------------------------------------------------------------------------------------------
# Coupling and frequency response
# ---------------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------------


def _fmt(xs, spec: str = ".3f") -> str:
    return ", ".join(format(x, spec) for x in xs)


def report_markdown(backend: Backend = "auto") -> str:
    """Run every check with its defaults and return the "ours vs the paper" markdown table."""
    st = check_single_axis_step(backend=backend)
    st5 = check_single_axis_step(step_m_s=5.0, backend=backend)
    hv = check_hover(backend=backend)
    sw = check_thrust_to_weight_sweep(backend=backend)
    big = check_thrust_to_weight_sweep(cmd_speed_m_s=60.0, duration_s=40.0, backend=backend)
    hw = check_headwind(backend=backend)
    rc = check_race(backend=backend)
    nz = check_noise(backend=backend)
    nzp = check_noise(kind="process", backend=backend)
    cp = check_coupling(backend=backend)
    fr = check_frequency_response(backend=backend)
    cs = check_constraints(backend=backend)
    rows = [
        ("Single-axis step: 2 % settling time", "about 1.67 s",
         f"x/y/z {_fmt(st.settling_time_s, '.2f')} s (1 m/s step); {_fmt(st5.settling_time_s, '.2f')} s (5 m/s); "
         f"linear model {st.analytic_settling_time_s:.2f} s"),
        ("Single-axis step: overshoot", "none",
         f"{max(st.overshoot_frac) * 100:.2f} % (1 m/s), {max(st5.overshoot_frac) * 100:.2f} % (5 m/s)"),
        ("Single-axis step: steady-state error", "very small",
         f"{_fmt(st.steady_state_error_m_s, '.4f')} m/s (1 m/s), {_fmt(st5.steady_state_error_m_s, '.3f')} m/s (5 m/s)"),
        ("Hover stability", "stable",
         f"from trim: max speed {hv.max_speed_from_trim_m_s:.1e} m/s; from {hv.initial_speed_m_s:.2f} m/s "
         f"and zero thrust: {hv.final_speed_from_perturbed_m_s:.1e} m/s after 30 s"),
        ("T/W sweep 1.5..6: max speed", "common, near 7.48 m/s",
         f"{_fmt(sw.max_speed_m_s, '.2f')} m/s for a {sw.cmd_speed_m_s:g} m/s command "
         f"(T/W {_fmt(sw.thrust_to_weight, 'g')}); under a {big.cmd_speed_m_s:g} m/s command "
         f"{_fmt(big.max_speed_m_s, '.1f')} m/s (tilt-limited drag terminal speed {big.tilt_limited_speed_m_s:.1f} m/s)"),
        ("T/W sweep: peak tilt / active constraint", "54.3 deg, attitude",
         f"{_fmt(sw.peak_tilt_deg, '.1f')} deg ({', '.join(sw.active_constraint)}) for the {sw.cmd_speed_m_s:g} m/s command, "
         f"peak thrust/T_max {_fmt(sw.peak_thrust_frac, '.2f')}; {_fmt(big.peak_tilt_deg, '.1f')} deg for {big.cmd_speed_m_s:g} m/s"),
        (f"Headwind 0..8 m/s, k_ff {hw.feedforward_gain:g}: steady-state error", "0.01..0.06 m/s",
         f"{hw.cmd_speed_m_s:g} m/s flight, winds {_fmt(hw.headwind_m_s, 'g')} m/s: still-air ff "
         f"{_fmt(hw.error_still_air_ff_m_s)}; wind-aware ff {_fmt(hw.error_wind_aware_ff_m_s)}; no ff "
         f"{_fmt(hw.error_no_ff_m_s)} m/s"),
        ("Monte Carlo noise 0..0.5 m/s RMS: lateral RMSE", "0.57 -> 2.98 m/s",
         f"measurement noise {_fmt(nz.rmse_lateral_m_s, '.2f')}; process noise {_fmt(nzp.rmse_lateral_m_s, '.2f')} m/s "
         f"(noise {_fmt(nz.noise_rms_m_s, 'g')} m/s, race profile, {nz.runs} runs/level, seed {nz.seed})"),
        ("Monte Carlo noise: vertical RMSE", "0.19 -> 2.18 m/s",
         f"measurement noise {_fmt(nz.rmse_vertical_m_s, '.2f')}; process noise {_fmt(nzp.rmse_vertical_m_s, '.2f')} m/s"),
        ("Aggressive manoeuvre (race), k_ff " + _fmt(rc.feedforward_gain, "g"), "tracks all axes (figure)",
         f"lateral RMSE {_fmt(rc.rmse_lateral_m_s)} m/s, vertical {_fmt(rc.rmse_vertical_m_s)} m/s, "
         f"8 m/s cruise error {_fmt(rc.cruise_error_m_s)} m/s, peak tilt {_fmt(rc.peak_tilt_deg, '.1f')} deg"),
        ("Cross-axis coupling", "decoupled (no figure)",
         f"{cp.step_m_s:g} m/s x step: max v_y {cp.max_y_from_hover_m_s:.1e}, v_z {cp.max_z_from_hover_m_s:.1e} m/s; "
         f"while cruising y at {cp.cruise_y_m_s:g} m/s: max y deviation {cp.max_y_dev_while_cruising_m_s:.3f} m/s"),
        ("Frequency response: -3 dB bandwidth", "no figure",
         f"{fr.bandwidth_hz:.3f} Hz measured, {fr.model_bandwidth_hz:.3f} Hz linear model "
         f"(1/(2 pi tau_v) = {fr.first_order_bandwidth_hz:.3f} Hz)"),
        ("Constraints never violated", "enforced",
         f"{cs.agents} random agents x {cs.steps} steps: max tilt excess {cs.max_tilt_excess_deg:.1e} deg, "
         f"max thrust excess {cs.max_thrust_excess_frac:.1e}"),
    ]  # fmt: skip
    lines = ["| Test | Paper | Ours |", "|---|---|---|"]
    lines += [f"| {a} | {b} | {c} |" for a, b, c in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m sim.plant_checks``: print the "ours vs the paper" table."""
    ap = argparse.ArgumentParser(prog="python -m sim.plant_checks", description=__doc__.split("\n")[0])
    ap.add_argument("--backend", choices=("auto", "numpy", "numba"), default="auto", help="plant kernel")
    args = ap.parse_args(argv)
    print(report_markdown(args.backend))  # CLI entry point: printing is its job
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
