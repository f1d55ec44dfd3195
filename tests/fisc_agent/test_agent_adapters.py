"""PX4 / ArduPilot encodings and the command reconciler."""

import pytest

from agent_testkit import RecordingVehicle
from fisc_agent.mavlink.adapters import (FRESH_HEARTBEAT_S, MAV_CMD_COMPONENT_ARM_DISARM, MAV_CMD_DO_SET_MODE, MAV_CMD_NAV_TAKEOFF,
                                 MAV_CMD_SET_MESSAGE_INTERVAL, ArduPilotAdapter, CommandKind, CommandResult, Commander,
                                 ModeClass, Px4Adapter, adapter_for, autopilot_from_heartbeat, command_result,
                                 is_armed)


def test_mavlink_numbers_from_the_dialect_are_the_standard_ones():
    assert (MAV_CMD_NAV_TAKEOFF, MAV_CMD_DO_SET_MODE, MAV_CMD_COMPONENT_ARM_DISARM,
            MAV_CMD_SET_MESSAGE_INTERVAL) == (22, 176, 400, 511)


def test_autopilot_identification_from_heartbeat():
    assert autopilot_from_heartbeat(12) == "px4"
    assert autopilot_from_heartbeat(3) == "ardupilot"
    assert autopilot_from_heartbeat(8) is None
    assert is_armed(128 | 1) and not is_armed(1)


def test_px4_mode_encoding_round_trip():
    px4 = Px4Adapter()
    assert px4.px4_custom_mode(6) == 6 << 16 == 393216
    assert px4.classify_mode(1, px4.px4_custom_mode(6)) == "offboard"
    assert px4.classify_mode(1, px4.px4_custom_mode(4, 3)) == "hold"
    assert px4.classify_mode(1, px4.px4_custom_mode(4, 6)) == "land"
    assert px4.classify_mode(1, px4.px4_custom_mode(3)) == "other"       # POSCTL
    assert px4.classify_mode(0, px4.px4_custom_mode(6)) == "other"       # custom mode flag not set
    cmd = px4.set_mode("offboard")
    assert cmd.command == MAV_CMD_DO_SET_MODE and cmd.params[:3] == (1.0, 6.0, 0.0)
    assert px4.set_mode("hold").params[:3] == (1.0, 4.0, 3.0)
    assert px4.set_mode("land").params[:3] == (1.0, 4.0, 6.0)
    assert px4.takeoff(3.0) is None and not px4.takeoff_by_command


def test_ardupilot_mode_encoding():
    ap = ArduPilotAdapter()
    assert ap.classify_mode(1, 4) == "offboard"
    assert ap.classify_mode(1, 5) == "hold" and ap.classify_mode(1, 17) == "hold"
    assert ap.classify_mode(1, 9) == "land"
    assert ap.classify_mode(1, 0) == "other"
    assert ap.set_mode("offboard").params[:2] == (1.0, 4.0)
    assert ap.set_mode("hold").params[1] == 17.0          # BRAKE: holds with no pilot
    with pytest.raises(ValueError, match="throttle"):       # LOITER follows the RC throttle: refused
        ArduPilotAdapter(hold_mode=5)
    t = ap.takeoff(2.5)
    assert t.command == MAV_CMD_NAV_TAKEOFF and t.params[6] == 2.5
    assert isinstance(adapter_for("px4"), Px4Adapter) and isinstance(adapter_for("ardupilot"), ArduPilotAdapter)
    with pytest.raises(ValueError):
        adapter_for("inav")


def test_px4_offboard_waits_for_the_setpoint_stream_then_retries():
    v = RecordingVehicle()
    sent = v.sent
    c = Commander(Px4Adapter(), v, retry_s=1.0)
    c.reconcile(0.0, "offboard", True, None, armed=False, mode="other", stream_s=0.2, mode_age_s=0.0)
    assert sent == []                               # stream not running long enough yet
    c.reconcile(1.0, "offboard", True, None, armed=False, mode="other", stream_s=1.2, mode_age_s=0.0)
    assert sent == [("set_mode", ModeClass.OFFBOARD)]
    c.reconcile(1.5, "offboard", True, None, armed=False, mode="other", stream_s=1.7, mode_age_s=0.0)
    assert len(sent) == 1                           # not before retry_s
    c.reconcile(2.1, "offboard", True, None, armed=False, mode="other", stream_s=2.3, mode_age_s=0.0)
    assert len(sent) == 2                           # retried
    c.reconcile(2.2, "offboard", True, None, armed=False, mode="offboard", stream_s=2.4, mode_age_s=0.0)
    assert sent[-1] == ("arm",)
    c.reconcile(2.3, "offboard", True, None, armed=True, mode="offboard", stream_s=2.5, mode_age_s=0.0)
    assert len(sent) == 3                           # satisfied: nothing more
    c.reconcile(9.0, "offboard", True, 2.5, armed=True, mode="offboard", stream_s=9.0, mode_age_s=0.0)
    assert len(sent) == 3                           # PX4 takes off by climbing in OFFBOARD: no takeoff request


@pytest.mark.parametrize("adapter", [Px4Adapter(), ArduPilotAdapter()], ids=["px4", "ardupilot"])
@pytest.mark.parametrize("armed", [False, True], ids=["on-the-ground", "in-the-air"])
@pytest.mark.parametrize("wanted", [ModeClass.OFFBOARD, ModeClass.HOLD, ModeClass.LAND])
def test_a_mode_is_requested_only_on_a_fresh_heartbeat(adapter, armed, wanted):
    """A mode change by someone else between two 1 Hz HEARTBEATs is invisible: every mode request, on the ground
    and in the air, waits for a HEARTBEAT at most FRESH_HEARTBEAT_S old (on its boundary: sent)."""
    current = ModeClass.OTHER
    for age, expected in [(FRESH_HEARTBEAT_S + 1e-3, []), (FRESH_HEARTBEAT_S, [("set_mode", wanted)]),
                          (0.0, [("set_mode", wanted)]), (0.9, [])]:
        v = RecordingVehicle()
        Commander(adapter, v).reconcile(0.0, wanted, None, None, armed=armed, mode=current, stream_s=5.0,
                                        mode_age_s=age)
        assert v.sent == expected, age


@pytest.mark.parametrize("adapter", [Px4Adapter(), ArduPilotAdapter()], ids=["px4", "ardupilot"])
def test_arming_and_the_take_off_are_requested_only_on_a_fresh_heartbeat(adapter):
    for age, expected in [(FRESH_HEARTBEAT_S + 1e-3, []), (FRESH_HEARTBEAT_S, [("arm",)])]:
        v = RecordingVehicle()
        Commander(adapter, v).reconcile(0.0, ModeClass.OFFBOARD, True, None, armed=False, mode=ModeClass.OFFBOARD,
                                        stream_s=5.0, mode_age_s=age)
        assert v.sent == expected, age
    if adapter.takeoff_by_command:
        for age, expected in [(FRESH_HEARTBEAT_S + 1e-3, []), (FRESH_HEARTBEAT_S, [("takeoff", 2.0)])]:
            v = RecordingVehicle()
            Commander(adapter, v).reconcile(0.0, ModeClass.OFFBOARD, True, 2.0, armed=True, mode=ModeClass.OFFBOARD,
                                            stream_s=5.0, mode_age_s=age)
            assert v.sent == expected, age


@pytest.mark.parametrize(("what", "armed"), [("set_mode", False), ("set_mode", True), ("arm", False),
                                             ("takeoff", True)])
def test_a_retry_waits_for_a_fresh_heartbeat_received_after_the_request(what, armed):
    """A pilot's switch after the agent's request shows only on the next 1 Hz HEARTBEAT: a retry goes out
    only after retry_s, on a HEARTBEAT at most FRESH_HEARTBEAT_S old *and* received after the request it
    repeats (the request at t = 0 on a HEARTBEAT at 0; the retry at t with the newest HEARTBEAT at h)."""
    mode, want_armed, takeoff = {"set_mode": (ModeClass.HOLD, None, None), "arm": (ModeClass.OFFBOARD, True, None),
                                 "takeoff": (ModeClass.OFFBOARD, True, 2.0)}[what]
    fresh = FRESH_HEARTBEAT_S
    for retry_s, t, h, retried in [
            (1.0, 1.2, 1e-3, False),                 # newer than the request, but 1.199 s old
            (1.0, 1.2, 1.2 - fresh, True),           # newer and just fresh
            (1.0, 1.2, 1.2 - fresh - 1e-3, False),   # newer, just stale
            (1.0, 1.2, 1.2, True),
            (1.0, 0.999, 0.999, False),              # fresh, but before retry_s
            (0.1, 0.2, 0.0, False),                  # fresh, but the HEARTBEAT the request was sent on
            (0.1, 0.2, 1e-3, True)]:                 # fresh and just after the request
        v = RecordingVehicle()
        c = Commander(ArduPilotAdapter(), v, retry_s=retry_s)
        for now, hb_age in [(0.0, 0.0), (t, t - h)]:
            c.reconcile(now, ModeClass.OFFBOARD, want_armed, takeoff, armed=armed, mode=mode, stream_s=5.0,
                        mode_age_s=hb_age)
        assert [x[0] for x in v.sent] == [what] * (2 if retried else 1), (retry_s, t, h)


def test_ardupilot_guided_arm_takeoff_sequence_and_acks():
    v = RecordingVehicle()
    sent = v.sent
    c = Commander(ArduPilotAdapter(), v, retry_s=1.0)
    c.reconcile(0.0, "offboard", True, 2.0, armed=False, mode="other", stream_s=0.0, mode_age_s=0.0)
    c.reconcile(0.1, "offboard", True, 2.0, armed=False, mode="offboard", stream_s=0.0, mode_age_s=0.0)
    c.reconcile(0.2, "offboard", True, 2.0, armed=True, mode="offboard", stream_s=0.0, mode_age_s=0.0)
    assert sent == [("set_mode", ModeClass.OFFBOARD), ("arm",), ("takeoff", 2.0)]
    c.reconcile(1.5, "offboard", True, 2.0, armed=True, mode="offboard", stream_s=0.0, mode_age_s=0.0)
    assert len(sent) == 4                           # no ack yet: takeoff resent
    c.on_result(command_result(MAV_CMD_NAV_TAKEOFF, 0))
    c.reconcile(3.0, "offboard", True, 2.0, armed=True, mode="offboard", stream_s=0.0, mode_age_s=0.0)
    assert len(sent) == 4                           # accepted: not resent
    c.on_result(command_result(MAV_CMD_COMPONENT_ARM_DISARM, 2))
    assert list(c.refusals) == [("arming", "DENIED")]


def test_command_acks_become_typed_results():
    assert command_result(MAV_CMD_NAV_TAKEOFF, 5) == CommandResult(CommandKind.TAKEOFF, True, "IN_PROGRESS")
    assert command_result(MAV_CMD_DO_SET_MODE, 4) == CommandResult(CommandKind.SET_MODE, False, "FAILED")
    assert command_result(MAV_CMD_SET_MESSAGE_INTERVAL, 3) == CommandResult(CommandKind.MESSAGE_INTERVAL, False,
                                                                             "UNSUPPORTED")
    assert command_result(31000, 1) == CommandResult(CommandKind.OTHER, False, "TEMPORARILY_REJECTED")
    assert command_result(MAV_CMD_COMPONENT_ARM_DISARM, 250).result == "250"   # unknown MAV_RESULT: its number


def test_a_flood_of_refusing_acks_is_bounded_and_rate_limited(caplog):
    """Forged COMMAND_ACKs from the autopilot's identity: the refusal list stays bounded and the log
    gets one line per kind per 5 s, not one per ack."""
    from fisc_agent.mavlink.adapters import MAX_REFUSALS_KEPT

    c = Commander(Px4Adapter(), RecordingVehicle())
    with caplog.at_level("WARNING", logger="fisc_agent.mavlink.adapters"):
        for _ in range(5000):
            c.on_result(command_result(MAV_CMD_COMPONENT_ARM_DISARM, 2))
    assert len(c.refusals) == MAX_REFUSALS_KEPT
    assert sum("refused arming" in r.getMessage() for r in caplog.records) == 1
