"""The vehicle's drag, identified in flight, and its acceleration feed-forward (pure).

A stock PX4 velocity loop is a PID on acceleration: ``a_sp = P e + I int(e) - D dv/dt + a_ff``.  Against
a linear drag ``c v`` its integrator alone must hold the thrust that flying at ``v`` needs, and it lags
behind every change of speed: on a ramp of acceleration ``a`` the steady error is ``c a / I`` (stock PX4:
I 0.4, SIH's drag c 1/s: 2.5 s of the ramp).  That lag is what left stock PX4 flying the duct's throat at
0.78-0.81 of the fitted speed and its outlet at 1.10-1.18 (docs/status.md), and no look-ahead cancels it.
Fed forward, ``a_ff = c_hat v_sp`` makes the loop's integrator unnecessary for the drag: the vehicle then
follows its setpoint as a first-order lag of about ``(1 + D) / (P + c)`` (0.43 s on stock PX4 SIH), which
the tracking's look-ahead cancels.

``c_hat`` comes from the vehicle's own attitude: in flight the thrust's horizontal part is the
acceleration it asks for, ``g tan(tilt)`` along the tilt (``thrust_accel_ne``; PX4 reports its attitude in
ODOMETRY), and what the vehicle does not gain of it is drag::

    a_thrust - dv/dt = c v + b      (horizontal; least squares over windows of ``window_s``)

The windows' averages keep the attitude's vibration and the velocity's noise out.  The constant ``b``
takes what is not drag of the vehicle's own speed: a steady wind (``c (v - w)``) and the attitude
estimate's tilt bias (stock PX4 SIH: 2 degrees, 0.37 m/s^2 along the flight; without ``b`` it read a drag
of 1.2-1.3 /s where SIH's ground truth gives 1.00).  The estimate is used only between ``min_drag_1_s``
and ``max_drag_1_s``; below (an emulator that reports no tilt) there is nothing to feed forward.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

G_M_S2 = 9.80665
"""Standard gravity [m/s^2] (PX4's CONSTANTS_ONE_G)."""


def thrust_accel_ne(q_wxyz: tuple[float, float, float, float]) -> tuple[float, float] | None:
    """Horizontal (north, east) acceleration of the thrust [m/s^2] at attitude ``q_wxyz`` (body FRD to
    local NED, w first), when the thrust holds the vehicle's weight (level flight): ``-g b_h / b_d`` with
    ``b`` the body z axis in NED (PX4's ``_accelerationControl`` inverted).  None for a quaternion that is
    not a rotation or a vehicle tilted 60 degrees or more (no level flight)."""
    w, x, y, z = q_wxyz
    n2 = w * w + x * x + y * y + z * z
    if not (math.isfinite(n2) and abs(n2 - 1.0) < 0.05):
        return None
    bn = 2.0 * (x * z + w * y)
    be = 2.0 * (y * z - w * x)
    bd = 1.0 - 2.0 * (x * x + y * y)
    if bd < 0.5:
        return None
    return (-G_M_S2 * bn / bd, -G_M_S2 * be / bd)


@dataclass(frozen=True)
class DragConfig:
    """How the agent identifies its vehicle's drag and feeds it forward (``AgentConfig.drag``)."""

    feedforward: bool = True
    """Send ``c_hat`` times the velocity setpoint as its acceleration feed-forward (PX4 only: ArduPilot's
    guided mode reads a setpoint's acceleration as the rate of its velocity target, not as a force)."""
    switch_on_speed_m_s: float = 0.3
    """The feed-forward comes on at a horizontal setpoint no faster than this [m/s] (a hover, a wait): switched
    on at speed ``v`` it would add ``c v`` to what PX4's integrator already holds."""
    window_s: float = 1.0
    """Length of one regression window [s]."""
    min_windows: int = 20
    """Windows needed before the estimate is used."""
    min_spread_m_s: float = 0.5
    """... and the RMS spread of their velocities needed (the fit's excitation) [m/s]."""
    max_accel_m_s2: float = 0.8
    """A window in which the vehicle accelerated more than this is left out [m/s^2]: a hard turn or stop,
    where a velocity that lags the attitude (a GNSS receiver's: up to 0.5 m/s in stock PX4 SIH's exit turn)
    would weigh most."""
    forget_s: float = 120.0
    """Forgetting time of the least squares [s]: the estimate follows a changed vehicle (a payload)."""
    min_drag_1_s: float = 0.1
    """Below this the vehicle shows no drag to feed forward (no tilt reported) [1/s]."""
    max_drag_1_s: float = 2.5
    """The estimate is bounded here [1/s] (a multirotor's linear drag is 0.2-1.5 /s)."""
    fresh_s: float = 0.3
    """An attitude older than this is not used [s]."""

    def __post_init__(self) -> None:
        for name in ("switch_on_speed_m_s", "window_s", "min_spread_m_s", "max_accel_m_s2", "forget_s",
                     "min_drag_1_s", "max_drag_1_s", "fresh_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"drag: {name} must be finite and > 0, is {v!r}")
        if self.min_windows < 1:
            raise ValueError(f"drag: min_windows must be >= 1, is {self.min_windows!r}")
        if self.min_drag_1_s >= self.max_drag_1_s:
            raise ValueError(f"drag: min_drag_1_s ({self.min_drag_1_s}) must be below max_drag_1_s "
                             f"({self.max_drag_1_s})")


class DragEstimator:
    """Least squares of ``a_thrust - dv/dt = c v + b`` over windows of flight (module docstring)."""

    def __init__(self, cfg: DragConfig = DragConfig()) -> None:
        self.cfg = cfg
        self.windows = 0
        """Windows that entered the estimate."""
        self._sw = 0.0  # forgetting-weighted sums: windows, v, f, |v|^2, f . v
        self._sv = [0.0, 0.0]
        self._sf = [0.0, 0.0]
        self._svv = 0.0
        self._sfv = 0.0
        self._w: tuple[float, tuple[float, float]] | None = None  # window start: (t, velocity)
        self._sum_a = [0.0, 0.0]
        self._sum_v = [0.0, 0.0]
        self._n = 0

    def observe(self, t_s: float, vel_ne_m_s: tuple[float, float], acc_thrust_ne_m_s2: tuple[float, float]) -> None:
        """One tick of flight: the horizontal velocity (NE) [m/s] and the thrust's acceleration [m/s^2]."""
        if self._w is None:
            self._start(t_s, vel_ne_m_s)
        t0, v0 = self._w
        dt = t_s - t0
        if dt < 0.0:
            self._start(t_s, vel_ne_m_s)
            dt = 0.0
        self._sum_a[0] += acc_thrust_ne_m_s2[0]
        self._sum_a[1] += acc_thrust_ne_m_s2[1]
        self._sum_v[0] += vel_ne_m_s[0]
        self._sum_v[1] += vel_ne_m_s[1]
        self._n += 1
        if dt < self.cfg.window_s:
            return
        an, ae = (vel_ne_m_s[0] - v0[0]) / dt, (vel_ne_m_s[1] - v0[1]) / dt
        if dt <= 3.0 * self.cfg.window_s and math.hypot(an, ae) <= self.cfg.max_accel_m_s2:
            k = 1.0 / self._n
            vn, ve = self._sum_v[0] * k, self._sum_v[1] * k
            fn, fe = self._sum_a[0] * k - an, self._sum_a[1] * k - ae
            keep = math.exp(-dt / self.cfg.forget_s)
            self._sw = keep * self._sw + 1.0
            self._sv = [keep * self._sv[0] + vn, keep * self._sv[1] + ve]
            self._sf = [keep * self._sf[0] + fn, keep * self._sf[1] + fe]
            self._svv = keep * self._svv + vn * vn + ve * ve
            self._sfv = keep * self._sfv + fn * vn + fe * ve
            self.windows += 1
        self._start(t_s, vel_ne_m_s)

    def gap(self) -> None:
        """No sample this tick (no fresh attitude, not flying): the window in progress is dropped."""
        self._w = None

    def _start(self, t_s: float, vel_ne_m_s: tuple[float, float]) -> None:
        self._w = (t_s, vel_ne_m_s)
        self._sum_a = [0.0, 0.0]
        self._sum_v = [0.0, 0.0]
        self._n = 0

    @property
    def speed_spread_m_s(self) -> float:
        """RMS deviation of the windows' velocities from their mean [m/s]: the excitation the fit has."""
        if self._sw <= 0.0:
            return 0.0
        sv0, sv1 = self._sv
        return math.sqrt(max(0.0, self._svv - (sv0 * sv0 + sv1 * sv1) / self._sw) / self._sw)

    @property
    def raw_drag_1_s(self) -> float | None:
        """The least-squares estimate [1/s] before its bounds; None before ``min_windows`` windows with a
        speed spread of ``min_spread_m_s``."""
        if self.windows < self.cfg.min_windows or self.speed_spread_m_s < self.cfg.min_spread_m_s:
            return None
        sv0, sv1 = self._sv
        sf0, sf1 = self._sf
        den = self._svv - (sv0 * sv0 + sv1 * sv1) / self._sw
        return (self._sfv - (sf0 * sv0 + sf1 * sv1) / self._sw) / den

    @property
    def offset_ne_m_s2(self) -> tuple[float, float] | None:
        """The fit's constant part ``b`` [m/s^2] (an attitude estimate's tilt bias, a wind's drag); None
        while the drag is not identified."""
        c = self.raw_drag_1_s
        if c is None:
            return None
        return ((self._sf[0] - c * self._sv[0]) / self._sw, (self._sf[1] - c * self._sv[1]) / self._sw)

    @property
    def drag_1_s(self) -> float | None:
        """The drag to feed forward [1/s]: the estimate bounded by ``max_drag_1_s``; None before it is
        identified or below ``min_drag_1_s``."""
        c = self.raw_drag_1_s
        if c is None or c < self.cfg.min_drag_1_s:
            return None
        return min(c, self.cfg.max_drag_1_s)


class DragFeedForward:
    """One agent's drag: identified while it flies, fed forward once it is and the vehicle is slow.

    It comes on only at a setpoint of at most ``DragConfig.switch_on_speed_m_s``: in flight PX4's integrator
    holds the drag's thrust already, and the feed-forward added to it would speed the vehicle up until the
    integrator unwound (stock PX4: seconds; a one-PX4 pass whose feed-forward came on at speed scored a
    ground-truth velocity nRMSE of 0.095, against 0.066-0.072 without).  Once on, it stays on."""

    def __init__(self, cfg: DragConfig = DragConfig()) -> None:
        self.cfg = cfg
        self.estimator = DragEstimator(cfg)
        """The least squares (``DragEstimator``)."""
        self.on = False
        """The feed-forward has come on."""

    def for_setpoint(self, sp_ne_m_s: tuple[float, float], autopilot: str | None) -> tuple[float | None, bool]:
        """(The drag to feed forward with this setpoint [1/s] or None, whether it came on just now).  Only
        identified, asked for, and for a PX4: ArduPilot's guided mode reads a setpoint's acceleration as its
        velocity target's rate, not as a force."""
        c = self.estimator.drag_1_s
        if c is None or not self.cfg.feedforward or autopilot != "px4":
            return None, False
        if self.on:
            return c, False
        if math.hypot(sp_ne_m_s[0], sp_ne_m_s[1]) > self.cfg.switch_on_speed_m_s:
            return None, False
        self.on = True
        return c, True
