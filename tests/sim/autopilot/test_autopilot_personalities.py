"""Mode, type and parameter encodings of the PX4 and ArduPilot Copter personalities."""

from __future__ import annotations

import struct

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim.autopilot.personalities import (
    ARDUPILOT,
    PX4,
    FlightMode,
    get_personality,
    px4_custom_mode,
    px4_main_sub,
)


@pytest.mark.parametrize(
    ("mode", "main", "sub"),
    [
        (FlightMode.MANUAL, 1, 0), (FlightMode.ALTCTL, 2, 0), (FlightMode.POSCTL, 3, 0),
        (FlightMode.AUTO_READY, 4, 1), (FlightMode.TAKEOFF, 4, 2), (FlightMode.LOITER, 4, 3),
        (FlightMode.MISSION, 4, 4), (FlightMode.RTL, 4, 5), (FlightMode.LAND, 4, 6),
        (FlightMode.ACRO, 5, 0), (FlightMode.OFFBOARD, 6, 0), (FlightMode.STABILIZED, 7, 0),
    ],
)  # fmt: skip
def test_px4_custom_mode_is_main_shl_16_or_sub_shl_24(mode, main, sub):
    word = PX4.custom_mode(mode)
    assert word == (main << 16) | (sub << 24)
    assert px4_main_sub(word) == (main, sub)
    assert PX4.mode_from_custom(word) == mode
    assert PX4.mode_from_command(float(main), float(sub)) == mode


def test_px4_known_words():
    assert PX4.custom_mode(FlightMode.OFFBOARD) == 393216
    assert PX4.custom_mode(FlightMode.LOITER) == 50593792
    assert px4_custom_mode(4, 6) == 0x06040000
    assert PX4.mode_from_command(4.0, 0.0) == FlightMode.LOITER  # AUTO without sub mode: Hold
    assert PX4.mode_from_command(9.0, 0.0) is None
    assert PX4.mode_from_command(float("nan"), 0.0) is None
    assert PX4.mode_from_command(6.0, float("nan")) == FlightMode.OFFBOARD  # NaN = unused sub mode
    assert ARDUPILOT.mode_from_command(4.0, float("nan")) == FlightMode.GUIDED


@pytest.mark.parametrize(
    ("mode", "number"),
    [(FlightMode.STABILIZED, 0), (FlightMode.ACRO, 1), (FlightMode.ALTCTL, 2), (FlightMode.MISSION, 3),
     (FlightMode.GUIDED, 4), (FlightMode.LOITER, 5), (FlightMode.RTL, 6), (FlightMode.LAND, 9),
     (FlightMode.POSCTL, 16), (FlightMode.BRAKE, 17)],
)  # fmt: skip
def test_ardupilot_copter_mode_numbers(mode, number):
    assert ARDUPILOT.custom_mode(mode) == number
    assert ARDUPILOT.mode_from_custom(number) == mode
    assert ARDUPILOT.mode_from_command(float(number), 0.0) == mode


def test_personality_identity():
    assert PX4.autopilot_type == mavlink.MAV_AUTOPILOT_PX4
    assert ARDUPILOT.autopilot_type == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert FlightMode.OFFBOARD not in ARDUPILOT.modes and FlightMode.GUIDED not in PX4.modes
    assert ARDUPILOT.mode_from_custom(7) is None  # CIRCLE is not emulated
    assert PX4.mode_name(FlightMode.LOITER) == "AUTO.LOITER" and ARDUPILOT.mode_name(FlightMode.GUIDED) == "GUIDED"
    assert get_personality("PX4") is PX4 and get_personality("apm") is ARDUPILOT
    with pytest.raises(ValueError, match="personality"):
        get_personality("betaflight")


def test_parameter_tables_have_the_failsafe_parameters():
    px4 = PX4.default_params(sysid=7)
    assert px4["COM_OF_LOSS_T"] == 1.0 and px4["COM_OBL_RC_ACT"] == 0 and px4["MAV_SYS_ID"] == 7
    ap = ARDUPILOT.default_params(sysid=3)
    assert ap["GUID_TIMEOUT"] == 3.0 and ap["FS_GCS_ENABLE"] == 0 and ap["SYSID_THISMAV"] == 3
    assert all(len(p.name) <= 16 for p in PX4.params + ARDUPILOT.params)


def test_px4_integer_params_are_bytewise_and_ardupilot_cast():
    i32 = mavlink.MAV_PARAM_TYPE_INT32
    wire = PX4.encode_param(5, i32)
    assert struct.pack("<f", wire) == struct.pack("<i", 5)
    assert PX4.decode_param(wire, i32) == 5.0
    assert PX4.encode_param(1.5, mavlink.MAV_PARAM_TYPE_REAL32) == 1.5
    assert ARDUPILOT.encode_param(5, mavlink.MAV_PARAM_TYPE_INT8) == 5.0
    assert ARDUPILOT.decode_param(1.0, mavlink.MAV_PARAM_TYPE_INT8) == 1.0
