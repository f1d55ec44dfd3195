"""In-flight identification of the vehicle's velocity response (pure numpy, no I/O).

While it takes off and joins, the agent streams velocity setpoints ``u`` and the autopilot
reports its velocity ``v``.  Per horizontal axis the response is fitted, by linear least
squares over both axes at once, to a first-order lag with a dead time and a steady gain::

    v[k+1] = a v[k] + b u[k - d]        (sample period h; d = 0 .. max_dead_steps)

    lag tau = -h / ln(a),   gain g = b / (1 - a),   dead time = d h

The dead time with the smallest residual is kept.  ``lookahead_s = tau + dead time`` is the
look-ahead that cancels this lag for a smooth command (``fisc_agent.flight.tracking``), and
``1 / g`` the feed-forward gain that cancels a steady shortfall (an autopilot whose velocity
loop settles below the setpoint against drag until its integrator catches up), taken only as far
as the fits to each half of the window agree (``VehicleResponse.gain_bound``).  The rise time
(10-90 %) of that model is ``dead time + tau ln 9``; the acceleration limit is the largest
measured acceleration (5-sample central difference).  Identification refuses (returns None)
when the setpoints did not move enough to excite the response or the fit is not a stable lag.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MIN_SAMPLES = 60
"""Fewest samples (3 s at 20 Hz) worth a fit."""
MIN_EXCITATION_M_S = 0.5
"""The setpoints must span at least this speed range on some axis [m/s]."""


FEEDFORWARD_MIN = 1.0
"""Least feed-forward gain: the agent never commands less than the field's velocity."""
FEEDFORWARD_MAX = 1.5
"""Largest feed-forward gain: never more than 50 % above the field's velocity."""
ONLINE_MIN_SPEED_M_S = 0.3
"""``OnlineGain`` gives no estimate while the modelled setpoint's RMS speed is below this [m/s]."""


def feedforward_from_gain(gain: float) -> float:
    """The feed-forward gain that cancels a steady velocity ``gain``: 1 / gain within
    [FEEDFORWARD_MIN, FEEDFORWARD_MAX] (a gain of 0, inf or NaN gives the nearer bound, NaN the least)."""
    if not gain > 0.0:
        return FEEDFORWARD_MAX if gain == 0.0 else FEEDFORWARD_MIN
    return min(FEEDFORWARD_MAX, max(FEEDFORWARD_MIN, 1.0 / gain))


@dataclass(frozen=True)
class VehicleResponse:
    """The identified horizontal velocity response of one vehicle."""

    lag_s: float
    """First-order time constant tau [s]."""
    dead_time_s: float
    """Pure delay before the response starts [s]."""
    gain: float
    """Steady velocity gain g (velocity / setpoint)."""
    gain_bound: float
    """The largest of the gains fitted to the whole window and to each of its halves (inf when a
    half cannot be fitted): the shortfall every part of the data agrees on.  In the flight logs of
    this project's real PX4 SITL tests the halves' gains differ by 0.03 to more than 1 (take-off and
    join excite an acceleration-limited, integrating velocity loop that the first-order model fits
    differently in each part), on ArduPilot SITL and in the emulator by <= 0.05."""
    rise_time_s: float
    """10-90 % rise time of the model, dead time included [s]."""
    max_accel_m_s2: float
    """Largest horizontal acceleration measured [m/s^2]."""
    residual_rms_m_s: float
    """One-step prediction residual of the fit [m/s]."""
    n_samples: int
    """Samples used."""

    @property
    def lookahead_s(self) -> float:
        """The look-ahead that cancels this lag: tau + dead time [s]."""
        return self.lag_s + self.dead_time_s

    @property
    def feedforward_gain(self) -> float:
        """1 / gain_bound, bounded to [FEEDFORWARD_MIN, FEEDFORWARD_MAX] (never amplify more than
        50 %, never attenuate).

        The conservative bound, not the whole window's gain: a real PX4 fleet whose vehicles
        applied 1 / gain (1.02-1.20) crossed the duct in 17.3-20.5 s on the same airframe, and one
        caught up with the vehicle that had entered 2.4 s before it (0.41 m).  In the duct the
        gain is learnt again from the flight itself (``OnlineGain``)."""
        return feedforward_from_gain(self.gain_bound)


def _fit_lag(t: np.ndarray, u: np.ndarray, v: np.ndarray, h: float,
             max_dead_steps: int) -> tuple[float, int, float, float] | None:
    """Least-squares ``(rms, d, a, b)`` of the model with the best dead time, or None (too few pairs)."""
    n = len(t)
    best: tuple[float, int, float, float] | None = None
    for d in range(max_dead_steps + 1):
        k = np.arange(d, n - 1)
        even = (t[k + 1] - t[k]) < 2.0 * h
        if d:
            even &= (t[k] - t[k - d]) < (d + 1) * h * 1.5
        k = k[even]
        if len(k) < MIN_SAMPLES // 2:
            continue
        x = np.column_stack([v[k].ravel(), u[k - d].ravel()])
        y = v[k + 1].ravel()
        coef, *_ = np.linalg.lstsq(x, y, rcond=None)
        rms = float(np.sqrt(np.mean((y - x @ coef) ** 2)))
        if best is None or rms < best[0]:
            best = (rms, d, float(coef[0]), float(coef[1]))
    return best


def _steady_gain(fit: tuple[float, int, float, float] | None) -> float | None:
    """g = b / (1 - a) of a stable fit, else None."""
    if fit is None:
        return None
    _, _, a, b = fit
    return b / (1.0 - a) if 0.0 < a < 1.0 and b > 0.0 else None


def fit_response(t_s: np.ndarray, u_m_s: np.ndarray, v_m_s: np.ndarray,
                 max_dead_steps: int = 8) -> VehicleResponse | None:
    """Fit the model to ``(n,)`` times and ``(n, k)`` setpoints and velocities (k axes).

    Samples must be (nearly) evenly spaced; pairs across a gap of more than twice the median
    period are skipped.  None when there is too little excitation or no stable lag fits.  The
    gain is fitted again to each half of the window (``VehicleResponse.gain_bound``).
    """
    t = np.asarray(t_s, dtype=float)
    u = np.asarray(u_m_s, dtype=float).reshape(len(t), -1)
    v = np.asarray(v_m_s, dtype=float).reshape(len(t), -1)
    ok = np.isfinite(t) & np.all(np.isfinite(u), axis=1) & np.all(np.isfinite(v), axis=1)
    t, u, v = t[ok], u[ok], v[ok]
    n = len(t)
    if n < MIN_SAMPLES or float(np.max(np.ptp(u, axis=0))) < MIN_EXCITATION_M_S:
        return None
    h = float(np.median(np.diff(t)))
    if not h > 0:
        return None
    best = _fit_lag(t, u, v, h, max_dead_steps)
    gain = _steady_gain(best)
    if best is None or gain is None or not (0.2 < gain < 2.0):
        return None
    rms, d, a, _ = best
    lag = -h / math.log(a)
    m = n // 2
    halves = [_steady_gain(_fit_lag(t[s], u[s], v[s], h, max_dead_steps)) for s in (slice(0, m), slice(m, n))]
    gain_bound = max([gain] + halves) if None not in halves else math.inf
    dv = v[4:] - v[:-4]
    dt4 = t[4:] - t[:-4]
    acc = np.linalg.norm(dv, axis=1) / np.where(dt4 > 0, dt4, np.inf)
    return VehicleResponse(lag_s=lag, dead_time_s=d * h, gain=gain, gain_bound=gain_bound,
                           rise_time_s=d * h + lag * math.log(9.0),
                           max_accel_m_s2=float(acc.max()) if acc.size else 0.0, residual_rms_m_s=rms, n_samples=n)


class ResponseRecorder:
    """Collects (t, setpoint, velocity) horizontal samples during take-off and join (bounded)."""

    def __init__(self, max_samples: int = 4000) -> None:
        self.max_samples = max_samples
        self._rows: list[tuple[float, float, float, float, float]] = []

    def add(self, t_s: float, sp_xy_m_s: tuple[float, float], vel_xy_m_s: tuple[float, float]) -> None:
        """Record one tick's horizontal setpoint and velocity (ignored beyond ``max_samples``)."""
        if len(self._rows) < self.max_samples:
            self._rows.append((t_s, sp_xy_m_s[0], sp_xy_m_s[1], vel_xy_m_s[0], vel_xy_m_s[1]))

    def __len__(self) -> int:
        return len(self._rows)

    def fit(self) -> VehicleResponse | None:
        """The identified response, or None with fewer than ``MIN_SAMPLES`` rows."""
        if len(self._rows) < MIN_SAMPLES:
            return None
        a = np.asarray(self._rows)
        return fit_response(a[:, 0], a[:, 1:3], a[:, 3:5])


class OnlineGain:
    """The vehicle's steady horizontal velocity gain, learnt again from every tick of the pass (pure).

    Identification before the pass sees an integrating velocity loop in take-off and join: stock
    PX4 gains (``MPC_XY_VEL_P_ACC`` 1.8, ``_I_ACC`` 0.4) against SIH's drag settle at 0.80-0.85 of
    the setpoint until the integrator catches up, and the halves' fits disagree, so the conservative
    ``VehicleResponse.feedforward_gain`` stays at 1.  Here the setpoint ``u`` streamed is passed
    through the identified lag (``lag_s``: a first-order model ``m``, unit gain), and the gain is the
    least-squares ratio of the measured velocity ``v`` to it with exponential forgetting::

        m <- m + (1 - exp(-dt / lag)) (u - m)
        g = <v . m> / <m . m>           (each <.> low-passed with time constant forget_s)

    The lag is modelled, so the pass's accelerations do not read as a gain.  None until
    ``forget_s`` of samples and an RMS modelled speed of ``ONLINE_MIN_SPEED_M_S``."""

    def __init__(self, lag_s: float, forget_s: float) -> None:
        if not (math.isfinite(lag_s) and lag_s >= 0.0):
            raise ValueError(f"OnlineGain: lag_s must be finite and >= 0, is {lag_s!r}")
        if not (math.isfinite(forget_s) and forget_s > 0.0):
            raise ValueError(f"OnlineGain: forget_s must be finite and > 0, is {forget_s!r}")
        self.lag_s = lag_s
        """The modelled lag (identified look-ahead: lag plus dead time) [s]."""
        self.forget_s = forget_s
        """Forgetting time constant of the averages [s]."""
        self._model: tuple[float, float] | None = None
        self._t_s: float | None = None
        self._vm = 0.0
        self._mm = 0.0
        self._weight = 0.0   # the same low pass of 1: <.> / _weight is a weighted mean
        self._seen_s = 0.0

    def update(self, t_s: float, sp_xy_m_s: tuple[float, float], vel_xy_m_s: tuple[float, float]) -> None:
        """One tick: the horizontal setpoint sent and the velocity measured.  Non-finite samples and
        gaps over 0.5 s (a hold, a lap's return) restart the model, keeping the averages."""
        if not all(math.isfinite(x) for x in (t_s, *sp_xy_m_s, *vel_xy_m_s)):
            return
        prev_t, self._t_s = self._t_s, t_s
        if self._model is None or prev_t is None or not 0.0 < t_s - prev_t <= 0.5:
            self._model = (float(sp_xy_m_s[0]), float(sp_xy_m_s[1]))
            return
        dt = t_s - prev_t
        k = 1.0 - math.exp(-dt / self.lag_s) if self.lag_s > 0.0 else 1.0
        mx, my = self._model
        mx, my = mx + k * (sp_xy_m_s[0] - mx), my + k * (sp_xy_m_s[1] - my)
        self._model = (mx, my)
        w = min(1.0, dt / self.forget_s)
        self._vm += w * (vel_xy_m_s[0] * mx + vel_xy_m_s[1] * my - self._vm)
        self._mm += w * (mx * mx + my * my - self._mm)
        self._weight += w * (1.0 - self._weight)
        self._seen_s += dt

    @property
    def gain(self) -> float | None:
        """The gain learnt so far, or None (too few samples or too slow a flight)."""
        if self._seen_s < self.forget_s or self._mm < self._weight * ONLINE_MIN_SPEED_M_S ** 2:
            return None
        return self._vm / self._mm
