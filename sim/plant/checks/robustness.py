"""The aggressive manoeuvre (race) and the Monte Carlo noise test of the paper's plant campaign."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from sim.plant.model import Backend, PlantParams, thrust_accel_norm, tilt_deg
from sim.plant.checks.common import DT_S, Run, simulate


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
