"""The emulator's stock-PX4 velocity loop on SIH's quadrotor (``sim.plant.px4_loop``): its steady states and
ramp lags against the PI loop's closed forms, its limits, and the drag the agent identifies on it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.plant.px4_loop import Px4LoopParams, Px4LoopPlant

DT = 0.02


def _fly(plant: Px4LoopPlant, seconds: float, sp=lambda t: (0.0, 0.0, 0.0), ff=lambda t: (0.0, 0.0, 0.0)):
    t, out = 0.0, []
    for _ in range(round(seconds / DT)):
        plant.accel_ff_ned_m_s2 = ff(t)
        v = plant.step(np.array([sp(t)]), DT)[0].copy()
        t += DT
        out.append((t, v, plant.thrust_accel[0].copy()))
    return out


def test_it_starts_hovering_and_a_zero_setpoint_keeps_it_there():
    plant = Px4LoopPlant()
    assert plant.thrust_accel[0] == pytest.approx((0.0, 0.0, -9.81))
    *_, (_, v, a) = _fly(plant, 5.0)
    assert v == pytest.approx((0.0, 0.0, 0.0), abs=1e-12) and a == pytest.approx((0.0, 0.0, -9.81))


def test_a_constant_setpoint_is_held_exactly_by_the_integrator_which_then_holds_the_drag():
    """A proportional loop settles short of the setpoint against drag; PX4's integrator removes that."""
    plant = Px4LoopPlant()
    *_, (_, v, a) = _fly(plant, 80.0, sp=lambda t: (1.5, -0.5, 0.0))
    assert v == pytest.approx((1.5, -0.5, 0.0), abs=1e-3)
    assert a[:2] == pytest.approx((1.0 * 1.5, 1.0 * -0.5), abs=1e-3)  # thrust = SIH's linear drag c v
    assert plant._integ[:2] == pytest.approx((1.5, -0.5), abs=1e-3)


@pytest.mark.parametrize("drag", [0.5, 1.0, 1.5])
def test_on_a_ramp_it_lags_by_c_a_over_i_and_the_drag_fed_forward_removes_the_lag(drag):
    """Closed forms of the PI loop with linear drag on a ramp ``v_sp = a t``: the error settles where the
    integrator's growth ``I e`` equals the drag's ``c a``, so ``e = c a / I`` (2.5 s of the ramp for stock I 0.4
    and SIH's c 1); fed forward ``c v_sp``, the error goes to 0 (the integrator holds the ramp's ``a``)."""
    ramp = 0.1
    params = Px4LoopParams(drag_1_s=drag)
    *_, (t, v, _) = _fly(Px4LoopPlant(params), 60.0, sp=lambda t: (ramp * t, 0.0, 0.0))
    assert ramp * t - v[0] == pytest.approx(drag * ramp / 0.4, rel=0.03)
    *_, (t, v, _) = _fly(Px4LoopPlant(params), 60.0, sp=lambda t: (ramp * t, 0.0, 0.0),
                         ff=lambda t: (drag * ramp * t, 0.0, 0.0))
    assert abs(ramp * t - v[0]) < 0.01


def test_the_thrust_tilts_no_more_than_tiltmax_and_climbs_and_descends_on_the_vertical_loop():
    plant = Px4LoopPlant()
    track = _fly(plant, 3.0, sp=lambda t: (30.0, 0.0, 0.0))
    for _, _, a in track:
        assert math.hypot(a[0], a[1]) <= -a[2] * math.tan(math.radians(45.0)) * (1 + 1e-9) + 1e-9
    assert max(math.degrees(math.atan2(math.hypot(a[0], a[1]), -a[2])) for *_, a in track) > 44.0
    plant = Px4LoopPlant()
    *_, (_, v, _) = _fly(plant, 20.0, sp=lambda t: (0.0, 0.0, -1.0))  # climb 1 m/s (NED up is -z)
    assert v[2] == pytest.approx(-1.0, abs=1e-3)


def test_reset_at_a_velocity_trims_it_there():
    plant = Px4LoopPlant()
    plant.reset(np.array([1.0, 0.0, 0.0]))
    *_, (_, v, _) = _fly(plant, 2.0, sp=lambda t: (1.0, 0.0, 0.0))
    assert v == pytest.approx((1.0, 0.0, 0.0), abs=1e-9)


@pytest.mark.parametrize("field, value", [("p_xy_1_s", 0.0), ("i_xy_1_s2", -0.1), ("drag_1_s", math.nan),
                                          ("tilt_max_deg", 90.0), ("max_substep_s", 0.0)])
def test_bad_parameters_are_refused_by_name(field, value):
    with pytest.raises(ValueError, match=field):
        Px4LoopParams(**{field: value})


def test_a_bad_step_is_refused():
    with pytest.raises(ValueError, match="dt_s"):
        Px4LoopPlant().step(np.zeros((1, 3)), 0.0)
