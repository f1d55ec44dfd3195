"""Streamline tracking (fisc_agent.flight.tracking) on analytic fields, on a simulated clock."""

import math

import numpy as np
import pytest

from fisc_agent.flight.tracking import KineticAxes, ParcelTracker, TrackingConfig, cross_stream


def uniform(x, y, z):
    return (2.0, 0.0, 0.0) if abs(y) <= 1.0 and abs(z) <= 1.0 and 0.0 <= x < 10.0 else None


def linear(x, y, z):
    """u = 1 + x along x: acceleration u du/dx = 1 + x."""
    return (1.0 + x, 0.0, 0.0) if 0.0 <= x < 10.0 else None


def test_cross_stream_error_is_pulled_back_and_along_stream_is_not():
    cfg = TrackingConfig(gain_1_s=1.0, integral_gain_1_s2=0.0, bias_time_constant_s=0.0)
    tr = ParcelTracker(cfg)
    tr.reset((0.0, 0.0, 0.0), 0.0)
    v = tr.step(0.05, (1.0, 0.3, -0.2), uniform)
    assert tr.parcel_m == pytest.approx((1.0, 0.0, 0.0))          # slid abreast of the vehicle
    assert v == pytest.approx((2.0, -0.3, 0.2))                   # pull across, none along
    v = tr.step(0.10, (4.0, 0.0, 0.0), uniform)                   # far ahead along the stream
    assert v == pytest.approx((2.0, 0.0, 0.0)) and tr.parcel_m == pytest.approx((4.0, 0.0, 0.0))


def test_correction_and_integral_are_bounded_and_the_integral_learns_a_steady_offset():
    cfg = TrackingConfig(gain_1_s=1.0, integral_gain_1_s2=0.5, max_correction_m_s=0.5, max_integral_m_s=0.3,
                         bias_time_constant_s=0.0)
    tr = ParcelTracker(cfg)
    tr.reset((0.0, 0.0, 0.0), 0.0)
    t = 0.0
    for _ in range(200):  # a vehicle stuck 0.2 m off its streamline for 10 s
        t += 0.05
        v = tr.step(t, (1.0, 0.2, 0.0), uniform)
    assert tr.integral_m_s[1] == pytest.approx(-0.3)              # anti-windup bound
    assert math.hypot(v[1], v[2]) == pytest.approx(0.5)           # total correction bound
    assert v[0] == pytest.approx(2.0)


def test_lookahead_on_a_linear_field_adds_lag_times_acceleration_within_and_beyond_its_reach():
    for reach in (5.0, 0.2):
        tr = ParcelTracker(TrackingConfig(lookahead_s=0.5, lookahead_reach_m=reach, bias_time_constant_s=0.0))
        tr.reset((1.0, 0.0, 0.0), 0.0)
        v = tr.step(0.0, (1.0, 0.0, 0.0), linear)                 # u = 2, a = u du/dx = 2
        assert v[0] == pytest.approx(2.0 + 0.5 * 2.0)


def test_feedforward_gain_scales_the_field_not_the_correction():
    cfg = TrackingConfig(gain_1_s=1.0, integral_gain_1_s2=0.0, bias_time_constant_s=0.0, feedforward_gain=1.25)
    tr = ParcelTracker(cfg)
    tr.reset((0.0, 0.0, 0.0), 0.0)
    assert tr.step(0.05, (1.0, 0.1, 0.0), uniform) == pytest.approx((2.5, -0.1, 0.0))


def test_velocity_estimate_bias_is_learnt_from_position_against_reported_velocity():
    tr = ParcelTracker(TrackingConfig(bias_time_constant_s=1.0))
    t, y = 0.0, 0.0
    for _ in range(200):  # moves 0.5 m/s east while reporting 0 east
        tr.observe(t, (0.0, y, 0.0), (0.0, 0.0, 0.0))
        t, y = t + 0.05, y + 0.5 * 0.05
    assert tr.bias_m_s == pytest.approx((0.0, 0.5, 0.0), abs=1e-3)
    tr.reset((1.0, 0.0, 0.0), t)
    v = tr.step(t + 0.05, (1.0, 0.0, 0.0), uniform)
    assert v[1] == pytest.approx(-0.5, abs=1e-3)                  # flies against the bias
    # a position jump (an estimator reset, a moved vehicle) is not a velocity: the bias stays
    tr.observe(t + 0.1, (1.0, 2.5, 0.0), (0.0, 0.0, 0.0))
    assert tr.bias_m_s == pytest.approx((0.0, 0.5, 0.0), abs=1e-3)


def test_a_slide_into_a_wall_cube_keeps_its_axial_part_and_the_parcel_coasts_past_the_outlet():
    def duct(x, y, z):  # flow angled towards +y, wall at y = 0.5
        return (1.0, 1.0, 0.0) if y <= 0.5 and 0.0 <= x < 5.0 else None

    tr = ParcelTracker(TrackingConfig(bias_time_constant_s=0.0), x_outlet_m=5.0)
    tr.reset((1.0, 0.45, 0.0), 0.0)
    tr.step(0.05, (1.3, 0.45, 0.0), duct)
    assert tr.parcel_m[1] <= 0.5 and tr.parcel_m[0] > 1.0
    tr.reset((4.9, 0.0, 0.0), 1.0)
    tr.step(1.05, (4.9, 0.0, 0.0), duct)
    assert tr.step(1.10, (5.6, 0.7, 0.0), duct) is not None      # downstream of the outlet: coasts
    assert tr.parcel_m[0] > 5.0


def test_a_parcel_blocked_at_a_corner_never_pulls_back_along_the_stream_and_resyncs_when_far_behind():
    """Flow along +x; beyond x = 2 only the strip 0.5 <= y <= 1 is open (a staircase step).  The
    parcel on the axis cannot slide past the step while its vehicle flies on through the strip."""
    def step_duct(x, y, z):
        open_ = 0.0 <= x < 2.0 and abs(y) <= 1.0 or 2.0 <= x < 6.0 and 0.5 <= y <= 1.0
        return (1.0, 0.0, 0.0) if open_ and abs(z) <= 1.0 else None

    cfg = TrackingConfig(gain_1_s=1.0, integral_gain_1_s2=0.5, bias_time_constant_s=0.0, resync_distance_m=1.0)
    tr = ParcelTracker(cfg)
    tr.reset((1.9, 0.0, 0.0), 0.0)
    v = tr.step(0.1, (2.5, 0.7, 0.0), step_duct)                 # 0.6 m past the blocked parcel
    assert tr.parcel_m == pytest.approx((1.9, 0.0, 0.0))
    assert v[0] == pytest.approx(1.0)                            # the field's speed: no pull backwards
    assert v[1] == pytest.approx(-0.7 - 0.5 * 0.1 * 0.7)         # the cross-stream pull stays
    assert tr.integral_m_s[0] == 0.0
    v = tr.step(0.2, (3.2, 0.7, 0.0), step_duct)                 # 1.3 m past it: a new parcel at the vehicle
    assert tr.parcel_m == pytest.approx((3.2, 0.7, 0.0))
    assert v[0] == pytest.approx(1.0)


def test_the_integral_does_not_learn_while_kinetic_deviations_are_flown():
    cfg = TrackingConfig(gain_1_s=1.0, integral_gain_1_s2=0.5, bias_time_constant_s=0.0)
    kinetic, plain = ParcelTracker(cfg), ParcelTracker(cfg)
    for tr in (kinetic, plain):
        tr.reset((1.0, 0.0, 0.0), 0.0)
    for k in range(1, 41):  # a vehicle 0.2 m off its parcel for 2 s
        kinetic.step(0.05 * k, (1.0, 0.2, 0.0), uniform, lambda p, t: (0.0, 0.0, 0.3))
        plain.step(0.05 * k, (1.0, 0.2, 0.0), uniform)
    assert kinetic.integral_m_s == (0.0, 0.0, 0.0)
    assert plain.integral_m_s[1] < -0.1


def test_config_rejects_nonsense():
    with pytest.raises(ValueError, match="gain_1_s"):
        TrackingConfig(gain_1_s=-1.0)
    with pytest.raises(ValueError, match="feedforward_gain"):
        TrackingConfig(feedforward_gain=math.nan)
    with pytest.raises(ValueError, match="resync_distance_m"):
        TrackingConfig(resync_distance_m=0.0)
    with pytest.raises(ValueError, match=r"kinetic_axes must be one of \['cross-stream', 'isotropic'\], is 'radial'"):
        TrackingConfig(kinetic_axes="radial")
    assert TrackingConfig(kinetic_axes="isotropic").kinetic_axes is KineticAxes.ISOTROPIC
    assert TrackingConfig().kinetic_axes is KineticAxes.CROSS_STREAM


@pytest.mark.parametrize("dev, t, expected", [
    ((0.0, 0.4, 0.0), (1.0, 0.0, 0.0), (0.0, 0.4, 0.0)),           # across already: unchanged
    ((0.3, 0.4, 0.0), (1.0, 0.0, 0.0), (0.0, 0.5, 0.0)),           # along part removed, |dev| 0.5 kept
    ((-0.3, 0.0, -0.4), (1.0, 0.0, 0.0), (0.0, 0.0, -0.5)),        # upstream and down: down at full speed
    ((0.3, 0.4, 0.0), (0.0, 1.0, 0.0), (0.5, 0.0, 0.0)),           # the stream along y
    ((0.0, 0.3, 0.4), (0.0, 0.0, 1.0), (0.0, 0.5, 0.0)),           # the stream along z
    ((0.6, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 0.0)),           # all along the stream: none across
    ((-0.6, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 0.0)),          # all against it: none either
    ((0.6, 2e-9, 0.0), (1.0, 0.0, 0.0), (0.0, 0.6, 0.0)),          # just above the 1e-9 m/s floor: full speed
    ((0.6, 1e-9, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 0.0)),          # at it: none
    ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 0.0)),           # no deviation
    ((0.3, 0.4, 0.0), (0.0, 0.0, 0.0), (0.3, 0.4, 0.0)),           # no field direction: as drawn
])
def test_cross_stream_removes_the_along_stream_part_and_keeps_the_magnitude(dev, t, expected):
    assert cross_stream(dev, t) == pytest.approx(expected, abs=1e-12)


def test_cross_stream_keeps_the_mean_squared_deviation_of_directions_uniform_on_the_sphere():
    """The fitted spread is the rms of the deviation: turned across a stream it stays, and it is shared
    equally by the two cross-stream axes (uniform on the circle)."""
    rng = np.random.default_rng(3)
    d = rng.normal(size=(20000, 3))
    d *= 0.5 / np.linalg.norm(d, axis=1, keepdims=True)
    t = (0.6, 0.8, 0.0)
    out = np.array([cross_stream(tuple(v), t) for v in d])
    assert np.mean((out ** 2).sum(axis=1)) == pytest.approx(0.25, rel=1e-9)
    assert abs(out @ np.array(t)).max() < 1e-12
    assert np.mean(out[:, 2] ** 2) == pytest.approx(0.125, rel=0.03)


def test_a_kinetic_deviation_moves_the_parcel_across_the_stream_and_is_flown_as_feedforward():
    """The parcel of a kinetic agent is a kinetic particle: the cross-stream part of its deviation
    moves it across the stream (so the position feedback does not cancel the deviation), the whole
    deviation joins the feed-forward, and the feedback aims at where a vehicle lagging by
    ``lookahead_s`` behind the deviated parcel should be."""
    cfg = TrackingConfig(gain_1_s=1.0, integral_gain_1_s2=0.0, bias_time_constant_s=0.0, lookahead_s=0.5)
    tr = ParcelTracker(cfg)
    tr.reset((1.0, 0.0, 0.0), 0.0)
    dev = (0.3, 0.4, 0.0)
    v = tr.step(0.1, (1.0, 0.0, 0.0), uniform, lambda p, t: dev)
    assert tr.parcel_m == pytest.approx((1.0, 0.04, 0.0))        # 0.4 m/s across for 0.1 s, none along
    # feed-forward 2 + 0.3 along, 0.4 across; feedback to parcel - 0.4 * 0.5 across = -0.16 m
    assert v == pytest.approx((2.3, 0.4 - 0.16, 0.0))
    t, pos = 0.1, (1.0, 0.0, 0.0)
    for _ in range(20):                                          # a vehicle that flies the command
        t += 0.05
        v = tr.step(t, pos, uniform, lambda p, t: dev)
        pos = (pos[0] + 0.05 * v[0], pos[1] + 0.05 * v[1], pos[2])
    assert pos[1] > 0.3 and tr.parcel_m[1] > pos[1]               # the deviation is flown, not cancelled
    assert tr.step(t + 0.05, pos, uniform) == pytest.approx((2.0, tr.parcel_m[1] - pos[1], 0.0))  # none: field only


def test_the_tracker_gives_the_deviation_the_field_direction_at_the_parcel():
    """With ``KineticAxes.CROSS_STREAM`` (``ScalarField.deviation`` turns the deviation with ``cross_stream``)
    the deviation's along-stream part is not flown: the vehicle crosses each slice at the field's speed, as
    without deviations, and deviates across the stream at the deviation's full magnitude."""
    cfg = TrackingConfig(gain_1_s=1.0, integral_gain_1_s2=0.0, bias_time_constant_s=0.0, lookahead_s=0.5)
    tr = ParcelTracker(cfg)
    tr.reset((1.0, 0.0, 0.0), 0.0)
    seen = []

    def turned(p, t):
        seen.append(t)
        return cross_stream((-0.3, 0.4, 0.0), t)                 # upstream and across, turned across

    v = tr.step(0.1, (1.0, 0.0, 0.0), uniform, turned)
    assert seen[-1] == pytest.approx((1.0, 0.0, 0.0))            # the uniform field's direction
    assert tr.parcel_m == pytest.approx((1.0, 0.05, 0.0))        # 0.5 m/s across for 0.1 s
    # feed-forward 2 along (not 1.7), 0.5 across; feedback to parcel - 0.5 * 0.5 across = -0.2 m
    assert v == pytest.approx((2.0, 0.5 - 0.2, 0.0))
    v = tr.step(0.2, (1.2, 0.0, 0.0), uniform, lambda p, t: cross_stream((-2.5, 0.0, 0.0), t))
    assert v[0] == pytest.approx(2.0)                            # straight upstream: nothing flown


def test_resume_keeps_the_streamline_and_does_not_integrate_the_interruption():
    cfg = TrackingConfig(gain_1_s=1.0, integral_gain_1_s2=0.5, bias_time_constant_s=0.0)
    tr = ParcelTracker(cfg)
    tr.reset((1.0, 0.0, 0.0), 0.0)
    tr.step(0.05, (1.0, 0.0, 0.0), uniform)
    tr.resume(10.05)                                              # a 10 s hold that left the vehicle 0.4 m off
    v = tr.step(10.10, (1.2, 0.4, 0.0), uniform)
    assert tr.parcel_m == pytest.approx((1.2, 0.0, 0.0))          # abreast again, on the old streamline
    assert tr.integral_m_s[1] == pytest.approx(-0.5 * 0.05 * 0.4)  # one tick's worth, not the hold's 10 s
    assert v == pytest.approx((2.0, -0.4 + tr.integral_m_s[1], 0.0))
    tr.clear()
    tr.resume(20.0)                                               # nothing to keep: the next step starts one
    assert tr.parcel_m is None
    tr.step(20.05, (2.0, 0.4, 0.0), uniform)
    assert tr.parcel_m == pytest.approx((2.0, 0.4, 0.0))


@pytest.mark.parametrize("resolved, explicit, wall_known, expected", [
    ("kinetic", None, True, ("staggered", True)),       # the map's recommendation, its real wall known: deviations
    ("kinetic", None, False, ("staggered", False)),     # no wall to turn them before: the staggered field alone
    ("kinetic", "kinetic", True, ("staggered", True)),  # asked for: the deviations ride on the parcel
    ("kinetic", "kinetic", False, ("staggered", True)),  # asked for without a wall: turned at the staircase
    ("staggered", "staggered", True, ("staggered", False)),
    ("staggered", None, True, ("staggered", False)),
    ("slot", None, True, ("slot", False)),
    ("mean", "mean", False, ("mean", False)),
])
def test_a_tracking_agent_flies_kinetic_deviations_where_it_knows_the_wall_or_when_asked_for(resolved, explicit,
                                                                                           wall_known, expected):
    from fisc_agent.flight.point_command import tracked_mode

    assert tracked_mode(resolved, explicit, wall_known) == expected
