"""The authority model (issue 36): a go to arm, never take over, hands off in every state, health
that gates arming and ends the laps, position-jump holds, restarts from the state file.

The pure rules (``ModeWatch``, ``fleet_action``, ``readiness``, ``state_file``) are tested at their
boundaries; the mission's use of them on the point vehicle of ``test_agent_mission``.
"""

from __future__ import annotations

import json

import pytest
from test_agent_mission import DT, SimVehicle, make, run, run_for  # noqa: F401 (sfield fixture below)

from fisc_agent.config import AgentConfig
from fisc_agent.flight.authority import MODE_ECHO_S, SUPERSEDED_ECHO_S, FleetAction, ModeWatch, fleet_action
from fisc_agent.flight.control import MapGeometry, ScalarField
from fisc_agent.flight.flightlog import FlightLog, rotate
from fisc_agent.flight.health import LandedState, SystemState, VehicleHealth
from fisc_agent.flight.integrity import IntegrityConfig
from fisc_agent.flight.mission import Mission
from fisc_agent.flight.fleet_orders import ARM_ANSWER_S, RESUME_WAIT_S
from fisc_agent.flight.mission_types import JUMP_HOLD_GRACE_S
from fisc_agent.flight.mission_types import Authority, Cause, FleetOrder, HoldCause, MissionCommand, State
from fisc_agent.flight.readiness import HealthKind, arming_blockers, battery_low, distance_to_box_m, health_problems
from fisc_agent.flight.state_file import AgentState, default_state_path, load_state, save_state
from fisc_agent.map.lookup import CommandField
from fisc_agent.mavlink.adapters import ModeClass

OFFBOARD, HOLD, LAND, OTHER, UNKNOWN = (ModeClass.OFFBOARD, ModeClass.HOLD, ModeClass.LAND, ModeClass.OTHER,
                                        ModeClass.UNKNOWN)


@pytest.fixture(scope="module")
def sfield(tunnel_map):
    return ScalarField(CommandField.from_map(tunnel_map))


class HealthVehicle(SimVehicle):
    """The point vehicle with a health report and a position-integrity verdict."""

    def __init__(self, autopilot="px4"):
        super().__init__(autopilot)
        self.health = VehicleHealth()
        self.integrity = (True, "")

    def status(self):
        return super().status()._replace(health=self.health, integrity_ok=self.integrity[0],
                                         integrity_reason=self.integrity[1])


def make_h(sfield, **kw):
    cfg, _, _ = make(sfield, **kw)
    return cfg, Mission(cfg, sfield), HealthVehicle()


def to_flow(m, v, cfg):
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW)


def silent(outs):
    return all(o.want_mode is None and o.want_armed is None and o.velocity_m_s is None for o in outs)


# ---- ModeWatch -------------------------------------------------------------------------------

def test_mode_watch_tells_own_changes_from_foreign_ones_at_the_echo_boundary():
    w = ModeWatch()
    assert w.observe(0.0, OTHER) is None                      # first sight is a baseline, not a change
    w.want(1.0, OFFBOARD)
    assert w.observe(1.0 + MODE_ECHO_S, OFFBOARD) is None     # wanted exactly echo_s ago: ours
    assert w.observe(2.0, OFFBOARD) is None                   # no change
    assert w.observe(2.0, UNKNOWN) is None and w.last_seen == OFFBOARD   # unknown is never a change
    w2 = ModeWatch(last_seen=OTHER)
    w2.want(0.0, OFFBOARD)
    assert w2.observe(MODE_ECHO_S + 1e-6, OFFBOARD) == OFFBOARD   # just outside the echo: foreign
    w3 = ModeWatch(last_seen=OFFBOARD)
    w3.want(5.0, HOLD)
    assert w3.observe(5.1, LAND) == LAND                       # a mode never asked for: foreign
    assert w3.observe(5.2, HOLD) is None                       # back to the wanted one: ours
    w3.forget()
    assert w3.observe(5.3, OFFBOARD) == OFFBOARD               # after forget() every change is foreign


def test_a_superseded_wanted_mode_is_the_agents_own_only_briefly():
    """The agent asked for HOLD for one tick, then OFFBOARD again: the autopilot's late answer to the
    HOLD request is its own within SUPERSEDED_ECHO_S of the last HOLD want, a ground station's HOLD
    after that is foreign (it was read as the agent's own for MODE_ECHO_S: the agent fought the ground)."""
    for seen_after, foreign in ((SUPERSEDED_ECHO_S - 1e-6, False), (SUPERSEDED_ECHO_S, False),
                                (SUPERSEDED_ECHO_S + 1e-6, True), (MODE_ECHO_S - 0.5, True)):
        w = ModeWatch(last_seen=OFFBOARD)
        w.want(10.0, HOLD)
        w.want(10.05, OFFBOARD)
        assert (w.observe(10.0 + seen_after, HOLD) == HOLD) is foreign, seen_after
    w = ModeWatch(last_seen=OTHER)
    w.want(10.0, HOLD)
    w.want(10.05, None)                                        # wanting none supersedes nothing
    assert w.observe(10.0 + MODE_ECHO_S, HOLD) is None
    assert SUPERSEDED_ECHO_S < MODE_ECHO_S


# ---- fleet_action: the rule table ------------------------------------------------------------

def _order(cmd, addressed=False):
    return FleetOrder(MissionCommand(cmd), addressed=addressed)


@pytest.mark.parametrize("cmd, addressed, authority, armed, holding, action", [
    ("go", False, Authority.WAITING, False, False, FleetAction.GO),
    ("go", True, Authority.WAITING, False, False, FleetAction.GO),
    ("go", False, Authority.COMMAND, True, False, FleetAction.IGNORE),
    ("go", False, Authority.NOT_OURS, True, False, FleetAction.IGNORE),
    ("go", False, Authority.RELEASED, False, False, FleetAction.IGNORE),      # one flight per process
    ("takeover", False, Authority.NOT_OURS, True, False, FleetAction.IGNORE),  # must be addressed
    ("takeover", True, Authority.NOT_OURS, True, False, FleetAction.TAKEOVER),
    ("takeover", True, Authority.HANDS_OFF, True, True, FleetAction.TAKEOVER),
    ("takeover", True, Authority.WAITING, False, False, FleetAction.GO),       # a disarmed vehicle: a go
    ("takeover", True, Authority.COMMAND, True, False, FleetAction.IGNORE),
    ("resume", False, Authority.HANDS_OFF, True, True, FleetAction.IGNORE),    # swarm-wide: not back
    ("resume", True, Authority.HANDS_OFF, True, True, FleetAction.TAKEOVER),   # addressed: back
    ("resume", True, Authority.HANDS_OFF, False, True, FleetAction.IGNORE),    # disarmed: nothing to resume
    ("resume", False, Authority.COMMAND, True, True, FleetAction.RESUME),
    ("resume", False, Authority.COMMAND, True, False, FleetAction.IGNORE),     # not holding
    ("resume", True, Authority.NOT_OURS, True, False, FleetAction.IGNORE),
    ("hold", False, Authority.COMMAND, True, False, FleetAction.HOLD),
    ("hold", False, Authority.WAITING, False, False, FleetAction.HOLD),
    ("hold", False, Authority.NOT_OURS, True, False, FleetAction.IGNORE),
    ("hold", True, Authority.HANDS_OFF, True, True, FleetAction.IGNORE),
    ("land", False, Authority.COMMAND, True, False, FleetAction.LAND),
    ("land", False, Authority.WAITING, False, False, FleetAction.END),
    ("land", False, Authority.NOT_OURS, True, False, FleetAction.IGNORE),
    ("land", True, Authority.HANDS_OFF, True, True, FleetAction.IGNORE),
])
def test_fleet_action_table(cmd, addressed, authority, armed, holding, action):
    verdict = fleet_action(_order(cmd, addressed), authority, armed, holding)
    assert verdict.action == action
    assert (verdict.note == "") == (action != FleetAction.IGNORE)  # every refusal says why



NOT_OURS_NOTE = "the vehicle is not ours (armed by someone else); only an addressed takeover hands it over"
HANDS_OFF_NOTE = ("hands off (the mode was changed outside the agent): only a resume or takeover addressed to "
                  "this agent gives it back")


@pytest.mark.parametrize("cmd, addressed, authority, armed, holding, note", [
    ("go", False, Authority.RELEASED, False, False, "the flight is over (a go is good for one flight of one process)"),
    ("takeover", False, Authority.NOT_OURS, True, False, "takeover must be addressed to this agent (--agents ID)"),
    ("takeover", True, Authority.COMMAND, True, False, "already in command"),
    ("hold", False, Authority.NOT_OURS, True, False, NOT_OURS_NOTE),
    ("resume", True, Authority.HANDS_OFF, False, True, "hands-off vehicle is disarmed: nothing to resume"),
    ("go", True, Authority.HANDS_OFF, True, True, HANDS_OFF_NOTE),
    ("go", False, Authority.COMMAND, True, False, "already flying"),
    ("resume", False, Authority.COMMAND, True, False, "not holding"),
])
def test_every_ignored_order_says_exactly_why(cmd, addressed, authority, armed, holding, note):
    verdict = fleet_action(_order(cmd, addressed), authority, armed, holding)
    assert (verdict.action, verdict.note) == (FleetAction.IGNORE, note)


def test_land_in_command_needs_the_vehicle_armed():
    """In command but already disarmed (landed): the flight ends, no land is sent."""
    assert fleet_action(_order("land"), Authority.COMMAND, False, False).action == FleetAction.END
    assert fleet_action(_order("land"), Authority.COMMAND, True, True).action == FleetAction.LAND

# ---- readiness -------------------------------------------------------------------------------

def test_battery_rule_boundaries():
    assert not battery_low(VehicleHealth(battery_pct=20.0), 20.0)         # equal: not below
    assert battery_low(VehicleHealth(battery_pct=19.99), 20.0)
    assert not battery_low(VehicleHealth(battery_pct=None), 20.0)         # unknown: no rule
    assert not battery_low(VehicleHealth(battery_pct=0.0), None)          # rule off
    assert not battery_low(VehicleHealth(battery_pct=0.0), 0.0)


def test_health_problems_are_typed():
    h = VehicleHealth(battery_pct=10.0, estimator_ok=False, estimator_detail="pos_horiz_abs",
                      system_state=SystemState.CRITICAL)
    kinds = [p.kind for p in health_problems(h, 20.0)]
    assert kinds == [HealthKind.BATTERY, HealthKind.ESTIMATOR, HealthKind.SYSTEM]
    assert health_problems(VehicleHealth(estimator_ok=None, system_state=SystemState.ACTIVE), 20.0) == ()
    assert health_problems(VehicleHealth(system_state=SystemState.STANDBY, estimator_ok=True), 20.0) == ()
    unsaid = health_problems(VehicleHealth(estimator_ok=False), None)  # bad, and the autopilot said nothing more
    assert [(p.kind, p.text) for p in unsaid] == [(HealthKind.ESTIMATOR, "estimator: not healthy")]


def test_distance_to_box_and_the_start_distance_gate(sfield):
    lo, hi = (0.0, 0.0, 0.0), (1.0, 2.0, 3.0)
    assert distance_to_box_m((0.5, 1.0, 1.0), lo, hi) == 0.0 and distance_to_box_m((1.0, 2.0, 3.0), lo, hi) == 0.0
    assert distance_to_box_m((-3.0, 6.0, 3.0), lo, hi) == pytest.approx(5.0)
    geom = MapGeometry.from_field(sfield.field)
    cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=1, max_start_distance_m=10.0)
    x0 = geom.lo_m[0]
    at = (x0 - 10.0, geom.lo_m[1], geom.lo_m[2])
    assert arming_blockers(VehicleHealth(), cfg, at, geom) == []                 # exactly the limit
    blocked = arming_blockers(VehicleHealth(), cfg, (x0 - 10.001, geom.lo_m[1], geom.lo_m[2]), geom)
    assert blocked == ["start point 10 m from the map (more than 10 m: check --origin / --geodetic-anchor)"]
    far = (x0 - 1000.0, geom.lo_m[1], geom.lo_m[2])
    assert arming_blockers(VehicleHealth(), cfg, far, None) == []           # no map yet: nothing to measure
    assert arming_blockers(VehicleHealth(), cfg, None, geom) == []          # no position yet: likewise


# ---- the mission ----------------------------------------------------------------------------

def test_no_arming_without_a_go_then_a_fleet_go_arms(sfield):
    cfg, m, v = make_h(sfield, go=False)
    outs = run_for(m, v, cfg, 5.0)
    assert m.state == State.STANDBY and m.authority == Authority.WAITING and m.reason.cause == Cause.WAITING_GO
    assert silent(outs) and not v.armed and v.modes == []
    m.command(FleetOrder(MissionCommand.GO))
    run(m, v, cfg, lambda m, v, o: m.state == State.TAKEOFF, max_s=v.t + 5)
    assert m.authority == Authority.COMMAND and v.armed


def test_a_go_is_withdrawn_when_someone_else_arms_and_is_good_for_one_flight(sfield):
    cfg, m, v = make_h(sfield, go=True, exit_policy="land")
    v.armed = True                                   # a ground station arms it before the agent acts
    run_for(m, v, cfg, 1.0)
    assert m.authority == Authority.NOT_OURS
    v.armed = False                                  # ... and disarms it again
    outs = run_for(m, v, cfg, 2.0)
    assert m.authority == Authority.WAITING and silent(outs) and not v.armed   # --go was withdrawn
    m.command("go")
    run(m, v, cfg, lambda m, v, o: m.state == State.DONE, max_s=v.t + 120)
    assert m.authority == Authority.RELEASED and m.reason.cause == Cause.LANDED
    m.command("go")                                  # the flight is over: no second flight
    outs = run_for(m, v, cfg, 2.0)
    assert m.state == State.DONE and silent(outs) and not v.armed


@pytest.mark.parametrize("until", [State.ARM, State.TAKEOFF, State.JOIN, State.FLOW, "hold-zero", "hold-mode"])
def test_a_ground_station_mode_change_makes_it_hands_off_in_every_state(sfield, until):
    cfg, m, v = make_h(sfield, hold_grace_s=1.0)
    if until == State.ARM:
        v.mute = True                                # the autopilot ignores the agent: ARM goes on
        run(m, v, cfg, lambda m, v, o: m.state == State.ARM)
        run_for(m, v, cfg, 0.5)
        v.mute = False
        v.mode = "hold"                              # ... and a ground station picks its own mode
        v.last_hb = v.t
    else:
        target = {"hold-zero": State.FLOW, "hold-mode": State.FLOW}.get(until, until)
        run(m, v, cfg, lambda m, v, o: m.state == target)
        if until == "hold-zero":
            m.command("hold")
            run_for(m, v, cfg, 0.3)
        elif until == "hold-mode":
            m.command("hold")
            run(m, v, cfg, lambda m, v, o: v.mode == "hold")
            run_for(m, v, cfg, 0.2)
        v.mode = "other"                             # a pilot switches to POSCTL
    before = list(v.modes)
    outs = run_for(m, v, cfg, 3.0)
    assert m.authority == Authority.HANDS_OFF and m.hold_cause == HoldCause.PILOT_OVERRIDE
    assert silent(outs[1:]) and v.modes == before    # no further mode request, no setpoint
    m.command("resume")                              # a fleet-wide resume does not take it back
    assert silent(run_for(m, v, cfg, 1.0)) and m.hands_off


def test_failsafe_land_after_a_link_loss_is_never_overridden(sfield):
    cfg, m, v = make_h(sfield)
    to_flow(m, v, cfg)
    v.mute = True                                    # the link drops ...
    run(m, v, cfg, lambda m, v, o: m.hold_cause == HoldCause.LINK_LOST)
    v.mode = "land"                                  # ... the autopilot's failsafe lands meanwhile
    run_for(m, v, cfg, 1.0)
    v.mute = False                                   # the link returns
    z0, requested = v.pos[2], list(v.modes)
    outs = run_for(m, v, cfg, 0.5)
    assert m.hands_off and v.mode == "land" and silent(outs[1:]) and v.pos[2] < z0
    outs = run(m, v, cfg, lambda m, v, o: m.state == State.DONE, max_s=v.t + 10)  # it lands where it was
    assert silent(outs) and v.modes == requested and m.reason.cause == Cause.DISARMED_IN_FLIGHT


def test_takeoff_timeout_lands(sfield):
    cfg, m, v = make_h(sfield, takeoff_timeout_s=2.0)
    v.health = VehicleHealth(landed=LandedState.ON_GROUND)   # stuck on the ground (e.g. a prop guard)
    run(m, v, cfg, lambda m, v, o: m.state == State.TAKEOFF)
    t0 = v.t
    run(m, v, cfg, lambda m, v, o: m.state == State.LAND, max_s=v.t + 5)
    assert m.reason.cause == Cause.TAKEOFF_TIMEOUT and v.t - t0 == pytest.approx(2.0, abs=2 * DT)


def test_low_battery_ends_the_laps_at_the_exit(sfield):
    cfg, m, v = make_h(sfield, exit_policy="loop", laps=0, min_battery_pct=30.0, low_battery_action="hold")
    v.health = VehicleHealth(battery_pct=30.0)       # equal to the minimum: flies on
    to_flow(m, v, cfg)
    v.health = VehicleHealth(battery_pct=29.0)       # below it mid-pass: the pass is finished ...
    assert m.state == State.FLOW
    run(m, v, cfg, lambda m, v, o: m.state != State.FLOW)
    assert m.state == State.EXIT and m.reason.cause == Cause.LOW_BATTERY and m.laps == 1
    assert str(m.reason) == "battery 29 % below 30 % after lap 1: to the exit, then hold"
    run(m, v, cfg, lambda m, v, o: m.state == State.HOLD)   # ... then the low-battery action at the exit
    assert m.hold_cause == HoldCause.EXIT


def test_no_arming_below_the_minimum_battery_or_with_a_bad_estimator(sfield):
    cfg, m, v = make_h(sfield, min_battery_pct=25.0)
    v.health = VehicleHealth(battery_pct=24.0)
    assert silent(run_for(m, v, cfg, 1.0)) and m.reason.cause == Cause.NOT_READY and "battery" in m.reason
    v.health = VehicleHealth(battery_pct=90.0, estimator_ok=False, estimator_detail="no GPS fix")
    run_for(m, v, cfg, 0.5)
    assert m.state == State.STANDBY and "estimator: no GPS fix" in m.reason and not v.armed
    v.health = VehicleHealth(battery_pct=90.0, estimator_ok=True)
    run(m, v, cfg, lambda m, v, o: m.state == State.TAKEOFF, max_s=v.t + 5)


def test_a_position_jump_holds_then_resumes_on_a_consistent_track(sfield):
    cfg, m, v = make_h(sfield)
    to_flow(m, v, cfg)
    v.integrity = (False, "reset counter stepped")
    run_for(m, v, cfg, 0.2)
    assert m.hold_cause == HoldCause.POSITION_JUMP and "reset counter" in m.reason
    v.integrity = (True, "")
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, max_s=v.t + 1)
    assert m.transitions[-1].reason.cause == Cause.POSITION_BACK


def test_a_long_position_jump_escalates_to_hold_mode_and_still_resumes(sfield):
    """A real EKF3 GPS glitch lasts ~15 s (SITL): the hold escalates to the autopilot's hold mode after
    --hold-grace but, unlike a lost position, is not latched: a consistent track flies on."""
    cfg, m, v = make_h(sfield, hold_grace_s=1.0)
    to_flow(m, v, cfg)
    v.integrity = (False, "estimator: GNSS glitch")
    run_for(m, v, cfg, 5.0)
    assert m.hold_cause == HoldCause.POSITION_JUMP and v.mode == "hold"
    v.integrity = (True, "")
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW and v.mode == "offboard", max_s=v.t + 2)
    assert m.authority == Authority.COMMAND


def test_a_position_jump_hold_escalates_only_after_the_estimator_reset_could_have_ended(sfield):
    """An estimator reset ends after a consistent track of IntegrityConfig.consistent_s (2 s, as --hold-grace):
    a jump hold escalates at JUMP_HOLD_GRACE_S, not at --hold-grace (a stale-position hold does, below), so a
    routine reset never asks for the autopilot's hold mode on the tick before it ends by itself."""
    for grace_s, expected_s in [(2.0, JUMP_HOLD_GRACE_S), (JUMP_HOLD_GRACE_S + 1.0, JUMP_HOLD_GRACE_S + 1.0)]:
        cfg, m, v = make_h(sfield, hold_grace_s=grace_s)
        to_flow(m, v, cfg)
        v.integrity = (False, "reset counter stepped")
        outs = run(m, v, cfg, lambda m, v, o: o.want_mode == "hold", max_s=v.t + 10)
        held_s = v.t - m.transitions[-1].t_s
        assert m.hold_cause == HoldCause.POSITION_JUMP and expected_s <= held_s < expected_s + 2 * DT, held_s
        assert outs[-2].want_mode == "offboard" and outs[-2].velocity_m_s == (0.0, 0.0, 0.0)
    assert JUMP_HOLD_GRACE_S == IntegrityConfig.consistent_s + 1.0


class LateArmVehicle(HealthVehicle):
    """Arms only when ``answer`` is set: an arm request still on its way when the agent's mission moves on."""

    def __init__(self):
        super().__init__()
        self.answer = False

    def apply(self, out, cfg):
        if not self.answer:
            out = out._replace(want_armed=None)
        super().apply(out, cfg)


def _held_in_arm(sfield):
    """A vehicle whose arming is slow, a fleet hold in ARM after the arm request went out."""
    cfg, _, _ = make(sfield)
    m, v = Mission(cfg, sfield), LateArmVehicle()
    run(m, v, cfg, lambda m, v, o: o.want_armed and v.mode == OFFBOARD)   # the request is out
    m.command("hold")
    t_hold = v.t
    outs = run_for(m, v, cfg, 0.5)
    assert m.hold_cause == HoldCause.FLEET_ON_GROUND and not v.armed
    return cfg, m, v, t_hold, outs


@pytest.mark.parametrize("disarmed_by_autopilot", [False, True])
def test_an_arm_landing_after_a_fleet_hold_in_arm_is_kept_streamed_and_resumed(sfield, disarmed_by_autopilot):
    """Real PX4 (2026-12-07): a hold 0.6 s after the arm request left the vehicle armed without setpoints;
    PX4 changed its mode, the agent went hands-off and the flight ended.  Now the hold streams zero velocity in
    offboard while the answer may come and while its vehicle is armed; a resume takes off, or re-arms if the
    autopilot disarmed it on the ground meanwhile."""
    cfg, m, v, t_hold, outs = _held_in_arm(sfield)
    assert all(o.velocity_m_s == (0.0, 0.0, 0.0) and o.want_mode == OFFBOARD and o.want_armed is None for o in outs)
    v.answer = True                                  # the autopilot's answer: armed, in offboard
    v.armed = True
    outs = run_for(m, v, cfg, 10.0)                  # long past the answer's window: armed, still streamed
    assert v.t - t_hold > ARM_ANSWER_S + 5
    assert all(o.velocity_m_s == (0.0, 0.0, 0.0) and o.want_mode == OFFBOARD for o in outs)
    assert m.authority == Authority.COMMAND and m.hold_cause == HoldCause.FLEET_ON_GROUND and v.pos[2] == v.ground_z
    if disarmed_by_autopilot:                        # PX4's pre-flight disarm (COM_DISARM_PRFLT)
        v.armed = False
        outs = run_for(m, v, cfg, 2.0)
        assert silent(outs) and m.hold_cause == HoldCause.FLEET_ON_GROUND and m.authority == Authority.COMMAND
    m.command("resume")
    run(m, v, cfg, lambda m, v, o: m.state == State.JOIN, max_s=v.t + 15)
    expect = [State.STANDBY, State.ARM] if disarmed_by_autopilot else [State.ARM]
    assert [tr.dst for tr in m.transitions if tr.t_s >= t_hold][1:len(expect) + 1] == expect
    assert not m.hands_off


def test_a_fleet_hold_in_arm_stops_streaming_when_the_arm_was_never_answered(sfield):
    cfg, m, v, t_hold, outs = _held_in_arm(sfield)
    outs = run_for(m, v, cfg, ARM_ANSWER_S + 1.0)
    times = [t_hold + 0.5 + DT * (k + 1) for k in range(len(outs))]
    streamed = [t for t, o in zip(times, outs) if o.velocity_m_s is not None]
    assert streamed and max(streamed) < t_hold + ARM_ANSWER_S + 2 * DT   # the answer's window, then silence
    assert silent(o for t, o in zip(times, outs) if t > t_hold + ARM_ANSWER_S + 2 * DT)
    assert m.hold_cause == HoldCause.FLEET_ON_GROUND and not v.armed


def test_a_fleet_hold_before_arming_streams_nothing(sfield):
    cfg, m, v = make_h(sfield, go=False)
    run_for(m, v, cfg, 1.0)
    m.command("hold")
    outs = run_for(m, v, cfg, 1.0)
    assert m.hold_cause == HoldCause.FLEET_ON_GROUND and silent(outs)


def test_restart_restores_a_fleet_hold_on_the_ground(sfield):
    cfg, _, _ = make(sfield)
    m = Mission(cfg, sfield, restored=AgentState(fleet_hold=True, laps=3))
    v = HealthVehicle()
    outs = run_for(m, v, cfg, 2.0)
    assert m.hold_cause == HoldCause.FLEET_ON_GROUND and silent(outs) and m.saved_state().fleet_hold
    m.command("resume")
    run(m, v, cfg, lambda m, v, o: m.state == State.TAKEOFF, max_s=v.t + 5)
    assert m.laps == 0 and not m.saved_state().fleet_hold     # a new flight counts its own laps


def test_restart_hands_off_stays_hands_off(sfield):
    cfg, _, _ = make(sfield)
    m = Mission(cfg, sfield, restored=AgentState(hands_off=True))
    v = HealthVehicle()
    outs = run_for(m, v, cfg, 2.0)
    assert m.hands_off and silent(outs) and m.saved_state().hands_off


# ---- state file and flight-log rotation ------------------------------------------------------

def test_state_file_round_trip_and_corrupt_files_kept_aside(tmp_path, caplog):
    p = tmp_path / "s" / "agent.json"
    assert load_state(p) == AgentState()                       # first start
    st = AgentState(hands_off=True, fleet_hold=False, laps=4, command_floors={"ab12": 17})
    save_state(p, st)
    assert load_state(p) == st and json.loads(p.read_text())["version"] == 1
    for bad, field in (('{"version": 1, "laps": -1}', "laps"), ('{"version": 1, "hands_off": 1}', "hands_off"),
                       ('{"version": 1, "command_floors": {"k": -2}}', "command_floors"),
                       ('{"version": 2}', "version"), ("not json", "not JSON")):
        p.write_text(bad)
        assert load_state(p) == AgentState()
        assert field in caplog.text and (p.parent / "agent.json.corrupt").read_text() == bad
    assert default_state_path(3, "demo").name == "agent-demo-3.json"
    assert default_state_path(3, None).name == "agent-local-3.json"


def test_flight_logs_rotate_and_are_never_truncated(tmp_path):
    p = tmp_path / "f.csv"
    assert rotate(p) is None                                   # nothing to keep
    for i in range(3):
        FlightLog(p).close()
        p.write_text(p.read_text() + f"flight {i}\n")
    assert (tmp_path / "f.csv.1").read_text().endswith("flight 1\n")
    assert (tmp_path / "f.csv.2").read_text().endswith("flight 0\n")
    assert p.read_text().endswith("flight 2\n")
    for _ in range(12):
        p.write_text("x")
        rotate(p, keep=3)
    assert sorted(q.name for q in tmp_path.iterdir()) == ["f.csv.1", "f.csv.2", "f.csv.3"]


def test_a_mode_change_on_the_disarm_heartbeat_after_landing_is_a_landing(sfield):
    """PX4 reports OFFBOARD again on the HEARTBEAT that says it disarmed after its landing: the flight
    ends 'landed', not 'pilot override'."""
    cfg, m, v = make_h(sfield)
    to_flow(m, v, cfg)
    m.command("land")
    run(m, v, cfg, lambda m, v, o: m.state == State.LAND and v.mode == "land")
    v.armed, v.mode = False, "offboard"          # touchdown: disarmed, and PX4's intended mode shows again
    run_for(m, v, cfg, 0.1)
    assert m.state == State.DONE and m.reason.cause == Cause.LANDED and m.authority == Authority.RELEASED


def test_a_blind_position_hold_requests_no_mode_before_the_link_is_called_lost(sfield):
    """Position and HEARTBEATs both stop (a cut link): no hold-mode request at --stale-timeout +
    --hold-grace, where it could land on a failsafe's Land; with HEARTBEATs still heard it escalates."""
    cfg, m, v = make_h(sfield, hold_grace_s=1.0)
    to_flow(m, v, cfg)
    requested = list(v.modes)
    v.mute = True                                   # nothing heard, nothing received
    outs = run_for(m, v, cfg, cfg.link_timeout_s - 0.1)
    assert m.hold_cause == HoldCause.POSITION_STALE and all(o.want_mode != ModeClass.HOLD for o in outs)
    assert v.modes == requested
    cfg2, m2, v2 = make_h(sfield, hold_grace_s=1.0)
    to_flow(m2, v2, cfg2)
    v2.drop_position = True                         # only the position stops: the autopilot is heard
    run_for(m2, v2, cfg2, cfg2.stale_timeout_s + cfg2.hold_grace_s + 0.2)
    assert v2.mode == "hold"


def _lost_and_held(sfield):
    """A vehicle flowing, then its position lost until the mission holds (latched): (cfg, mission, vehicle)."""
    cfg, m, v = make(sfield, hold_grace_s=0.3, stale_timeout_s=0.5)
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW)
    v.drop_position = True
    run(m, v, cfg, lambda m, v, o: o.want_mode == "hold", max_s=v.t + 3)
    assert m.state == State.HOLD and m.hold_cause == HoldCause.POSITION_STALE
    return cfg, m, v


@pytest.mark.parametrize("back_after_s, resumed", [(0.0, True), (RESUME_WAIT_S - 0.2, True),
                                                    (RESUME_WAIT_S + 0.2, False)])
def test_a_resume_refused_for_its_position_is_carried_out_once_the_position_is_good_within_the_wait(
        sfield, back_after_s, resumed, caplog):
    caplog.set_level("INFO", logger="fisc_agent.flight.mission")
    cfg, m, v = _lost_and_held(sfield)
    m.command("resume")
    run_for(m, v, cfg, DT)
    assert m.state == State.HOLD                                # refused: the position is lost
    run_for(m, v, cfg, back_after_s)
    assert m.state == State.HOLD
    v.drop_position = False
    run_for(m, v, cfg, 0.5)
    assert (m.state == State.FLOW) is resumed, (m.state, m.reason)
    said = [r.getMessage() for r in caplog.records]
    assert any(t.startswith("fleet resume: the position is good again") for t in said) is resumed
    assert any(t.startswith("fleet resume dropped: the position is still lost") for t in said) is not resumed


def test_a_newer_fleet_order_replaces_a_resume_waiting_for_its_position(sfield):
    cfg, m, v = _lost_and_held(sfield)
    m.command("resume")
    run_for(m, v, cfg, DT)
    m.command("hold")                                           # the operator holds again before the fix is back
    run_for(m, v, cfg, DT)
    v.drop_position = False
    run_for(m, v, cfg, 1.0)
    assert m.state == State.HOLD and m.hold_cause == HoldCause.FLEET
