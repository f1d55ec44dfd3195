"""Position integrity (issue 36 item 4): IntegrityMonitor on simulated clocks, at its boundaries."""

from __future__ import annotations

import pytest

from fisc_agent.flight.integrity import (DisruptionReason, IntegrityConfig, IntegrityMonitor, IntegrityVerdict,
                                         unexplained_m)

CFG = IntegrityConfig(max_unexplained_m=0.5, max_accel_m_s2=10.0, consistent_s=2.0, max_gap_s=1.0)
DT = 0.125  # exact in binary: the boundaries below are exact


def fly(mon, t0, t1, x0, v=1.0, dt=DT):
    """Fixes at ``dt`` from t0 (inclusive) to t1 (inclusive), moving north at ``v`` from ``x0``; last verdict."""
    n = round((t1 - t0) / dt)
    out = None
    for i in range(n + 1):
        out = mon.on_fix(t0 + i * dt, (x0 + v * i * dt, 0.0, -5.0), (v, 0.0, 0.0))
    return out


def test_config_rejects_non_positive_thresholds():
    for name in ("max_unexplained_m", "max_accel_m_s2", "consistent_s", "max_gap_s"):
        with pytest.raises(ValueError, match=name):
            IntegrityConfig(**{name: 0.0})


def test_unexplained_uses_the_mean_velocity():
    assert unexplained_m((0, 0, 0), (1, 0, 0), (1.5, 0, 0), (2, 0, 0), 1.0) == pytest.approx(0.0)
    assert unexplained_m((0, 0, 0), (0, 0, 0), (0, 3, 4), (0, 0, 0), 1.0) == pytest.approx(5.0)


def test_a_steady_track_is_ok_and_nothing_is_logged():
    mon = IntegrityMonitor(CFG)
    assert mon.verdict == IntegrityVerdict()
    assert fly(mon, 0.0, 5.0, 0.0).ok and mon.pop_events() == [] and mon.disruptions == 0


@pytest.mark.parametrize("extra_m, disrupted", [(0.0, False), (-1e-6, False), (1e-6, True)])
def test_jump_threshold_equal_inside_outside(extra_m, disrupted):
    """allowance = 0.5 + 10 * 0.125^2 / 2 = 0.578125 m at dt = 0.125 s."""
    mon = IntegrityMonitor(CFG)
    mon.on_fix(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    v = mon.on_fix(DT, (0.578125 + extra_m, 0.0, 0.0), (0.0, 0.0, 0.0))
    assert v.ok is not disrupted
    if disrupted:
        assert v.reason == DisruptionReason.JUMP and v.since_s == DT and "0.58 m" in v.detail


def test_a_jump_holds_until_a_consistent_track_of_consistent_s_then_reanchors():
    mon = IntegrityMonitor(CFG)
    fly(mon, 0.0, 1.0, 0.0)
    v = mon.on_fix(1.125, (4.0, 0.0, -5.0), (1.0, 0.0, 0.0))            # EKF reset: 2.9 m sideways of the track
    assert not v.ok and v.reason == DisruptionReason.JUMP and v.since_s == 1.125
    assert not fly(mon, 1.25, 3.0, 4.125).ok                             # 1.875 s of track: just short
    v = mon.on_fix(3.125, (6.0, 0.0, -5.0), (1.0, 0.0, 0.0))            # exactly consistent_s after the jump
    assert v.ok and v.since_s == 3.125 and v.reason is None
    events = mon.pop_events()
    assert [e.verdict.ok for e in events] == [False, True]
    assert events[1].reanchored_ned_m == (6.0, 0.0, -5.0) and mon.disruptions == 1


def test_a_second_jump_while_recovering_restarts_the_clock_but_keeps_since():
    mon = IntegrityMonitor(CFG)
    fly(mon, 0.0, 1.0, 0.0)
    mon.on_fix(1.125, (4.0, 0.0, -5.0), (1.0, 0.0, 0.0))
    fly(mon, 1.25, 2.5, 4.125)
    v = mon.on_fix(2.625, (10.0, 0.0, -5.0), (1.0, 0.0, 0.0))
    assert not v.ok and v.since_s == 1.125 and mon.disruptions == 2
    assert not fly(mon, 2.75, 4.5, 10.125).ok                            # 1.875 s after the second jump
    assert mon.on_fix(4.625, (12.0, 0.0, -5.0), (1.0, 0.0, 0.0)).ok


def test_reset_counter_step_disrupts_even_without_a_visible_jump():
    mon = IntegrityMonitor(CFG)
    fly(mon, 0.0, 1.0, 0.0)
    mon.on_reset(1.0, 0)                                                  # no step: nothing
    assert mon.verdict.ok
    mon.on_reset(1.05, 1)
    assert mon.verdict.reason == DisruptionReason.RESET_COUNTER and mon.verdict.since_s == 1.05
    assert not fly(mon, 1.125, 3.0, 1.125).ok
    assert fly(mon, 3.125, 3.125, 3.125).ok                               # 2.075 s after the reset


def test_an_unhealthy_estimator_holds_until_it_recovers_plus_consistent_s():
    mon = IntegrityMonitor(CFG)
    fly(mon, 0.0, 1.0, 0.0)
    mon.on_estimator(1.0, True)
    assert mon.verdict.ok
    mon.on_estimator(1.0, False, "GNSS glitch")
    assert mon.verdict.reason == DisruptionReason.ESTIMATOR and "GNSS glitch" in mon.verdict.detail
    mon.on_estimator(2.0, False, "GNSS glitch")                           # still bad: one disruption only
    assert mon.disruptions == 1
    assert not fly(mon, 1.125, 5.0, 1.125).ok                             # consistent fixes, estimator still bad
    mon.on_estimator(5.0, True)
    assert not fly(mon, 5.125, 6.875, 5.125).ok
    assert fly(mon, 7.0, 7.0, 7.0).ok                                     # 2.0 s after the estimator recovered


def test_fixes_across_a_gap_are_not_compared_and_autopilot_time_is_preferred():
    mon = IntegrityMonitor(CFG)
    mon.on_fix(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    assert mon.on_fix(1.5, (30.0, 0.0, 0.0), (0.0, 0.0, 0.0)).ok         # gap > max_gap_s: the stale rule's job
    # two fixes received together (bunched) but 0.1 s apart on the autopilot's clock, at 5 m/s
    mon = IntegrityMonitor(CFG)
    mon.on_fix(10.0, (0.0, 0.0, 0.0), (5.0, 0.0, 0.0), autopilot_t_s=100.0)
    assert mon.on_fix(10.0, (0.5, 0.0, 0.0), (5.0, 0.0, 0.0), autopilot_t_s=100.1).ok
    mon = IntegrityMonitor(CFG)                                           # the same on receive times would be a jump
    mon.on_fix(10.0, (0.0, 0.0, 0.0), (5.0, 0.0, 0.0))
    mon.on_fix(10.0, (0.6, 0.0, 0.0), (5.0, 0.0, 0.0))
    assert mon.verdict.reason == DisruptionReason.JUMP


def test_a_reboot_disrupts_until_a_consistent_track():
    mon = IntegrityMonitor(CFG)
    fly(mon, 0.0, 1.0, 0.0)
    mon.on_reboot(1.0)
    assert mon.verdict.reason == DisruptionReason.AUTOPILOT_REBOOT and mon.verdict.since_s == 1.0
    assert not fly(mon, 1.125, 2.875, 1.125).ok
    assert fly(mon, 3.0, 3.0, 3.0).ok
