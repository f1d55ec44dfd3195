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

import enum
import math
from dataclasses import dataclass
from typing import Callable

Vec = tuple[float, float, float]
FieldFn = Callable[[float, float, float], "Vec | None"]
"""Map-frame command at a point (the selected command mode), None outside the map's CVs."""
DeviationFn = Callable[[Vec, Vec], Vec]
"""The ``kinetic`` mode's deviation of this agent at a map-frame point, given the field's unit direction
there [m/s] (zero outside the CVs; ``ScalarField.deviation``)."""

ZERO: Vec = (0.0, 0.0, 0.0)


class KineticAxes(str, enum.Enum):
    """Along which axes a streamline-tracking agent flies its ``kinetic`` deviation (``TrackingConfig.kinetic_axes``)."""

    CROSS_STREAM = "cross-stream"
    """Across the stream only, at the deviation's full magnitude (``cross_stream``): the swarm's velocity
    spread, and so the pressure analogue, is the fitted one, while every vehicle crosses each slice at the
    field's speed, so its transit time, and so the swarm's density, is the staggered field's."""
    ISOTROPIC = "isotropic"
    """The deviation as drawn, uniform on the sphere (``fisc-sim run``'s agents): its along-stream part
    slows some vehicles where the spread exceeds the field's speed (inlet and outlet: spread 0.55 m/s,
    speed 0.43 m/s), which linger there or turn upstream and leave the map through the inlet."""


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
    gnss_bias_time_constant_s: float = 0.5
    """Low-pass time constant of the horizontal bias where the GNSS receiver's velocity gives it
    (``ParcelTracker.observe``) [s]: shorter than ``bias_time_constant_s``, as that velocity is measured
    directly (noise about 0.1 m/s RMS at 8 Hz on PX4 SIH) and the estimator's error changes within
    a second as the vehicle accelerates."""
    lookahead_reach_m: float = 1.0
    """The look-ahead samples the field at most this far ahead and extrapolates the secant beyond it
    (a look-ahead of ``lookahead_s * speed`` metres would otherwise jump past a velocity peak) [m]."""
    resync_distance_m: float = 1.0
    """An along-stream offset between vehicle and parcel left after the slides larger than this (a
    parcel blocked at a staircase corner while its vehicle flew on) moves the parcel to the vehicle [m]."""
    feedforward_gain: float = 1.0
    """Multiplies the field's command: the inverse of the vehicle's steady velocity gain (an autopilot
    whose velocity loop settles below its setpoint, e.g. against drag, flies ``gain * setpoint``)."""
    feedforward_auto: bool = False
    """Replace ``feedforward_gain`` by the inverse of the steady gain identified in flight and learnt
    again through the pass (``--feedforward-gain auto``; with ``--lookahead auto``).  Off by default:
    the gain below one that the take-off's step fit reads on a stock PX4 (0.78-0.86) is its PI velocity
    loop catching up, not a steady shortfall.  With the velocity-estimate bias learnt from the GNSS
    velocity, six stock PX4 (SIH) flew a ground-truth velocity nRMSE of 0.054-0.083 with the gain at 1
    (two runs, twelve passes), 0.072-0.119 with it learnt (feed-forward 1.1-1.3: too fast wherever the
    duct slows them); the stock hexacopter 0.067 and 0.077 (2026-12-06, docs/deployment.md)."""
    online_gain_time_s: float = 3.0
    """With ``feedforward_auto``: forgetting time of the steady velocity gain learnt again through the
    pass (``identify.OnlineGain``), which then sets ``feedforward_gain`` [s]; 0: off (the gain
    identified before the pass is kept)."""
    kinetic_axes: KineticAxes = KineticAxes.CROSS_STREAM
    """How the ``kinetic`` deviation is flown (``--kinetic-axes``).  Emulated, eight vehicles looping 300 s
    beside a real fleet (``fisc-sim emulate --plant px4-sih-loop --fleet-mode --estimate-error --mode kinetic``,
    2026-12-07): across the stream, profile density r 0.96, pressure r 0.81, closest approach 1.00 m;
    isotropic, 0.76, 0.86 and 0.50 m (docs/emulation.md)."""

    def __post_init__(self) -> None:
        for name in ("gain_1_s", "integral_gain_1_s2", "max_correction_m_s", "max_integral_m_s", "lookahead_s",
                     "bias_time_constant_s", "max_bias_m_s", "online_gain_time_s", "gnss_bias_time_constant_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"tracking: {name} must be finite and >= 0, is {v!r}")
        for name in ("lookahead_reach_m", "resync_distance_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"tracking: {name} must be finite and > 0, is {v!r}")
        if not (math.isfinite(self.feedforward_gain) and 0.5 <= self.feedforward_gain <= 2.0):
            raise ValueError(f"tracking: feedforward_gain must be in [0.5, 2], is {self.feedforward_gain!r}")
        try:
            object.__setattr__(self, "kinetic_axes", KineticAxes(self.kinetic_axes))
        except ValueError:
            raise ValueError(f"tracking: kinetic_axes must be one of {[k.value for k in KineticAxes]}, "
                             f"is {self.kinetic_axes!r}") from None


def cross_stream(dev: Vec, t: Vec) -> Vec:
    """The deviation ``dev`` turned across the stream of unit direction ``t``: its along-stream part
    removed and the rest scaled back to ``|dev|`` (``KineticAxes.CROSS_STREAM``).  A deviation whose
    cross-stream part is at most 1e-9 m/s gives zero; ``t`` zero (no field direction) leaves
    ``dev`` as it is.  Each magnitude is kept, so the swarm's mean squared deviation, the fitted spread,
    is too; a direction uniform on the sphere becomes uniform on the circle across ``t``."""
    d0, d1, d2 = dev
    t0, t1, t2 = t
    a = d0 * t0 + d1 * t1 + d2 * t2
    c0, c1, c2 = d0 - a * t0, d1 - a * t1, d2 - a * t2
    cn = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    if cn <= 1e-9:
        return ZERO
    k = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) / cn
    return (c0 * k, c1 * k, c2 * k)


def _unit(a: Vec) -> Vec:
    """``a / |a|`` (as ``a * (1 / |a|)``); the zero vector for a (near) zero ``a``."""
    a0, a1, a2 = a
    n = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    if n > 1e-9:
        k = 1.0 / n
        return (a0 * k, a1 * k, a2 * k)
    return ZERO


def saturate(v: Vec, limit: float) -> Vec:
    """``v`` scaled down to length ``limit`` if longer."""
    v0, v1, v2 = v
    n = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    if n > limit and n > 0.0:
        k = limit / n
        return (v0 * k, v1 * k, v2 * k)
    return v


GNSS_FRESH_S = 0.5
"""A GNSS velocity older than this [s] is not used for the bias (``ParcelTracker.observe``): the
position's rate is, as without a receiver's velocity."""


class ParcelTracker:
    """One agent's streamline parcel.  ``reset`` where the vehicle enters the map, then ``step``; ``resume``
    after an interruption (a hold, a geofence return) to fly back onto the same streamline."""

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

    def observe(self, t_s: float, pos_m: Vec, vel_m_s: Vec, gnss_xy_m_s: tuple[float, float] | None = None) -> None:
        """Update the velocity-estimate bias from one reported fix (call every tick while flying).

        ``t_s`` is the fix's own time (the autopilot's clock where the link gives it, else the
        receive time), not the tick's: a fix seen again by the next tick (``dt`` 0) is skipped.
        ``gnss_xy_m_s``: the GNSS receiver's own horizontal velocity (map x, y; a fresh GPS_RAW_INT),
        whose difference from the reported velocity is then the horizontal bias.  The position's rate
        sees only what the estimator's GNSS fusion pulls its position by: stock PX4 SIH's EKF2 weighs
        GNSS velocity so lightly that its velocity strayed 0.33 m/s RMS from SIH's ground truth (up to
        0.9 m/s) while the receiver's stayed within 0.10 m/s RMS of it, without a measurable delay
        (``tests/faults`` seed 7, 2026-12-05; docs/deployment.md)."""
        tau = self.cfg.bias_time_constant_s
        prev, self._prev = self._prev, (t_s, pos_m)
        if tau <= 0.0 or prev is None:
            return
        dt = t_s - prev[0]
        if not 0.0 < dt <= 0.5:
            return
        q, inv_dt = prev[1], 1.0 / dt
        # the rate of the reported position minus the reported velocity, written out on floats
        d0 = (pos_m[0] - q[0]) * inv_dt - vel_m_s[0]
        d1 = (pos_m[1] - q[1]) * inv_dt - vel_m_s[1]
        d2 = (pos_m[2] - q[2]) * inv_dt - vel_m_s[2]
        if math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) > 2.0 * self.cfg.max_bias_m_s:
            return  # a position jump (an estimator reset), not a velocity bias
        k = kh = min(1.0, dt / tau)
        if gnss_xy_m_s is not None:
            d0, d1 = gnss_xy_m_s[0] - vel_m_s[0], gnss_xy_m_s[1] - vel_m_s[1]
            tau_h = self.cfg.gnss_bias_time_constant_s
            kh = min(1.0, dt / tau_h) if tau_h > 0.0 else 1.0
        b0, b1, b2 = self.bias_m_s
        self.bias_m_s = saturate((b0 + kh * (d0 - b0), b1 + kh * (d1 - b1), b2 + k * (d2 - b2)), self.cfg.max_bias_m_s)

    def reset(self, pos_m: Vec, t_s: float) -> None:
        """A new parcel at the vehicle (entering the map, a takeover)."""
        self.parcel_m, self._t_s, self._v_last = pos_m, t_s, None

    def resume(self, t_s: float) -> None:
        """Keep the parcel (its streamline) after an interruption that ends at ``t_s``: the next ``step``
        slides it abreast of the vehicle again and pulls the vehicle back onto that streamline; the time of
        the interruption is not integrated (a parcel left more than ``resync_distance_m`` along the stream
        starts again at the vehicle, as always).  Without a parcel, the next ``step`` starts one."""
        if self.parcel_m is not None:
            self._t_s = t_s

    def clear(self) -> None:
        """Forget the parcel; the next ``step`` starts a new one at the vehicle."""
        self.parcel_m, self._t_s, self._v_last = None, None, None

    def _field_at(self, p: Vec, field: FieldFn) -> Vec | None:
        v = field(*p)
        if v is None and p[0] >= self.x_outlet_m:
            return self._v_last  # downstream of the outlet: the parcel coasts out
        return v

    def _slide(self, p: Vec, d: Vec, field: FieldFn) -> tuple[Vec, Vec | None]:
        """``p + d``; if that lands outside the map's CVs, only its axial part; if that does too, ``p``.
        With it, the field there (``_field_at``, sampled once) where it moved; None where it stayed at ``p``."""
        nxt = (p[0] + d[0], p[1] + d[1], p[2] + d[2])
        v = self._field_at(nxt, field)
        if v is not None:
            return nxt, v
        nxt = (p[0] + d[0], p[1] + 0.0, p[2] + 0.0)  # + 0.0 as the vector sum gives it (a -0.0 turns +0.0)
        v = self._field_at(nxt, field)
        if v is not None:
            return nxt, v
        return p, None

    def _ahead(self, p: Vec, v: Vec, field: FieldFn) -> Vec:
        """The field ``lookahead_s`` ahead along the streamline: ``v(p + L v)`` within the reach,
        the secant ``v + (v(p + d t) - v) L |v| / d`` beyond it (d = reach)."""
        la = self.cfg.lookahead_s
        if la <= 0.0:
            return v
        vx, vy, vz = v
        n = math.sqrt(vx * vx + vy * vy + vz * vz)
        dist = la * n
        if dist <= 1e-9:
            return v
        d = min(dist, self.cfg.lookahead_reach_m)
        if n > 1e-9:
            k = 1.0 / n
            ux, uy, uz = vx * k, vy * k, vz * k
        else:
            ux = uy = uz = 0.0
        ahead = self._field_at((p[0] + d * ux, p[1] + d * uy, p[2] + d * uz), field)
        if ahead is None:
            return v
        f = dist / d
        return (vx + f * (ahead[0] - vx), vy + f * (ahead[1] - vy), vz + f * (ahead[2] - vz))

    def step(self, t_s: float, pos_m: Vec, field: FieldFn, deviation: DeviationFn | None = None) -> Vec | None:
        """Move the parcel abreast of the vehicle and return the velocity command (map frame).

        ``deviation`` (the ``kinetic`` mode): the agent's persistent deviation at a point, given the
        field's direction there (``ScalarField.deviation``).  The parcel then is a kinetic particle: its cross-stream part
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
        # the vector algebra written out on floats (issue 40: the tick's hot path); each line computes
        # exactly what the vector helpers' form (a + k b, k a, a . b) did, operation for operation
        x0, x1, x2 = pos_m
        for _ in range(2):
            t0, t1, t2 = _unit(v)
            a = (x0 - p[0]) * t0 + (x1 - p[1]) * t1 + (x2 - p[2]) * t2
            p, v_p = self._slide(p, (t0 * a, t1 * a, t2 * a), field)
            v = (v_p if v_p is not None else self._field_at(p, field)) or v  # the field at p, sampled once
        t0, t1, t2 = _unit(v)
        if abs((x0 - p[0]) * t0 + (x1 - p[1]) * t1 + (x2 - p[2]) * t2) > cfg.resync_distance_m:
            v_here = field(x0, x1, x2)
            if v_here is not None:  # the parcel is stuck behind a corner: a new parcel at the vehicle
                p, v = pos_m, v_here
                t0, t1, t2 = _unit(v)
        self._v_last = v
        v_ff = self._ahead(p, v, field)
        l0 = l1 = l2 = 0.0
        if deviation is not None:
            dev = deviation(p, (t0, t1, t2))
            a = dev[0] * t0 + dev[1] * t1 + dev[2] * t2
            c0, c1, c2 = dev[0] - a * t0, dev[1] - a * t1, dev[2] - a * t2
            if dt > 0.0:
                p = self._slide(p, (c0 * dt, c1 * dt, c2 * dt), field)[0]
            v_ff = (v_ff[0] + dev[0], v_ff[1] + dev[1], v_ff[2] + dev[2])
            # a vehicle lagging by about lookahead_s trails its deviated parcel by cross * lookahead_s:
            # the position feedback aims there, so it does not amplify the deviation
            la = cfg.lookahead_s
            l0, l1, l2 = c0 * la, c1 * la, c2 * la
        self.parcel_m = p
        e0, e1, e2 = (p[0] - l0) - x0, (p[1] - l1) - x1, (p[2] - l2) - x2
        a = e0 * t0 + e1 * t1 + e2 * t2
        e0, e1, e2 = e0 - a * t0, e1 - a * t1, e2 - a * t2  # across the stream only: no along-stream catch-up
        if dt > 0.0 and deviation is None:  # a kinetic agent's offsets are its deviations' lag, not a bias
            k = cfg.integral_gain_1_s2 * dt
            i0, i1, i2 = self.integral_m_s
            self.integral_m_s = saturate((i0 + k * e0, i1 + k * e1, i2 + k * e2), cfg.max_integral_m_s)
        g = cfg.gain_1_s
        i0, i1, i2 = self.integral_m_s
        c0, c1, c2 = saturate((e0 * g + i0, e1 * g + i1, e2 * g + i2), cfg.max_correction_m_s)
        f = cfg.feedforward_gain
        b0, b1, b2 = self.bias_m_s
        return ((v_ff[0] * f + c0) - b0, (v_ff[1] * f + c1) - b1, (v_ff[2] * f + c2) - b2)
