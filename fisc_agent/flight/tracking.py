"""Streamline tracking (pure): each vehicle stays on its own streamline of the command field.

Flying the map's velocity open loop (the paper's Algorithm 1) lets every velocity error
accumulate into position: an estimator bias, wind, a heading error or the autopilot's lag turn
into a cross-stream drift that nothing corrects, and on a real PX4 the vehicle leaves the duct
within seconds.  Here each agent carries a *parcel* ``p``: a point on the streamline through
the place where the vehicle entered the map, kept abreast of the vehicle.  Every tick the
parcel slides along the field's direction ``t`` at the parcel by the vehicle's along-stream
offset, ``p <- p + ((x - p) . t) t`` (twice, so curved streamlines are followed), which keeps
it on its streamline and level with the vehicle.  The setpoint is the field's velocity there,
evaluated ``lookahead_s`` ahead (``v_ahead``, cancelling a first-order lag of that time constant;
see ``_ahead`` for how far it samples) and scaled
by ``feedforward_gain`` (cancelling a steady velocity shortfall), plus a PI pull across the
stream towards the parcel; the integral learns a steady velocity bias of the vehicle, such as an
estimator's heading error or a wind::

    e = (p - x) - ((p - x) . t) t   (its part across the stream)
    v_cmd = feedforward_gain * v_ahead(p)
            + sat(gain_1_s * e + sat(integral_gain_1_s2 * int(e dt), max_integral_m_s), max_correction_m_s)
            - b

``b`` is the bias of the autopilot's velocity estimate, seen from the vehicle's own data: the
autopilot's position estimate is anchored to GNSS while its velocity estimate can drift (PX4 SIH
shows up to 1 m/s with a 10-15 degree heading error early in a flight), and its velocity loop
holds the *estimated* velocity at the setpoint.  ``b`` is the low-passed difference between the
rate of change of the reported position (between successive fixes, on the autopilot's clock where
the link gives it) and the reported velocity (time constant
``bias_time_constant_s``), bounded by ``max_bias_m_s``; subtracting it makes the vehicle's real
velocity, not its estimate, follow the field.

Along the stream there is no position feedback on purpose: the swarm's velocity field should be
the field's own at every place, not a catch-up.  The offset is projected across the field's
direction at the parcel even where a slide could not bring the parcel level (a staircase corner),
and a parcel left more than ``resync_distance_m`` behind or ahead starts again at the vehicle.
Where a slide would carry the parcel into a place without a CV upstream of the outlet (a
staircase wall cube), the axial part of the slide is kept and the cross-stream part dropped;
downstream of the outlet the parcel coasts with the last velocity.

Only the agent's own position and the map are used: no inter-agent messages.  With
``gain_1_s = 0`` the mission does not track at all: it flies the simulator's own command
function (``fisc_agent.map.lookup.flight_command``) at the vehicle's position, open loop (the paper's
Algorithm 1 with the ``mean`` mode and no look-ahead).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

Vec = tuple[float, float, float]
FieldFn = Callable[[float, float, float], "Vec | None"]
"""Map-frame command at a point (the selected command mode), None outside the map's CVs."""
DeviationFn = Callable[[Vec], Vec]
"""The ``kinetic`` mode's deviation of this agent at a map-frame point [m/s] (zero outside the CVs)."""

ZERO: Vec = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class TrackingConfig:
    """How an agent tracks its streamline (``AgentConfig.tracking``)."""

    gain_1_s: float = 1.2
    """Cross-stream position feedback gain [1/s]; 0: no tracking (the mission flies the field open loop)."""
    integral_gain_1_s2: float = 0.5
    """Cross-stream integral gain [1/s^2]: learns a steady velocity bias (estimator, wind).  Not while
    kinetic deviations are flown: the offsets are then mostly the vehicle's lag behind its deviated
    parcel, and integrating them adds a random velocity (emulated swarm: throat pressure 2.6x that of
    ``fisc-sim run`` with it, 2.2x without)."""
    max_correction_m_s: float = 1.5
    """Largest feedback velocity added to the field's command [m/s]."""
    max_integral_m_s: float = 1.0
    """Bound of the integral term (anti-windup) [m/s]."""
    lookahead_s: float = 0.0
    """Evaluate the field this far ahead along the streamline (lag compensation) [s]."""
    bias_time_constant_s: float = 1.0
    """Low-pass time constant of the velocity-estimate bias ``b`` [s]; 0 switches the correction off."""
    max_bias_m_s: float = 1.5
    """Bound of the bias correction [m/s]."""
    lookahead_reach_m: float = 1.0
    """The look-ahead samples the field at most this far ahead and extrapolates the secant beyond it
    (a look-ahead of ``lookahead_s * speed`` metres would otherwise jump past a velocity peak) [m]."""
    resync_distance_m: float = 1.0
    """An along-stream offset between vehicle and parcel left after the slides larger than this (a
    parcel blocked at a staircase corner while its vehicle flew on) moves the parcel to the vehicle [m]."""
    feedforward_gain: float = 1.0
    """Multiplies the field's command: the inverse of the vehicle's steady velocity gain (an autopilot
    whose velocity loop settles below its setpoint, e.g. against drag, flies ``gain * setpoint``)."""
    online_gain_time_s: float = 3.0
    """With the response identified in flight (``--lookahead auto``): forgetting time of the steady
    velocity gain learnt again through the pass (``identify.OnlineGain``), which then sets
    ``feedforward_gain`` [s]; 0: off (the gain identified before the pass is kept)."""

    def __post_init__(self) -> None:
        for name in ("gain_1_s", "integral_gain_1_s2", "max_correction_m_s", "max_integral_m_s", "lookahead_s",
                     "bias_time_constant_s", "max_bias_m_s", "online_gain_time_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"tracking: {name} must be finite and >= 0, is {v!r}")
        for name in ("lookahead_reach_m", "resync_distance_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"tracking: {name} must be finite and > 0, is {v!r}")
        if not (math.isfinite(self.feedforward_gain) and 0.5 <= self.feedforward_gain <= 2.0):
            raise ValueError(f"tracking: feedforward_gain must be in [0.5, 2], is {self.feedforward_gain!r}")


def _add(a: Vec, b: Vec, k: float = 1.0) -> Vec:
    return (a[0] + k * b[0], a[1] + k * b[1], a[2] + k * b[2])


def _scale(a: Vec, k: float) -> Vec:
    return (a[0] * k, a[1] * k, a[2] * k)


def _dot(a: Vec, b: Vec) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _norm(a: Vec) -> float:
    return math.sqrt(_dot(a, a))


def _unit(a: Vec) -> Vec:
    """``a / |a|``; the zero vector for a (near) zero ``a``."""
    n = _norm(a)
    return _scale(a, 1.0 / n) if n > 1e-9 else ZERO


def saturate(v: Vec, limit: float) -> Vec:
    """``v`` scaled down to length ``limit`` if longer."""
    n = _norm(v)
    if n > limit and n > 0.0:
        return _scale(v, limit / n)
    return v


class ParcelTracker:
    """One agent's streamline parcel.  ``reset`` where the vehicle enters the map, then ``step``."""

    def __init__(self, cfg: TrackingConfig, x_outlet_m: float = math.inf) -> None:
        self.cfg = cfg
        """The tracking settings (replaced whole when the response is identified in flight)."""
        self.x_outlet_m = x_outlet_m
        """Past this map-frame x the parcel has left through the outlet and keeps its velocity."""
        self.parcel_m: Vec | None = None
        """The parcel, map frame [m]; None before the first step."""
        self.integral_m_s: Vec = ZERO
        """The integral term: the velocity bias learnt so far [m/s] (kept across parcels)."""
        self.bias_m_s: Vec = ZERO
        """The velocity-estimate bias learnt so far [m/s] (kept across parcels)."""
        self._v_last: Vec | None = None
        self._t_s: float | None = None
        self._prev: tuple[float, Vec] | None = None

    def observe(self, t_s: float, pos_m: Vec, vel_m_s: Vec) -> None:
        """Update the velocity-estimate bias from one reported fix (call every tick while flying).

        ``t_s`` is the fix's own time (the autopilot's clock where the link gives it, else the
        receive time), not the tick's: a fix seen again by the next tick (``dt`` 0) is skipped."""
        tau = self.cfg.bias_time_constant_s
        prev, self._prev = self._prev, (t_s, pos_m)
        if tau <= 0.0 or prev is None:
            return
        dt = t_s - prev[0]
        if not 0.0 < dt <= 0.5:
            return
        rate = _scale(_add(pos_m, prev[1], -1.0), 1.0 / dt)
        if _norm(_add(rate, vel_m_s, -1.0)) > 2.0 * self.cfg.max_bias_m_s:
            return  # a position jump (an estimator reset), not a velocity bias
        k = min(1.0, dt / tau)
        self.bias_m_s = saturate(_add(self.bias_m_s, _add(_add(rate, vel_m_s, -1.0), self.bias_m_s, -1.0), k),
                                 self.cfg.max_bias_m_s)

    def reset(self, pos_m: Vec, t_s: float) -> None:
        """A new parcel at the vehicle (entering the map, resuming after a hold)."""
        self.parcel_m, self._t_s, self._v_last = pos_m, t_s, None

    def clear(self) -> None:
        """Forget the parcel; the next ``step`` starts a new one at the vehicle."""
        self.parcel_m, self._t_s, self._v_last = None, None, None

    def _field_at(self, p: Vec, field: FieldFn) -> Vec | None:
        v = field(*p)
        if v is None and p[0] >= self.x_outlet_m:
            return self._v_last  # downstream of the outlet: the parcel coasts out
        return v

    def _slide(self, p: Vec, d: Vec, field: FieldFn) -> Vec:
        """``p + d``; if that lands outside the map's CVs, only its axial part; if that does too, ``p``."""
        for step in (d, (d[0], 0.0, 0.0)):
            nxt = _add(p, step)
            if self._field_at(nxt, field) is not None:
                return nxt
        return p

    def _ahead(self, p: Vec, v: Vec, field: FieldFn) -> Vec:
        """The field ``lookahead_s`` ahead along the streamline: ``v(p + L v)`` within the reach,
        the secant ``v + (v(p + d t) - v) L |v| / d`` beyond it (d = reach)."""
        la = self.cfg.lookahead_s
        if la <= 0.0:
            return v
        dist = la * _norm(v)
        if dist <= 1e-9:
            return v
        d = min(dist, self.cfg.lookahead_reach_m)
        ahead = self._field_at(_add(p, _unit(v), d), field)
        if ahead is None:
            return v
        return _add(v, _add(ahead, v, -1.0), dist / d)

    def step(self, t_s: float, pos_m: Vec, field: FieldFn, deviation: DeviationFn | None = None) -> Vec | None:
        """Move the parcel abreast of the vehicle and return the velocity command (map frame).

        ``deviation`` (the ``kinetic`` mode): the agent's persistent deviation at a point
        (``ScalarField.deviation``).  The parcel then is a kinetic particle: its cross-stream part
        moves the parcel across the stream (so the vehicle's position feedback pulls towards a
        deviated parcel instead of cancelling the deviation), and the whole deviation is added to the
        feed-forward; along the stream it is flown open loop, like the field.

        None when the field has no command at the parcel; the mission then applies its geofence
        to the vehicle's own position.
        """
        cfg = self.cfg
        if self.parcel_m is None or self._t_s is None:
            self.reset(pos_m, t_s)
        p = self.parcel_m
        dt = max(0.0, t_s - self._t_s)
        self._t_s = t_s
        v = self._field_at(p, field)
        if v is None:
            return None
        for _ in range(2):
            t_hat = _unit(v)
            p = self._slide(p, _scale(t_hat, _dot(_add(pos_m, p, -1.0), t_hat)), field)
            v = self._field_at(p, field) or v
        t_hat = _unit(v)
        if abs(_dot(_add(pos_m, p, -1.0), t_hat)) > cfg.resync_distance_m:
            v_here = field(*pos_m)
            if v_here is not None:  # the parcel is stuck behind a corner: a new parcel at the vehicle
                p, v = pos_m, v_here
                t_hat = _unit(v)
        self._v_last = v
        v_ff = self._ahead(p, v, field)
        lag_m: Vec = ZERO
        if deviation is not None:
            dev = deviation(p)
            cross = _add(dev, t_hat, -_dot(dev, t_hat))
            if dt > 0.0:
                p = self._slide(p, _scale(cross, dt), field)
            v_ff = _add(v_ff, dev)
            # a vehicle lagging by about lookahead_s trails its deviated parcel by cross * lookahead_s:
            # the position feedback aims there, so it does not amplify the deviation
            lag_m = _scale(cross, cfg.lookahead_s)
        self.parcel_m = p
        e = _add(_add(p, lag_m, -1.0), pos_m, -1.0)
        e = _add(e, t_hat, -_dot(e, t_hat))  # across the stream only: no along-stream catch-up
        if dt > 0.0 and deviation is None:  # a kinetic agent's offsets are its deviations' lag, not a bias
            self.integral_m_s = saturate(_add(self.integral_m_s, e, cfg.integral_gain_1_s2 * dt),
                                         cfg.max_integral_m_s)
        corr = saturate(_add(_scale(e, cfg.gain_1_s), self.integral_m_s), cfg.max_correction_m_s)
        return _add(_add(_scale(v_ff, cfg.feedforward_gain), corr), self.bias_m_s, -1.0)
