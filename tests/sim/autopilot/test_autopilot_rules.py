"""The personalities' failsafe and limit rules, value by value (PX4 and ArduPilot parameter docs)."""

from __future__ import annotations

import pytest

from sim.autopilot.personalities import ARDUPILOT, PX4, FlightMode
from sim.autopilot.rules import AP_NO_RC_DESCENT_M_S, FailsafeAction, PersonalityRules
from sim.autopilot.vehicle import Vehicle

LOITER, RTL, LAND = FlightMode.LOITER, FlightMode.RTL, FlightMode.LAND


@pytest.mark.parametrize(
    ("act", "action"),
    [(0, FailsafeAction(LOITER)), (1, FailsafeAction(LOITER)), (2, FailsafeAction(LOITER)), (3, FailsafeAction(RTL)),
     (4, FailsafeAction(LAND)), (5, FailsafeAction(LOITER)), (6, FailsafeAction(LOITER, True)),
     (7, FailsafeAction(LOITER, True))],
)  # fmt: skip
def test_px4_offboard_loss_action(act, action):
    params = PX4.default_params()
    params["COM_OBL_RC_ACT"] = act
    assert PersonalityRules(True, params).offboard_loss_action() == action


@pytest.mark.parametrize(
    ("px4", "act", "action"),
    [(True, 1, FailsafeAction(LOITER)), (True, 2, FailsafeAction(RTL)), (True, 3, FailsafeAction(LAND)),
     (True, 4, FailsafeAction(LOITER)), (True, 5, FailsafeAction(None, True)), (True, 6, FailsafeAction(None, True)),
     (False, 1, FailsafeAction(RTL)), (False, 2, FailsafeAction(RTL)), (False, 5, FailsafeAction(LAND))],
)  # fmt: skip
def test_gcs_loss_action(px4, act, action):
    params = (PX4 if px4 else ARDUPILOT).default_params()
    assert PersonalityRules(px4, params).gcs_loss_action(act) == action


def test_rules_read_the_live_parameter_table_in_each_autopilots_units():
    px4 = Vehicle(PX4)
    ap = Vehicle(ARDUPILOT)
    px4.set_param("MPC_XY_VEL_MAX", 7.5)
    ap.set_param("WPNAV_SPEED", 750.0)  # cm/s
    assert px4._rules.command_limits_m_s()[0] == 7.5 and ap._rules.command_limits_m_s()[0] == 7.5
    ap.set_param("DISARM_DELAY", 0.0)
    assert ap._rules.auto_disarm_delay_s(True) == -1.0  # 0 disables ArduPilot's auto-disarm
    assert ap._rules.no_rc_descent_m_s(LOITER) == AP_NO_RC_DESCENT_M_S and px4._rules.no_rc_descent_m_s(LOITER) is None
    assert px4._rules.reject_code != ap._rules.reject_code
