"""In-flight identification of the velocity response (fisc_agent.flight.identify) on simulated data."""

import numpy as np
import pytest

from fisc_agent.flight.identify import (FEEDFORWARD_MAX, FEEDFORWARD_MIN, ONLINE_MIN_SPEED_M_S, OnlineGain, ResponseRecorder,
                                       feedforward_from_gain, fit_response)


def simulate(lag_s, dead_s, gain, h=0.05, seconds=20.0, seed=0, noise=0.0):
    """Two axes of a first-order lag with dead time and gain, driven by piecewise-constant setpoints."""
    rng = np.random.default_rng(seed)
    n = int(seconds / h)
    t = np.arange(n) * h
    u = np.repeat(rng.uniform(-2.0, 2.0, size=(n // 40 + 1, 2)), 40, axis=0)[:n]
    d = int(round(dead_s / h))
    a = np.exp(-h / lag_s)
    v = np.zeros((n, 2))
    for k in range(n - 1):
        v[k + 1] = a * v[k] + (1 - a) * gain * u[max(k - d, 0)]
    return t, u, v + rng.normal(0.0, noise, size=v.shape)


@pytest.mark.parametrize("lag, dead, gain", [(0.58, 0.0, 1.0), (0.7, 0.15, 0.8), (0.35, 0.1, 0.97)])
def test_recovers_lag_dead_time_and_gain(lag, dead, gain):
    resp = fit_response(*simulate(lag, dead, gain))
    assert resp is not None
    assert resp.lag_s == pytest.approx(lag, rel=0.05)
    assert resp.dead_time_s == pytest.approx(dead, abs=0.026)
    assert resp.gain == pytest.approx(gain, rel=0.02)
    assert resp.lookahead_s == pytest.approx(lag + dead, rel=0.05)
    assert resp.feedforward_gain == pytest.approx(min(1.5, 1 / gain), rel=0.02)
    assert resp.rise_time_s == pytest.approx(dead + lag * np.log(9), rel=0.05)


def test_the_feedforward_takes_only_the_shortfall_both_halves_of_the_window_agree_on():
    """A vehicle whose response is gain 1 in one half and 0.8 in the other (real PX4 SITL joins fit
    this inconsistently): the whole window says ~0.9, the feed-forward stays 1."""
    t, u, v = simulate(0.5, 0.1, 1.0, seed=1)
    _, _, v_short = simulate(0.5, 0.1, 0.8, seed=1)
    half = len(t) // 2
    v = np.concatenate([v[:half], v_short[half:]])
    resp = fit_response(t, u, v)
    assert 0.8 < resp.gain < 0.97
    assert resp.gain_bound == pytest.approx(1.0, abs=0.03)
    assert resp.feedforward_gain == pytest.approx(1.0, abs=0.03)
    short = fit_response(*simulate(0.5, 0.1, 0.8, seed=1))                   # consistently short: cancelled
    assert short.gain_bound == pytest.approx(0.8, rel=0.02)
    assert short.feedforward_gain == pytest.approx(1.25, rel=0.02)


def test_noisy_measurements_still_give_the_lag_within_fifteen_percent():
    resp = fit_response(*simulate(0.7, 0.1, 0.85, noise=0.02))
    assert resp.lookahead_s == pytest.approx(0.8, rel=0.15)


def test_refuses_without_excitation_or_samples():
    t, u, v = simulate(0.5, 0.0, 1.0)
    assert fit_response(t, np.zeros_like(u), np.zeros_like(v)) is None     # hovering: nothing to learn
    assert fit_response(t[:30], u[:30], v[:30]) is None                       # too short
    rec = ResponseRecorder()
    assert rec.fit() is None
    for k in range(len(t)):
        rec.add(t[k], tuple(u[k]), tuple(v[k]))
    assert rec.fit().lag_s == pytest.approx(0.5, rel=0.05)


# ---- the gain learnt again through the pass (OnlineGain) ---------------------------------------------
def _duct_pass(gain, lag_s, h=0.05, seconds=20.0):
    """A duct-like pass: the setpoint speeds up from 0.6 to 1.7 m/s and back (accelerations a lag
    turns into a shortfall), flown by a first-order lag of ``lag_s`` with steady ``gain``."""
    t = np.arange(int(seconds / h)) * h
    speed = 0.6 + 1.1 * np.sin(np.pi * t / seconds) ** 2
    u = np.column_stack([speed, 0.2 * np.sin(t)])
    a = np.exp(-h / lag_s)
    v = np.zeros_like(u)
    v[0] = gain * u[0]
    for k in range(len(t) - 1):
        v[k + 1] = a * v[k] + (1 - a) * gain * u[k]
    return t, u, v


def _learn(t, u, v, lag_s, forget_s=3.0):
    est = OnlineGain(lag_s, forget_s)
    for k in range(len(t)):
        est.update(float(t[k]), tuple(u[k]), tuple(v[k]))
    return est


@pytest.mark.parametrize("gain", [0.84, 1.0, 1.1])
def test_the_online_gain_recovers_a_steady_shortfall_through_the_pass_accelerations(gain):
    t, u, v = _duct_pass(gain, lag_s=0.85)
    est = _learn(t, u, v, lag_s=0.85)
    assert est.gain == pytest.approx(gain, abs=0.01)
    # the lag is modelled: without it the same pass reads as another gain
    assert abs(_learn(t, u, v, lag_s=0.0).gain - gain) > 0.02


def test_the_online_gain_waits_for_its_window_and_for_speed():
    t, u, v = _duct_pass(0.84, lag_s=0.5)
    est = OnlineGain(0.5, 3.0)
    n_window = int(round(3.0 / 0.05))            # samples after the first: 3.0 s of dt
    for k in range(n_window):
        est.update(float(t[k]), tuple(u[k]), tuple(v[k]))
    assert est.gain is None                      # 2.95 s seen: just inside the window
    est.update(float(t[n_window]), tuple(u[n_window]), tuple(v[n_window]))
    assert est.gain is not None                  # 3.0 s: equal
    slow = OnlineGain(0.0, 1.0)                  # a hover: the RMS speed below ONLINE_MIN_SPEED_M_S
    for k in range(40):
        slow.update(k * 0.05, (ONLINE_MIN_SPEED_M_S * 0.99, 0.0), (0.2, 0.0))
    assert slow.gain is None
    fast = OnlineGain(0.0, 1.0)
    for k in range(40):
        fast.update(k * 0.05, (ONLINE_MIN_SPEED_M_S * 1.01, 0.0), (0.2, 0.0))
    assert fast.gain == pytest.approx(0.2 / (ONLINE_MIN_SPEED_M_S * 1.01))


def test_the_online_gain_skips_bad_samples_and_restarts_its_model_after_a_gap():
    est = OnlineGain(0.5, 1.0)
    for k in range(40):
        est.update(k * 0.05, (1.0, 0.0), (0.8, 0.0))
    g = est.gain
    est.update(2.05, (float("nan"), 0.0), (0.8, 0.0))          # ignored
    assert est.gain == g
    est.update(10.0, (-5.0, 0.0), (0.8, 0.0))                  # after a 7.95 s gap: a new model, no sample
    assert est.gain == g
    with pytest.raises(ValueError, match="lag_s"):
        OnlineGain(-0.1, 1.0)
    with pytest.raises(ValueError, match="forget_s"):
        OnlineGain(0.5, 0.0)


@pytest.mark.parametrize("gain, ff", [(0.84, 1 / 0.84), (1.0, 1.0), (1.2, 1.0), (2 / 3, 1.5), (0.5, 1.5),
                                      (0.0, 1.5), (-0.3, 1.0), (float("inf"), 1.0), (float("nan"), 1.0)])
def test_feedforward_from_gain_inverts_within_its_bounds(gain, ff):
    assert feedforward_from_gain(gain) == pytest.approx(ff)
    assert FEEDFORWARD_MIN <= feedforward_from_gain(gain) <= FEEDFORWARD_MAX
