"""The mission's reasons and its fault path at their boundaries (issue 38, mutation testing of
``fisc_agent.flight.mission``): the exact text of each transition a pass makes, the reasons that carry
numbers, and ``Mission.fault`` in and out of flight.  On the point vehicle of ``test_agent_mission``,
whose ``run`` also checks every step's transitions (time, source state, typed cause)."""

from __future__ import annotations

import re

import pytest
from test_agent_mission import DT, SimVehicle, make, run, run_for, step  # noqa: F401 (sfield fixture below)
from test_authority import HealthVehicle, make_h

from fisc_agent.flight.health import LandedState

from fisc_agent.flight.authority import AuthorityCause
from fisc_agent.flight.control import ScalarField
from fisc_agent.flight.health import VehicleHealth
from fisc_agent.flight.mission_types import Authority, Cause, FleetOrder, HoldCause, MissionCommand, MissionOutput, State
from fisc_agent.map.lookup import CommandField
from fisc_agent.flight.tracking import TrackingConfig


@pytest.fixture(scope="module")
def sfield(tunnel_map):
    return ScalarField(CommandField.from_map(tunnel_map))


def _reasons(m):
    return [(tr.dst, tr.reason.cause, str(tr.reason)) for tr in m.transitions]


def test_a_two_lap_pass_says_why_at_every_transition(sfield):
    cfg, m, v = make(sfield, exit_policy="loop", laps=2)
    outs = run(m, v, cfg, lambda m, v, o: m.state == State.HOLD, max_s=120)
    flying = [o for prev, o in zip(outs, outs[1:]) if o.state == prev.state in (State.JOIN, State.FLOW, State.EXIT)]
    assert len(flying) > 100                                   # (the tick a state is entered has the last one's asks)
    assert all(o.want_mode == "offboard" and o.want_armed is None for o in flying)  # offboard, arming left alone
    assert all(o.velocity_m_s is not None for o in outs if o.state == State.FLOW)  # from the tick it enters
    got = _reasons(m)
    entered = [r for r in got if r[1] == Cause.ENTERED_MAP]
    assert entered and all(text == f"entered the map at CV {text.rsplit(' ', 1)[1]}" and int(text.rsplit(" ", 1)[1]) >= 0
                           for _, _, text in entered)
    assert [r for r in got if r[1] != Cause.ENTERED_MAP] == [
        (State.ARM, Cause.AUTOPILOT_FOUND, "go; position and px4 heartbeat received"),
        (State.TAKEOFF, Cause.ARMED, Cause.ARMED.value),
        (State.JOIN, Cause.TAKEOFF_DONE, "takeoff height 1.0 m reached"),
        (State.JOIN, Cause.LAP_DONE, "lap 1 done: back to the inlet"),
        (State.EXIT, Cause.PASSED_OUTLET, "passed the outlet (lap 2)"),
        (State.HOLD, HoldCause.EXIT, HoldCause.EXIT.value),
    ]


class NeverArms(SimVehicle):
    """Takes the modes asked for but never arms (a pre-arm check the agent cannot see)."""

    def apply(self, out, cfg):
        super().apply(out._replace(want_armed=None), cfg)


def test_arming_gives_up_just_after_the_command_timeout_saying_so(sfield):
    cfg, m, _ = make(sfield, command_timeout_s=1.0)
    v = NeverArms()
    run(m, v, cfg, lambda m, v, o: m.state == State.ARM)
    arm_t, s = m.transitions[-1].t_s, v.status()
    assert step(m, s._replace(t_s=arm_t + 1.0)).state == State.ARM        # exactly the timeout: still trying
    assert step(m, s._replace(t_s=arm_t + 1.0 + 1e-6)).state == State.DONE
    assert m.reason.cause == Cause.ARM_FAILED and str(m.reason) == f"{Cause.ARM_FAILED.value} after 1 s" and m.failed


def test_take_off_gives_up_just_after_its_timeout_saying_so(sfield):
    cfg, m, _ = make_h(sfield, takeoff_timeout_s=2.0)
    v = HealthVehicle()
    v.health = VehicleHealth(landed=LandedState.ON_GROUND)   # never leaves the ground
    run(m, v, cfg, lambda m, v, o: m.state == State.TAKEOFF)
    t0, s = m.transitions[-1].t_s, v.status()
    assert step(m, s._replace(t_s=t0 + 2.0)).state == State.TAKEOFF
    assert step(m, s._replace(t_s=t0 + 2.0 + 1e-6)).state == State.LAND
    assert m.reason.cause == Cause.TAKEOFF_TIMEOUT and str(m.reason) == "take-off not done after 2 s: landing"


def test_low_battery_while_joining_lands_saying_how_low(sfield):
    cfg, m, _ = make_h(sfield, min_battery_pct=30.0)
    v = HealthVehicle()
    run(m, v, cfg, lambda m, v, o: m.state == State.JOIN)
    v.health = VehicleHealth(battery_pct=29.4)
    run(m, v, cfg, lambda m, v, o: m.state == State.LAND, max_s=v.t + 1)
    assert m.reason.cause == Cause.LOW_BATTERY
    assert str(m.reason) == "battery 29 % below 30 %: no new pass, landing"


def test_a_fault_in_flight_holds_and_outputs_the_hold(sfield):
    cfg, m, v = make(sfield, hold_grace_s=5.0)
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW)
    t = 100.0  # later than the last step, and exact: the grace boundary below is exactly 5 s
    out = m.fault(t, "tick raised")
    assert m.state == State.HOLD and m.hold_cause == HoldCause.AGENT_FAULT and m.reason == "agent fault: tick raised"
    assert out == MissionOutput(State.HOLD, (0.0, 0.0, 0.0), "offboard", None, None, -1, m.reason)
    assert m.transitions[-1].t_s == t and m.transitions[-1].src == State.FLOW
    again = m.fault(t + 1.0, "again")       # an armed hold takes the newer fault, and its grace starts again
    assert m.reason == "agent fault: again" and again == MissionOutput(State.HOLD, (0.0, 0.0, 0.0), "offboard", None,
                                                                       None, -1, m.reason)
    assert m.fault(t + 5.999, "again").want_mode == "offboard"
    assert m.fault(t + 6.0, "again") == MissionOutput(State.HOLD, None, "hold", None, None, -1, m.reason)  # grace over
    v.t = t + 6.0
    run_for(m, v, cfg, 1.0)
    assert m.state == State.HOLD  # latched: a good position does not end it


def test_a_fault_on_the_ground_changes_nothing(sfield):
    cfg, m, v = make(sfield, go=False)
    run_for(m, v, cfg, 0.5)
    assert m.state == State.STANDBY
    before = list(m.transitions)
    assert m.fault(v.t, "tick raised") == MissionOutput(State.STANDBY, None, None, None, None, -1, m.reason)
    assert m.transitions == before
    m.command("hold")                                 # a fleet hold on the ground: not armed
    run_for(m, v, cfg, 0.2)
    assert m.hold_cause == HoldCause.FLEET_ON_GROUND
    assert m.fault(v.t, "tick raised") == MissionOutput(State.HOLD, None, None, None, None, -1, m.reason)
    assert m.hold_cause == HoldCause.FLEET_ON_GROUND  # an unarmed hold is not made a fault hold


def test_a_fresh_or_restored_mission_reports_its_start(sfield):
    from fisc_agent.flight.mission import Mission
    from fisc_agent.flight.state_file import AgentState

    cfg, m, _ = make(sfield, go=False)
    assert (m.laps, m.authority_cause, m.saved_state()) == (0, AuthorityCause.START, AgentState())
    back = Mission(cfg, sfield, restored=AgentState(laps=3, fleet_hold=True))
    assert back.laps == 3 and back.saved_state() == AgentState(fleet_hold=True, laps=3)


def test_a_fleet_hold_on_the_ground_resumes_where_it_was(sfield):
    for go, before in ((False, State.STANDBY), (True, State.WAIT_POSITION)):
        cfg, m, v = make(sfield, go=go)
        if before == State.WAIT_POSITION:
            v.drop_position, v.last_fix = True, -10.0  # no fix yet: the mission waits for one
        run_for(m, v, cfg, 0.2)
        assert m.state == before
        m.command("hold")
        run_for(m, v, cfg, 0.1)
        assert m.hold_cause == HoldCause.FLEET_ON_GROUND and m.saved_state().fleet_hold
        m.command("resume")
        run_for(m, v, cfg, DT)
        resumed = [tr for tr in m.transitions if tr.reason.cause == Cause.FLEET_RESUME]
        assert [tr.dst for tr in resumed] == [before] and m.state == before
        assert not m.saved_state().fleet_hold


def test_a_go_ends_a_fleet_hold_on_the_ground_and_a_land_ends_a_mission_on_it(sfield):
    cfg, m, v = make(sfield, go=False)
    run_for(m, v, cfg, 0.2)
    m.command("hold")
    run_for(m, v, cfg, 0.1)
    m.command("go")
    run(m, v, cfg, lambda m, v, o: m.state == State.ARM, max_s=v.t + 1)
    assert [(tr.dst, tr.reason.cause) for tr in m.transitions[-3:]] == [
        (State.HOLD, HoldCause.FLEET_ON_GROUND), (State.STANDBY, Cause.GO), (State.ARM, Cause.AUTOPILOT_FOUND)]
    cfg, m, v = make(sfield, go=False)
    run_for(m, v, cfg, 0.2)
    m.command("land")  # disarmed on the ground: the mission ends
    run_for(m, v, cfg, DT)
    assert m.state == State.DONE and m.reason.cause == Cause.FLEET_LAND_DISARMED and not v.armed
    m.command("land")
    run_for(m, v, cfg, DT)
    assert len([tr for tr in m.transitions if tr.dst == State.DONE]) == 1


def test_px4_climbs_by_velocity_to_its_take_off_height(sfield):
    cfg, m, v = make(sfield, climb_speed_m_s=2.0, takeoff_alt_m=1.0)
    seen = []
    run(m, v, cfg, lambda m, v, o: m.state == State.JOIN, hook=lambda m, v, o: seen.append((o, m.state)))
    outs = [o for o, _ in seen]
    arm = [o for o in outs if o.state == State.ARM]
    assert arm and all(o.want_armed is True and o.want_mode == "offboard" for o in arm)
    take = [o for o in outs if o.state == State.TAKEOFF]
    assert len(take) > 5 and all(o.want_armed is True and o.want_mode == "offboard" for o in take)
    home_z, target_z = -3.0, -3.0 + 1.0
    vz = [o.velocity_m_s[2] for o in take[1:]]  # (the first is the arming tick's)
    assert vz[0] == pytest.approx(min(2.0, 1.5 * (target_z - home_z)))     # 1.5 m/s per metre to go, capped
    assert min(vz) == pytest.approx(0.2)                                     # never slower than 0.2 m/s
    assert v.pos[2] >= target_z - 0.1 - 0.2 * DT - 1e-9 and v.pos[2] < target_z  # up to 0.1 m short: done


def _armed_by_someone_else(sfield, pos, with_map=True):
    from fisc_agent.flight.mission import Mission

    cfg, m, v = make(sfield)
    if not with_map:
        m = Mission(cfg)
    v.armed, v.mode, v.pos = True, "offboard", list(pos)
    run_for(m, v, cfg, 0.5)
    assert m.authority == (Authority.NOT_OURS if with_map else Authority.WAITING)  # no map: still waiting for one
    return cfg, m, v


def test_an_addressed_takeover_needs_a_good_fix_and_a_map(sfield):
    takeover = FleetOrder(MissionCommand.TAKEOVER, addressed=True)
    cfg, m, v = _armed_by_someone_else(sfield, (1.0, 0.1, 0.1), with_map=False)
    m.command(takeover)
    assert step(m, v.status()).cv_id == -1                 # no map: no CV
    assert m.authority == Authority.WAITING and m.state == State.WAIT_POSITION  # no map: nothing to fly
    cfg, m, v = _armed_by_someone_else(sfield, (1.0, 0.1, 0.1))
    v.drop_position = True
    run(m, v, cfg, lambda m, v, o: v.t - v.last_fix > cfg.stale_timeout_s)
    m.command(takeover)
    run_for(m, v, cfg, DT)
    assert m.authority == Authority.NOT_OURS  # a stale fix: not taken over blind
    v.drop_position = False
    m.command(takeover)
    run_for(m, v, cfg, DT)
    assert (m.authority, m.authority_cause, m.state) == (Authority.COMMAND, AuthorityCause.TAKEOVER, State.FLOW)
    assert m.transitions[-1].reason.cause == Cause.TAKING_OVER
    run_for(m, v, cfg, 1.0)
    assert m.authority == Authority.COMMAND   # the mode it was in at the takeover is no change of mode


def test_a_takeover_outside_the_map_joins_it(sfield):
    cfg, m, v = _armed_by_someone_else(sfield, (-3.0, 0.0, 0.5))
    m.command(FleetOrder(MissionCommand.TAKEOVER, addressed=True))
    run_for(m, v, cfg, DT)
    assert m.state == State.JOIN and m.authority == Authority.COMMAND


def test_a_vehicle_given_back_after_a_pilot_override_says_so(sfield):
    cfg, m, v = make(sfield)
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW)
    v.mode = "other"
    run(m, v, cfg, lambda m, v, o: m.hands_off)
    assert m.authority_cause == AuthorityCause.MODE_CHANGED
    m.command(FleetOrder(MissionCommand.RESUME, addressed=True))
    run_for(m, v, cfg, DT)
    assert (m.authority, m.authority_cause) == (Authority.COMMAND, AuthorityCause.GIVEN_BACK)


@pytest.mark.parametrize("auto", [True, False])
def test_the_response_is_recorded_while_taking_off_and_joining_and_learnt_again_in_the_flow(sfield, auto):
    cfg, m, v = make(sfield, tracking=TrackingConfig(feedforward_auto=auto, feedforward_gain=1.0))
    v.gain = 0.8                                  # a vehicle that settles at 0.8 of its setpoint
    calls = {}

    def observe(m, v, out):
        sp = out.velocity_m_s if out.velocity_m_s is not None else (0.0, 0.0, 0.0)
        key = m.state if m.response is None else "identified"  # (the join's final leg identifies it)
        calls[key] = calls.get(key, 0) + 1
        m.observe_response(v.t, sp, tuple(v.vel))

    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, hook=observe)
    recorded = calls.get(State.TAKEOFF, 0) + calls.get(State.JOIN, 0)
    assert calls[State.ARM] > 0 and recorded > 0 and len(m.nav.recorder) == recorded  # not while arming
    assert m.response.n_samples == recorded and m.response.gain == pytest.approx(0.8, abs=0.1)
    assert m.response.lookahead_s == m.tracker.cfg.lookahead_s             # the look-ahead is always flown
    # the feed-forward gain only with --feedforward-gain auto; else the configured 1
    assert m.tracker.cfg.feedforward_gain == (pytest.approx(m.response.feedforward_gain) if auto else 1.0)
    for _ in range(80):  # 4 s of the pass
        out = step(m, v.status())
        observe(m, v, out)
        v.apply(out, cfg)
    assert len(m.nav.recorder) == recorded        # identified: no more recording
    assert (m.nav.online_gain is not None) == auto                          # the flow feeds the online gain
    assert m.tracker.cfg.feedforward_gain == (pytest.approx(1 / 0.8, abs=0.05) if auto else 1.0)


def test_cv_0_is_in_the_map(sfield):
    """CV 0 (the id boundary of ``cv >= 0``) counts as inside: a takeover there flies the flow, a resume there
    flies on instead of returning."""
    at_cv0 = tuple(float(c) for c in sfield.field.centers_m[0])
    assert sfield.cv_of(*at_cv0) == 0
    cfg, m, v = _armed_by_someone_else(sfield, at_cv0)
    m.command(FleetOrder(MissionCommand.TAKEOVER, addressed=True))
    run_for(m, v, cfg, DT)
    assert m.transitions[-1].src == State.STANDBY and m.transitions[-1].dst == State.FLOW
    cfg, m, v = make(sfield)
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW)
    m.command("hold")
    run_for(m, v, cfg, 0.2)
    v.pos, v.vel = list(at_cv0), [0.0, 0.0, 0.0]
    run_for(m, v, cfg, 0.2)
    m.command("resume")
    run_for(m, v, cfg, DT)
    resumed = [tr for tr in m.transitions if tr.reason.cause == Cause.FLEET_RESUME]
    assert [tr.dst for tr in resumed] == [State.FLOW]


def test_a_resumed_fleet_hold_leaves_no_latch_on_the_next_stale_position_hold(sfield):
    cfg, m, v = make(sfield, hold_grace_s=5.0)
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW)
    m.command("hold")                      # latched: only a resume ends it
    run_for(m, v, cfg, 0.3)
    m.command("resume")
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, max_s=v.t + 2)
    v.drop_position = True
    run(m, v, cfg, lambda m, v, o: m.hold_cause == HoldCause.POSITION_STALE, max_s=v.t + 2)
    v.drop_position = False                # back well within the grace: the hold ends by itself
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, max_s=v.t + 1)
    assert m.transitions[-1].reason.cause == Cause.POSITION_BACK


# ------------------------------------------------------------------ the log an operator reads
def _log(caplog):
    return [(r.levelname, r.getMessage()) for r in caplog.records if r.name == "fisc_agent.flight.mission"]


def test_every_transition_authority_change_and_fleet_command_is_logged_in_full(sfield, caplog):
    caplog.set_level("INFO", logger="fisc_agent.flight.mission")
    cfg, m, v = make(sfield, hold_grace_s=0.5)
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW)
    m.command("go")                                        # swarm-wide, and refused: a warning with the note
    m.command("hold")
    run(m, v, cfg, lambda m, v, o: o.want_mode == "hold", max_s=v.t + 2)
    m.command(FleetOrder(MissionCommand.RESUME, addressed=True))
    run_for(m, v, cfg, DT)
    log = _log(caplog)
    for tr in m.transitions:
        assert ("INFO", f"mission {tr.src.value} -> {tr.dst.value} ({tr.reason})") in log
    assert ("INFO", f"authority waiting -> command ({AuthorityCause.ARMING.value})") in log
    assert ("WARNING", "fleet command go (swarm-wide) in state FLOW: already flying") in log
    assert ("INFO", "fleet command hold (swarm-wide) in state FLOW") in log
    assert ("INFO", "hold: grace over, requesting the autopilot's hold mode") in log
    assert ("INFO", "fleet command resume (addressed) in state HOLD") in log


def test_failsafes_and_refusals_are_logged_in_full(sfield, caplog):
    caplog.set_level("INFO", logger="fisc_agent.flight.mission")
    cfg, m, v = make(sfield, hold_grace_s=0.3, stale_timeout_s=0.5)
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW)
    status = v.status()._replace(integrity_ok=False, integrity_reason="estimator reset (x 1.2 m)")
    step(m, status)
    assert ("WARNING", "position integrity: estimator reset (x 1.2 m); holding until the track is consistent "
                       "again") in _log(caplog)
    assert m.reason == "position jump: estimator reset (x 1.2 m)"
    cfg, m, v = make(sfield)
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW)
    step(m, v.status()._replace(integrity_ok=False, integrity_reason=""))  # no reason given
    assert ("WARNING", "position integrity: estimator reset; holding until the track is consistent again") in _log(caplog)
    assert m.hold_cause == HoldCause.POSITION_JUMP and m.reason == "position jump: reset"
    cfg, m, v = make(sfield, hold_grace_s=0.3, stale_timeout_s=0.5)
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW)
    v.drop_position = True
    run(m, v, cfg, lambda m, v, o: o.want_mode == "hold", max_s=v.t + 3)
    lost = [text for level, text in _log(caplog) if text.startswith("position lost for ")]
    assert len(lost) == 1 and re.fullmatch(r"position lost for \d+\.\d s: requesting the autopilot's hold mode", lost[0])
    m.command("resume")
    run_for(m, v, cfg, DT)
    assert ("WARNING", "fleet resume refused: position is lost; carried out if it is good within 5 s") in _log(caplog)
    v.drop_position, v.mute = False, True
    run(m, v, cfg, lambda m, v, o: m.hold_cause == HoldCause.LINK_LOST, max_s=v.t + 10)
    age = v.t - DT - v.last_hb
    assert ("WARNING", f"link lost: no autopilot HEARTBEAT for {age:.1f} s; the autopilot's offboard-loss failsafe "
                       "is in charge") in _log(caplog)


def test_hands_off_and_not_ours_are_logged_in_full(sfield, caplog):
    caplog.set_level("INFO", logger="fisc_agent.flight.mission")
    cfg, m, v = make(sfield)
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW)
    v.mode = "other"
    run(m, v, cfg, lambda m, v, o: m.hands_off)
    assert ("WARNING", "mode changed to other outside the agent (in FLOW): hands off, no mode request and no "
                       "setpoint until a command addressed to this agent") in _log(caplog)
    caplog.clear()
    cfg, m, v = _armed_by_someone_else(sfield, (1.0, 0.1, 0.1))     # with --go: the go is withdrawn
    assert ("WARNING", "the go is withdrawn: the vehicle was armed by someone else") in _log(caplog)
    assert ("INFO", f"authority waiting -> not-ours ({AuthorityCause.ARMED_BY_OTHER.value})") in _log(caplog)
    from fisc_agent.flight.mission import Mission
    m = Mission(cfg)                                   # no map: a takeover is refused
    m.command(FleetOrder(MissionCommand.TAKEOVER, addressed=True))
    step(m, v.status())
    assert ("WARNING", "takeover refused: no good position or no map yet") in _log(caplog)


def test_a_fault_while_landing_asks_for_nothing(sfield):
    cfg, m, v = make(sfield)
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW)
    m.command("hold")                                  # an armed hold ...
    run_for(m, v, cfg, 0.2)
    m.command("land")                                  # ... then a landing: the fault must not ask for offboard
    run_for(m, v, cfg, DT)
    assert m.state == State.LAND
    assert m.fault(v.t, "tick raised") == MissionOutput(State.LAND, None, None, None, None, -1, m.reason)
    assert all(o.want_armed is None for o in run_for(m, v, cfg, 0.5))  # landing: arming left alone


def test_not_arming_names_every_blocker(sfield):
    cfg, m, _ = make_h(sfield, min_battery_pct=25.0)
    v = HealthVehicle()
    v.health = VehicleHealth(battery_pct=24.0, estimator_ok=False, estimator_detail="no GPS fix")
    run_for(m, v, cfg, 0.3)
    assert m.reason.cause == Cause.NOT_READY
    assert str(m.reason) == "not arming: battery 24 % < 25 %; estimator: no GPS fix"


def test_a_restored_fleet_hold_keeps_the_vehicle_on_the_ground_saying_so(sfield):
    from fisc_agent.flight.mission import Mission
    from fisc_agent.flight.state_file import AgentState

    cfg, _, v = make(sfield)
    m = Mission(cfg, sfield, restored=AgentState(fleet_hold=True))
    run_for(m, v, cfg, 0.2)
    assert m.hold_cause == HoldCause.FLEET_ON_GROUND and not v.armed
    assert str(m.reason) == "fleet hold (restored from the state file)"
