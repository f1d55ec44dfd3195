"""The emulated autopilot's estimate error (``sim.autopilot.estimate_error``) and how the vehicle flies it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.autopilot.estimate_error import (ACF_E_FOLD, PX4_SIH_ESTIMATE_ERROR, EstimateError, EstimateErrorParams,
                                          gauss_markov_step, smooth_gauss_markov_step)
from sim.autopilot.personalities import PX4, FlightMode
from sim.autopilot.vehicle import Vehicle
from sim.autopilot.vehicle_types import Setpoint, VehicleConfig


def test_a_gauss_markov_step_decays_by_exp_minus_dt_over_tau_and_adds_the_stationary_share_of_noise():
    tau, sd = np.array([2.0]), np.array([0.5])
    # no noise: pure decay, exp(-dt/tau)
    assert gauss_markov_step(np.array([1.0]), 2.0, tau, sd, np.array([0.0]))[0] == pytest.approx(math.exp(-1.0))
    # from zero, one unit draw: sd sqrt(1 - exp(-2 dt/tau))
    assert gauss_markov_step(np.array([0.0]), 2.0, tau, sd, np.array([1.0]))[0] == pytest.approx(
        0.5 * math.sqrt(1.0 - math.exp(-2.0)))
    # dt >> tau: the draw alone, at the stationary spread
    assert gauss_markov_step(np.array([1.0]), 1e3, tau, sd, np.array([1.0]))[0] == pytest.approx(0.5)


def test_the_smooth_step_lags_its_driving_process_by_its_time_constant():
    t, sd = np.array([2.0]), np.array([0.5])
    u, x = smooth_gauss_markov_step(np.array([0.0]), np.array([1.0]), 2.0, t, sd, np.array([0.0]))
    assert (u[0], x[0]) == (0.0, pytest.approx(math.exp(-1.0)))  # no drive: x decays by exp(-dt/T)
    u, x = smooth_gauss_markov_step(np.array([0.3]), np.array([0.0]), 1e3, t, sd, np.array([1.0]))
    assert x[0] == pytest.approx(0.3 * 2.0)  # a held drive u: x settles at u T
    assert u[0] == pytest.approx(0.5 * math.sqrt(2.0) / 2.0)  # u's own spread: sd sqrt(2) / T


def _acf(x: np.ndarray, lag: int) -> float:
    x = x - x.mean()
    return float(np.dot(x[:-lag], x[lag:]) / np.dot(x, x))


def test_the_error_holds_its_spread_correlation_time_and_rate_over_a_long_run():
    p = EstimateErrorParams(velocity_sd_ned_m_s=(0.2, 0.3, 0.0), velocity_tau_s=(1.0, 3.0, 1.0),
                            position_sd_ned_m=(0.2, 0.2, 0.2), position_tau_s=(5.0, 5.0, 5.0), seed=3)
    e, dt = EstimateError(p), 0.05
    v, x = np.empty((40_000, 3)), np.empty((40_000, 3))
    for k in range(v.shape[0]):
        e.step(dt)
        v[k], x[k] = e.velocity_ned_m_s, e.position_ned_m
    rate_sd = 0.2 * ACF_E_FOLD / 5.0  # the position error's rate: sd / T
    for axis in range(3):
        assert x[:, axis].std() == pytest.approx(0.2, rel=0.15), axis
        assert _acf(x[:, axis], int(round(5.0 / dt))) == pytest.approx(math.exp(-1.0), abs=0.08), axis
        # smooth paths: the rate's spread is sd / T (a first-order process's grows as dt shrinks)
        assert (np.diff(x[:, axis]) / dt).std() == pytest.approx(rate_sd, rel=0.15), axis
    # the velocity error: the position error's rate plus an independent part making up its spread
    assert v[:, 0].std() == pytest.approx(0.2, rel=0.15) and v[:, 1].std() == pytest.approx(0.3, rel=0.15)
    w = v[:-1] - np.diff(x, axis=0) / dt  # the rate at a step moves the position over the next
    assert w[:, 0].std() == pytest.approx(math.sqrt(0.2 ** 2 - rate_sd ** 2), rel=0.15)
    assert _acf(w[:, 1], int(round(3.0 / dt))) == pytest.approx(math.exp(-1.0), abs=0.1)
    # an axis asking less than the position's rate: the rate alone, no independent part
    assert np.abs(w[:, 2]).max() < 0.01 and v[:, 2].std() == pytest.approx(rate_sd, rel=0.15)


def test_the_same_seed_gives_the_same_sequence_and_another_seed_another():
    a, b, c = (EstimateError(EstimateErrorParams(seed=s)) for s in (1, 1, 2))
    for e in (a, b, c):
        e.step(0.1)
    assert a.velocity_ned_m_s == b.velocity_ned_m_s and a.velocity_ned_m_s != c.velocity_ned_m_s


@pytest.mark.parametrize("field, value, match", [
    ("velocity_sd_ned_m_s", (0.1, -0.1, 0.1), ">= 0"),
    ("velocity_tau_s", (1.0, 0.0, 1.0), "> 0"),
    ("position_tau_s", (1.0, 1.0), "3 finite numbers"),
    ("position_sd_ned_m", (0.1, math.nan, 0.1), "3 finite numbers"),
])
def test_bad_parameters_are_refused_by_name(field, value, match):
    with pytest.raises(ValueError, match=f"{field}.*{match}"):
        EstimateErrorParams(**{field: value})


def _flying(estimate_error):
    v = Vehicle(PX4, VehicleConfig(start_ned_m=(0.0, 0.0, -5.0), estimate_error=estimate_error))
    v.set_setpoint(Setpoint(velocity_ned_m_s=(1.0, 0.0, 0.0)), 0.0)
    assert v.set_mode(FlightMode.OFFBOARD, 0.0).result == 0
    return v


def test_the_vehicle_holds_its_estimate_at_the_setpoint_and_reports_it_while_the_truth_differs():
    err = EstimateErrorParams(velocity_sd_ned_m_s=(0.0, 0.3, 0.0), velocity_tau_s=(1.0, 1e6, 1.0),
                              position_sd_ned_m=(0.0, 0.2, 0.0), position_tau_s=(1.0, 1e6, 1.0), seed=5)
    v = _flying(err)
    t = 0.0
    while t < 20.0:
        t += 0.5
        v.set_setpoint(Setpoint(velocity_ned_m_s=(1.0, 0.0, 0.0)), t)
    st = v.snapshot()
    e_v, e_p = v._est.velocity_ned_m_s[1], v._est.position_ned_m[1]  # nearly constant: tau 1e6 s
    assert abs(e_v) > 0.05 and abs(e_p) > 0.02  # this seed's draw is not tiny
    # the estimate is flown: estimated east velocity at the setpoint 0, the truth -e
    assert st.reported_velocity_ned_m_s[1] == pytest.approx(0.0, abs=2e-3)
    assert st.velocity_ned_m_s[1] == pytest.approx(-e_v, abs=2e-3)
    assert st.reported_position_ned_m[1] - st.position_ned_m[1] == pytest.approx(e_p, abs=1e-9)
    assert st.reported_velocity_ned_m_s[0] == pytest.approx(st.velocity_ned_m_s[0])  # sd 0 on north


def test_without_an_estimate_error_the_report_is_the_truth():
    v = _flying(None)
    v.step(3.0)
    st = v.snapshot()
    assert st.estimate_position_ned_m is None and st.reported_position_ned_m == st.position_ned_m
    assert st.reported_velocity_ned_m_s == st.velocity_ned_m_s


def test_the_hold_modes_do_not_fly_the_error():
    v = Vehicle(PX4, VehicleConfig(start_ned_m=(0.0, 0.0, -5.0), estimate_error=PX4_SIH_ESTIMATE_ERROR))
    v.step(10.0)  # airborne start: the hold mode, zero velocity on the truth
    assert v.mode == FlightMode.LOITER and np.allclose(v.snapshot().velocity_ned_m_s, 0.0, atol=1e-9)
    assert v.snapshot().reported_velocity_ned_m_s != v.snapshot().velocity_ned_m_s


def test_the_position_messages_carry_the_estimate_and_gps_raw_int_the_receivers_truth():
    from dataclasses import replace

    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from fisc_agent.flight.frames import GeodeticAnchor
    from sim.autopilot.framing import Encoder
    from sim.autopilot.telemetry import TelemetryBuilder

    v = _flying(None)
    v.step(2.0)
    truth = v.snapshot()
    st = replace(truth, estimate_position_ned_m=(1.0, 2.0, -3.0), estimate_velocity_ned_m_s=(0.5, -0.25, 0.125))
    anchor = GeodeticAnchor(47.4, 8.5, 500.0, 0.0)
    tb = TelemetryBuilder(Encoder(1, 1).mav, PX4, anchor, 1, lambda: 0.0)
    lp = tb.local_position_ned(st)
    assert (lp.x, lp.y, lp.z, lp.vx, lp.vy, lp.vz) == pytest.approx((1.0, 2.0, -3.0, 0.5, -0.25, 0.125))
    fast = mavlink.MAVLink_local_position_ned_message.unpacker.unpack(tb.local_position_ned_payload(st))
    assert fast[1:] == pytest.approx((1.0, 2.0, -3.0, 0.5, -0.25, 0.125))
    gp = tb.global_position_int(st)
    lat, lon, alt = anchor.ned_to_geodetic(1.0, 2.0, -3.0)
    assert (gp.lat, gp.lon, gp.vx, gp.vy, gp.vz) == (round(lat * 1e7), round(lon * 1e7), 50, -25, 12)
    od = tb.odometry(st)
    assert (od.x, od.y, od.z) == pytest.approx((1.0, 2.0, -3.0))
    raw = tb.gps_raw_int(st)  # the receiver: the truth's ground speed, not the estimate's
    assert raw.vel == round(math.hypot(*truth.velocity_ned_m_s[:2]) * 100)
    assert raw.lat == round(anchor.ned_to_geodetic(*truth.position_ned_m)[0] * 1e7)
