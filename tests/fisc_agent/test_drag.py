"""The drag identified from the vehicle's attitude (``fisc_agent.flight.drag``): the thrust's horizontal
acceleration from a quaternion, the windowed least squares on a simulated vehicle, and its bounds."""

from __future__ import annotations

import math

import pytest

from fisc_agent.flight.drag import G_M_S2, DragConfig, DragEstimator, DragFeedForward, thrust_accel_ne


def _tilt(axis: str, angle_rad: float) -> tuple[float, float, float, float]:
    """The quaternion (w, x, y, z) of a rotation by ``angle_rad`` about body x (roll) or y (pitch)."""
    c, s = math.cos(angle_rad / 2), math.sin(angle_rad / 2)
    return (c, s, 0.0, 0.0) if axis == "roll" else (c, 0.0, s, 0.0)


def test_level_gives_no_horizontal_thrust():
    assert thrust_accel_ne((1.0, 0.0, 0.0, 0.0)) == (0.0, 0.0)


def test_nose_down_pitch_accelerates_north_and_right_roll_east():
    a = math.radians(10.0)
    an, ae = thrust_accel_ne(_tilt("pitch", -a))  # FRD: a negative pitch is nose down
    assert an == pytest.approx(G_M_S2 * math.tan(a)) and ae == pytest.approx(0.0, abs=1e-12)
    an, ae = thrust_accel_ne(_tilt("roll", a))
    assert ae == pytest.approx(G_M_S2 * math.tan(a)) and an == pytest.approx(0.0, abs=1e-12)


def test_yaw_turns_the_tilt_with_the_vehicle():
    """Heading east (yaw 90 degrees), nose down accelerates east."""
    a, yaw = math.radians(8.0), math.radians(90.0)
    qy = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
    qp = _tilt("pitch", -a)
    w1, x1, y1, z1 = qy
    w2, x2, y2, z2 = qp
    q = (w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
         w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2)
    an, ae = thrust_accel_ne(q)
    assert ae == pytest.approx(G_M_S2 * math.tan(a)) and an == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("q", [(0.0, 0.0, 0.0, 0.0), (2.0, 0.0, 0.0, 0.0), (math.nan, 0.0, 0.0, 0.0)])
def test_not_a_rotation_gives_none(q):
    assert thrust_accel_ne(q) is None


def test_tilt_boundary_sixty_degrees():
    """Level flight is assumed: a vehicle tilted 60 degrees or more gives nothing (body z's down part < 0.5)."""
    assert thrust_accel_ne(_tilt("roll", math.radians(59.9))) is not None
    assert thrust_accel_ne(_tilt("roll", math.radians(60.1))) is None


def _fly(c_1_s: float, seconds: float, est: DragEstimator, wind_ne=(0.0, 0.0), dt=0.05, noise=None,
         bias_ne=(0.0, 0.0)):
    """A vehicle with drag ``c (v - w)`` whose thrust follows a speed profile that changes direction."""
    v = [0.0, 0.0]
    t = 0.0
    while t < seconds:
        heading = 0.1 * t
        target = 1.5 + 0.5 * math.sin(0.7 * t)
        vt = (target * math.cos(heading), target * math.sin(heading))
        a_dyn = (2.0 * (vt[0] - v[0]), 2.0 * (vt[1] - v[1]))  # what the loop asks to accelerate
        thrust = (a_dyn[0] + c_1_s * (v[0] - wind_ne[0]) + bias_ne[0], a_dyn[1] + c_1_s * (v[1] - wind_ne[1]) + bias_ne[1])
        v = [v[0] + a_dyn[0] * dt, v[1] + a_dyn[1] * dt]
        t += dt
        meas = thrust if noise is None else (thrust[0] + noise(), thrust[1] + noise())
        est.observe(t, (v[0], v[1]), meas)
    return est


@pytest.mark.parametrize("c", [0.3, 1.0, 1.8])
def test_the_drag_of_a_simulated_vehicle_is_identified(c):
    est = _fly(c, 30.0, DragEstimator())
    assert est.drag_1_s == pytest.approx(c, rel=0.05)


def test_vibration_averages_out_in_the_windows():
    import random

    rng = random.Random(3)
    est = _fly(1.0, 60.0, DragEstimator(), noise=lambda: rng.gauss(0.0, 0.5))
    assert est.drag_1_s == pytest.approx(1.0, rel=0.1)


def test_a_tilt_bias_and_a_steady_wind_do_not_bias_the_drag():
    """Stock PX4 SIH's attitude estimate leans 2 degrees (0.37 m/s^2) along the flight: the fit's constant
    takes it, as it takes a steady wind's drag ``-c w``."""
    est = _fly(1.0, 60.0, DragEstimator(), wind_ne=(0.8, -0.5), bias_ne=(0.37, 0.2))
    assert est.drag_1_s == pytest.approx(1.0, rel=0.05)
    bn, be = est.offset_ne_m_s2
    assert bn == pytest.approx(0.37 - 0.8, abs=0.05) and be == pytest.approx(0.2 + 0.5, abs=0.05)


def _steady_windows(est: DragEstimator, speeds_m_s, c_1_s: float = 1.0) -> None:
    """One 1 s window at 20 Hz per speed, the velocity steady in it (north), the thrust ``c v``."""
    for k, v in enumerate(speeds_m_s):
        for i in range(21):
            est.observe(2.0 * k + i * 0.05, (v, 0.0), (c_1_s * v, 0.0))
        est.gap()


def test_nothing_before_min_windows_and_then_the_estimate():
    speeds = [0.5, 1.5] * 4
    est = DragEstimator(DragConfig(min_windows=8, min_spread_m_s=0.1))
    _steady_windows(est, speeds[:7])
    assert est.windows == 7 and est.drag_1_s is None and est.raw_drag_1_s is None and est.offset_ne_m_s2 is None
    est = DragEstimator(DragConfig(min_windows=8, min_spread_m_s=0.1))
    _steady_windows(est, speeds)
    assert est.windows == 8 and est.drag_1_s == pytest.approx(1.0)


def test_a_hover_gives_no_excitation():
    """Windows at one velocity count, but their spread is nil: no estimate (two unknowns, one velocity)."""
    est = DragEstimator()
    for i in range(800):
        est.observe(i * 0.05, (0.2, 0.1), (0.3, 0.1))
    assert est.windows >= 20 and est.speed_spread_m_s == pytest.approx(0.0, abs=1e-6) and est.drag_1_s is None


def test_the_spread_boundary():
    """Windows alternating between two speeds 2s apart have an RMS spread of s."""
    for s_m_s, identified in ((0.49, False), (0.51, True)):
        est = DragEstimator(DragConfig(min_windows=4, min_spread_m_s=0.5, forget_s=1e9))
        _steady_windows(est, [1.0 + (s_m_s if k % 2 else -s_m_s) for k in range(8)])
        assert est.speed_spread_m_s == pytest.approx(s_m_s, rel=1e-6)
        assert (est.drag_1_s is not None) is identified


def test_no_tilt_reported_means_no_drag_to_feed_forward():
    """An emulator that reports its vehicle level: the estimate is about 0 (no thrust for the drag), below
    ``min_drag_1_s``: nothing is fed forward."""
    est = DragEstimator()
    v = 0.0
    for i in range(1200):
        t = i * 0.05
        v = 1.5 + 0.9 * math.sin(0.4 * t)
        est.observe(t, (v, 0.3 * math.cos(0.3 * t)), (0.0, 0.0))
    assert est.raw_drag_1_s is not None and abs(est.raw_drag_1_s) < 0.1 and est.drag_1_s is None


@pytest.mark.parametrize("accel, counted", [(0.79, True), (0.81, False)])
def test_a_hard_manoeuvre_window_is_left_out(accel, counted):
    est = DragEstimator(DragConfig(max_accel_m_s2=0.8))
    for i in range(21):
        t = i * 0.05
        est.observe(t, (1.0 + accel * t, 0.0), (accel + 1.0, 0.0))
    assert est.windows == (1 if counted else 0)


def test_the_bounds_of_what_is_fed_forward():
    cfg = DragConfig(min_drag_1_s=0.1, max_drag_1_s=2.5)
    assert _fly(0.09, 30.0, DragEstimator(cfg)).drag_1_s is None
    assert _fly(0.12, 30.0, DragEstimator(cfg)).drag_1_s == pytest.approx(0.12, rel=0.05)
    assert _fly(3.0, 30.0, DragEstimator(cfg)).drag_1_s == 2.5


def test_a_gap_drops_the_window_in_progress():
    est = DragEstimator()
    est.observe(0.0, (1.0, 0.0), (1.0, 0.0))
    est.gap()
    est.observe(5.0, (1.0, 0.0), (1.0, 0.0))  # starts a new window: no 5 s window of a 1 s length
    assert est.windows == 0
    est.observe(6.0, (1.0, 0.0), (1.0, 0.0))
    assert est.windows == 1


def test_a_late_window_is_not_counted():
    """A window stretched beyond 3x its length (a stalled loop) is dropped, not fitted."""
    est = DragEstimator()
    est.observe(0.0, (1.0, 0.0), (1.0, 0.0))
    est.observe(3.01, (1.0, 0.0), (1.0, 0.0))
    assert est.windows == 0
    est.observe(6.0, (1.0, 0.0), (1.0, 0.0))
    assert est.windows == 1


def test_config_is_checked():
    with pytest.raises(ValueError, match="window_s"):
        DragConfig(window_s=0.0)
    with pytest.raises(ValueError, match="min_windows"):
        DragConfig(min_windows=0)
    with pytest.raises(ValueError, match="below max_drag_1_s"):
        DragConfig(min_drag_1_s=2.0, max_drag_1_s=2.0)


def _identified(cfg: DragConfig = DragConfig()) -> DragFeedForward:
    ff = DragFeedForward(cfg)
    _fly(1.0, 60.0, ff.estimator)
    assert ff.estimator.drag_1_s == pytest.approx(1.0, rel=0.05)
    return ff


def test_the_feedforward_comes_on_only_at_a_slow_setpoint_and_stays_on():
    ff = _identified()
    s = ff.cfg.switch_on_speed_m_s
    assert ff.for_setpoint((s + 1e-6, 0.0), "px4") == (None, False) and not ff.on      # just too fast
    c, now = ff.for_setpoint((0.0, s), "px4")                                          # at the bound: on
    assert c == ff.estimator.drag_1_s and now and ff.on
    assert ff.for_setpoint((2.0, 1.0), "px4") == (c, False)                            # and it stays on at speed


def test_no_feedforward_before_the_drag_is_identified_for_ardupilot_or_when_off():
    ff = DragFeedForward()
    assert ff.for_setpoint((0.0, 0.0), "px4") == (None, False)
    assert _identified().for_setpoint((0.0, 0.0), "ardupilot") == (None, False)
    assert _identified().for_setpoint((0.0, 0.0), None) == (None, False)
    assert _identified(DragConfig(feedforward=False)).for_setpoint((0.0, 0.0), "px4") == (None, False)
