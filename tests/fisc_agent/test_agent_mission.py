"""Mission state machine on a simulated clock with a kinematic vehicle that obeys instantly."""

import json
import math
import pickle

import numpy as np
import pytest

from fisc_agent.config import AgentConfig
from fisc_agent.flight.control import MapGeometry, ScalarField, clamp_velocity, distance
from fisc_agent.flight.spacing import ENTRY_OPEN_FRACTION
from fisc_agent.map.lookup import CommandField, return_command
from fisc_agent.flight.failsafe import HANDOVER_S
from fisc_agent.flight.mission import Cause, HoldCause, Mission, Reason, State, VehicleStatus
from fisc_agent.flight.mission_types import Authority, FleetOrder, MissionCommand
from fisc_agent.flight.tracking import TrackingConfig
from fisc_agent.map.wall import DuctWall

DT = 0.05


class SimVehicle:
    """Map-frame point vehicle: takes the mission's wants at face value (no network)."""

    def __init__(self, autopilot="px4", pos=(0.0, 0.0, -3.0)):
        self.autopilot = autopilot
        self.pos = list(pos)
        self.ground_z = pos[2]
        self.vel = [0.0, 0.0, 0.0]
        self.armed = False
        self.mode = "other"
        self.t = 0.0
        self.last_fix = 0.0
        self.last_hb = 0.0
        self.drop_position = False
        self.mute = False
        self.takeoff_to = None
        self.modes = []
        self.gain = 1.0
        """Steady horizontal velocity gain: the vehicle flies ``gain`` times its horizontal setpoint."""
        self.velocity_bias = (0.0, 0.0, 0.0)
        """Added to the real motion in ``bias_states``, not to the reported velocity: an estimator's velocity bias."""
        self.bias_states = (State.FLOW,)
        """Mission states in which the vehicle really moves ``velocity_bias`` off what it reports."""

        self.fix_period_s = 0.0
        """A new fix at most this often (0: every tick); between fixes the last one is reported again."""
        self._fix = (tuple(self.pos), tuple(self.vel))
        self.clock_rate = 1.0
        """The autopilot's clock against the agent's (PX4 SITL on a loaded host: < 1): the vehicle moves
        at its velocity on its own clock."""
        self.stamp_fixes = False
        """Fixes carry the autopilot's own time (``VehicleStatus.fix_t_s``), as MAVLink's time_boot_ms."""
        self._fix_t = None

    def status(self):
        if not self.drop_position and not self.mute and self.t - self.last_fix >= self.fix_period_s - 1e-9:
            self.last_fix = self.t
            self._fix = (tuple(self.pos), tuple(self.vel))
            self._fix_t = self.clock_rate * self.t if self.stamp_fixes else None
        if not self.mute:
            self.last_hb = self.t
        pos, vel = self._fix if self.fix_period_s > 0 else (tuple(self.pos), tuple(self.vel))
        return VehicleStatus(self.t, pos, vel, self.t - self.last_fix, self.t - self.last_hb,
                             self.autopilot, self.armed, self.mode, fix_t_s=self._fix_t)

    def apply(self, out, cfg):
        if not self.mute:
            if out.want_mode is not None and out.want_mode != self.mode:
                self.mode = out.want_mode
                self.modes.append(self.mode)
            if out.want_armed and not self.armed and self.mode == "offboard":
                self.armed = True
            if out.takeoff_alt_m is not None and self.armed and self.takeoff_to is None:
                self.takeoff_to = self.ground_z + out.takeoff_alt_m
        v = (0.0, 0.0, 0.0)
        if self.mode == "land":
            v = (0.0, 0.0, -1.0)
        elif self.takeoff_to is not None and self.pos[2] < self.takeoff_to:
            v = (0.0, 0.0, 1.0)
        elif self.mode == "offboard" and out.velocity_m_s is not None and not self.mute:
            want = out.velocity_m_s
            want = (self.gain * want[0], self.gain * want[1], want[2])
            v = clamp_velocity(want, tuple(self.vel), DT, cfg.max_speed_m_s, cfg.max_accel_m_s2)
        if not self.armed:
            v = (0.0, 0.0, 0.0)
        self.vel = list(v)
        bias = self.velocity_bias if out.state in self.bias_states else (0.0, 0.0, 0.0)
        for i in range(3):
            self.pos[i] += (v[i] + bias[i]) * DT * self.clock_rate
        if self.pos[2] <= self.ground_z:
            self.pos[2] = self.ground_z
            if self.mode == "land":
                self.armed = False
        self.t += DT


def make(sfield, autopilot="px4", **kw):
    base = dict(mavlink_url="udpin:0.0.0.0:14540", agent_id=2, go=True, origin_ned_m=(0.0, 0.0, -3.0), takeoff_alt_m=1.0,
                max_speed_m_s=4.0, max_accel_m_s2=6.0, join_speed_m_s=3.0, climb_speed_m_s=2.0)
    base.update(kw)
    cfg = AgentConfig(**base)
    return cfg, Mission(cfg, sfield), SimVehicle(autopilot)


def step(m, status):
    """``m.step(status)``, checking what every step keeps: each transition it makes is stamped with the
    tick's time, leaves the state the one before entered, and carries a typed cause and a text (no
    ``None`` in it); the output reports the state and reason the mission is in."""
    src, n = m.state, len(m.transitions)
    out = m.step(status)
    for tr in m.transitions[n:]:
        assert tr.t_s == status.t_s and tr.src == src, (tr, status.t_s, src)
        assert isinstance(tr.reason, Reason) and isinstance(tr.reason.cause, (Cause, HoldCause)), tr
        assert tr.reason and "None" not in tr.reason, tr
        src = tr.dst
    assert m.state == src and out.state == m.state and out.reason is m.reason
    return out


def run(m, v, cfg, until, max_s=60.0, hook=None):
    outs = []
    while v.t < max_s:
        out = step(m, v.status())
        outs.append(out)
        if hook:
            hook(m, v, out)
        v.apply(out, cfg)
        if until(m, v, out):
            return outs
    raise AssertionError(f"timed out in {m.state} ({m.reason}); transitions: {m.transitions}")


def run_for(m, v, cfg, seconds):
    outs, end = [], v.t + seconds
    while v.t < end:
        out = step(m, v.status())
        outs.append(out)
        v.apply(out, cfg)
    return outs


@pytest.fixture(scope="module")
def sfield(tunnel_map):
    return ScalarField(CommandField.from_map(tunnel_map))


def states(m):
    return [m.transitions[0].src] + [t.dst for t in m.transitions]


OPEN_LOOP = dict(tracking=TrackingConfig(gain_1_s=0.0), lookahead_auto=False)
"""The paper's Algorithm 1: the map's command at the vehicle's own CV, no feedback, no look-ahead."""


def test_px4_full_pass_then_exit_hold(sfield):
    cfg, m, v = make(sfield, **OPEN_LOOP)
    geom = MapGeometry.from_field(sfield.field)
    inside_before_flow = []

    def hook(m, v, out):
        if m.state in (State.TAKEOFF, State.JOIN) and geom.in_box(tuple(v.pos)) and v.pos[0] > 0.05:
            inside_before_flow.append(tuple(v.pos))

    outs = run(m, v, cfg, lambda m, v, o: m.state == State.HOLD and o.want_mode == "hold", hook=hook)
    assert states(m) == [State.WAIT_POSITION, State.ARM, State.TAKEOFF, State.JOIN, State.FLOW, State.EXIT,
                         State.HOLD]
    assert m.laps == 1 and "exit" in m.reason
    assert inside_before_flow == []             # joined from outside, through the inlet
    flow = [o for o in outs if o.state == State.FLOW and o.velocity_m_s is not None]
    assert len(flow) > 10 and all(o.cv_id >= 0 for o in flow)
    # in FLOW the unclamped setpoint is exactly the map's command at the vehicle's CV
    assert all(o.velocity_m_s == sfield.command(0, 0, 0, 2, "mean", o.cv_id) for o in flow)
    arm = [o for o in outs if o.state == State.ARM]
    assert all(o.velocity_m_s == (0.0, 0.0, 0.0) for o in arm)   # PX4: stream before OFFBOARD
    assert v.pos[0] > geom.x_outlet_m


def test_agents_hold_after_the_outlet_at_their_own_points_spaced_apart(sfield):
    from fisc_agent.flight.control import hold_point

    geom = MapGeometry.from_field(sfield.field)
    held = {}
    for agent_id in (0, 1, 2):
        cfg, m, v = make(sfield, agent_id=agent_id, exit_spacing_m=1.5, **OPEN_LOOP)
        run(m, v, cfg, lambda m, v, o: m.state == State.HOLD and o.want_mode == "hold", max_s=120.0)
        held[agent_id] = np.array(v.pos)
        assert held[agent_id][0] == pytest.approx(geom.x_outlet_m + cfg.exit_clearance_m, abs=cfg.waypoint_radius_m)
        assert np.linalg.norm(held[agent_id] - hold_point(agent_id, geom, geom.x_outlet_m + cfg.exit_clearance_m,
                                                          1.5)) < cfg.waypoint_radius_m
    for a, b in ((0, 1), (0, 2), (1, 2)):   # they left the outlet decimetres apart; they hold >= 1.5 m apart
        assert np.linalg.norm(held[a][:2] - held[b][:2]) >= 1.5 - 2 * cfg.waypoint_radius_m   # horizontally


def test_agents_land_below_their_own_hold_spots_spaced_apart_horizontally(sfield):
    landed = {}
    for agent_id in (0, 1, 2):
        cfg, m, v = make(sfield, agent_id=agent_id, exit_policy="land", **OPEN_LOOP)
        outs = run(m, v, cfg, lambda m, v, o: m.state == State.LAND, max_s=120.0)
        landed[agent_id] = np.array(v.pos[:2])   # LAND comes straight down from here
        assert outs[-1].state == State.LAND
    for a, b in ((0, 1), (0, 2), (1, 2)):
        assert np.linalg.norm(landed[a] - landed[b]) >= 1.5 - 2 * cfg.waypoint_radius_m


def test_ardupilot_takes_off_by_command_without_setpoints(sfield):
    cfg, m, v = make(sfield, autopilot="ardupilot", exit_policy="land")
    outs = run(m, v, cfg, lambda m, v, o: m.state == State.DONE)
    take = [o for o in outs if o.state == State.TAKEOFF]
    assert take and all(o.velocity_m_s is None for o in take)
    assert all(o.takeoff_alt_m == 1.0 for o in take[1:])
    assert states(m)[-3:] == [State.EXIT, State.LAND, State.DONE]
    assert m.reason == "landed and disarmed" and not v.armed


def test_loop_policy_flies_the_requested_laps(sfield):
    cfg, m, v = make(sfield, exit_policy="loop", laps=2)
    run(m, v, cfg, lambda m, v, o: m.state == State.HOLD, max_s=120)
    assert m.laps == 2
    assert states(m).count(State.FLOW) == 2 and states(m).count(State.JOIN) == 2


def _fly_to_flow(m, v, cfg):
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW)
    run(m, v, cfg, lambda m, v, o: v.pos[0] > 0.8)


def test_stale_position_zero_hold_then_auto_resume(sfield):
    cfg, m, v = make(sfield)
    _fly_to_flow(m, v, cfg)
    v.drop_position = True
    outs = run(m, v, cfg, lambda m, v, o: v.t - v.last_fix > 1.0)
    assert m.state == State.HOLD and m.reason == "position stale"
    assert outs[-1].velocity_m_s == (0.0, 0.0, 0.0) and outs[-1].want_mode == "offboard"
    v.drop_position = False
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, max_s=v.t + 1)
    assert m.transitions[-1].reason == "position fix back"


def test_position_lost_escalates_to_autopilot_hold_and_waits_for_resume(sfield):
    cfg, m, v = make(sfield, hold_grace_s=1.0)
    _fly_to_flow(m, v, cfg)
    v.drop_position = True
    outs = run(m, v, cfg, lambda m, v, o: o.want_mode == "hold")
    assert m.state == State.HOLD and m.reason == "position stale"  # the hold is the stale-position one
    assert [t.reason for t in m.transitions].count("position stale") == 1
    assert v.t - v.last_fix > cfg.stale_timeout_s + cfg.hold_grace_s - 2 * DT
    assert outs[-1].velocity_m_s == (0.0, 0.0, 0.0)  # handing over: zero while the request waits, still in offboard
    outs = run_for(m, v, cfg, HANDOVER_S)
    assert outs[-1].velocity_m_s is None and outs[-1].want_mode == "hold"  # then nothing (refused: the failsafe's)
    v.drop_position = False
    outs = run_for(m, v, cfg, 2.0)
    assert outs[-1].want_mode == "hold"
    assert m.state == State.HOLD                    # latched: no automatic resume
    m.command("resume")
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, max_s=v.t + 10)


def test_geofence_hold(sfield):
    cfg, m, v = make(sfield, geofence="hold")
    _fly_to_flow(m, v, cfg)
    v.pos[1] = 2.5                                   # pushed out through the side
    outs = run(m, v, cfg, lambda m, v, o: m.state == State.HOLD)
    # at the spot where it began, the geofence's hold keeps it (KEEPING_SPOT): zero but the learnt bias (~1e-16)
    assert m.reason.startswith("geofence") and outs[-1].velocity_m_s == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
    assert m.hold_cause == HoldCause.GEOFENCE and outs[-1].reason.cause == HoldCause.GEOFENCE
    outs = run(m, v, cfg, lambda m, v, o: o.want_mode == "hold")
    m.command("resume")                              # resume from a geofence hold flies back
    run(m, v, cfg, lambda m, v, o: m.state == State.RETURN, max_s=v.t + 1)
    y0 = v.pos[1]
    run_for(m, v, cfg, 1.0)
    assert m.state == State.RETURN and v.pos[1] < y0 - 0.5


def test_geofence_return_far_from_the_map_flies_straight_back_then_rejoins(sfield):
    cfg, m, v = make(sfield, geofence="return")
    _fly_to_flow(m, v, cfg)
    v.pos[1] = 2.5                                   # 3 cells out: beyond RETURN_RADIUS_CELLS
    outs = run(m, v, cfg, lambda m, v, o: m.state == State.RETURN)
    vy = outs[-1].velocity_m_s[1]
    assert vy < 0 and math.hypot(*outs[-1].velocity_m_s) <= cfg.return_speed_m_s + 1e-9
    # within two cells of a CV it flies that CV's flow (downstream) with the inward pull
    outs = run(m, v, cfg, lambda m, v, o: o.velocity_m_s is not None and o.velocity_m_s[0] > 1.0, max_s=v.t + 3)
    assert m.state == State.RETURN and v.pos[1] < 2.0 and outs[-1].velocity_m_s[1] < 0


def test_geofence_return_near_the_map_rejoins_its_flow_downstream(sfield):
    # just past a side face the vehicle flies the nearest CV's flow plus an inward pull (the
    # simulator's rule), never back against the flow
    cfg, m, v = make(sfield, geofence="return")
    _fly_to_flow(m, v, cfg)
    v.pos[1] = 1.2                                   # 0.2 m outside the side face
    at = []
    outs = run(m, v, cfg, lambda m, v, o: m.state == State.RETURN, hook=lambda m, v, o: at.append(tuple(v.pos)))
    near = sfield.field.nearest_cv_within([at[-1]])[0]
    np.testing.assert_allclose(outs[-1].velocity_m_s, return_command(sfield.field, [at[-1]], [near])[0])
    outs += run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, max_s=v.t + 3)
    back = [o.velocity_m_s for o in outs if o.state == State.RETURN]
    assert back and all(vel[0] > 0 for vel in back) and all(vel[1] < 0 for vel in back)


def test_return_carried_past_the_outlet_ends_the_lap(sfield):
    cfg, m, v = make(sfield, geofence="return", exit_policy="loop")
    _fly_to_flow(m, v, cfg)
    v.pos[0], v.pos[1] = 2.8, 1.3                    # outside, near the outlet: the flow carries it past
    run(m, v, cfg, lambda m, v, o: m.state != State.FLOW, max_s=v.t + 1)
    assert m.state == State.RETURN
    run(m, v, cfg, lambda m, v, o: m.state != State.RETURN, max_s=v.t + 3)
    assert m.state == State.JOIN and m.reason.cause == Cause.LAP_DONE and m.laps == 1


@pytest.fixture(scope="module")
def walled(tunnel_map):
    """The tunnel with a real wall 1.2 m from the axis, just outside its CV staircase (|y| <= 1 m)."""
    return ScalarField(CommandField.from_map(tunnel_map), wall=DuctWall(np.array([0.0, 3.0]), np.array([1.2, 1.2])))


def test_a_resume_at_the_wall_flies_straight_in_before_it_flows_again(walled, sfield):
    # a hold that left the vehicle inside the map but at its wall (stock PX4 SIH drifts there on its
    # biased velocity estimate): the resume first flies it in, across the stream, until it is the
    # rejoin inset (the 0.8 m margin capped at half the 1.2 m radius: 0.6 m) inside the wall
    cfg, m, v = make(walled)
    _fly_to_flow(m, v, cfg)
    m.command("hold")
    run(m, v, cfg, lambda m, v, o: m.state == State.HOLD)
    v.pos[1], v.pos[2] = 0.9, 0.1                    # in a CV, 0.29 m from the wall
    assert walled.cv_of(*v.pos) >= 0
    m.command("resume")
    outs = run(m, v, cfg, lambda m, v, o: m.state != State.HOLD)
    assert m.state == State.RETURN and m.reason.cause == Cause.FLEET_RESUME
    vel = outs[-1].velocity_m_s
    assert vel[1] < 0 and vel[2] < 0 and abs(vel[0]) < 1e-9 and math.hypot(*vel) <= cfg.return_speed_m_s + 1e-9
    at = []
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, max_s=v.t + 3, hook=lambda m, v, o: at.append(tuple(v.pos)))
    assert m.reason.cause == Cause.BACK_IN_MAP and "clear of the wall" in m.reason
    assert math.hypot(at[-1][1], at[-1][2]) <= 0.6 < math.hypot(at[-2][1], at[-2][2])   # the position it decided on
    # without a wall in the map the CVs alone decide: the same spot flows on at once
    cfg, m, v = make(sfield)
    _fly_to_flow(m, v, cfg)
    m.command("hold")
    run(m, v, cfg, lambda m, v, o: m.state == State.HOLD)
    v.pos[1], v.pos[2] = 0.9, 0.1
    m.command("resume")
    run(m, v, cfg, lambda m, v, o: m.state != State.HOLD)
    assert m.state == State.FLOW


def test_a_resume_clear_of_the_wall_flows_at_once(walled):
    cfg, m, v = make(walled)
    _fly_to_flow(m, v, cfg)
    m.command("hold")
    run(m, v, cfg, lambda m, v, o: m.state == State.HOLD)
    v.pos[1], v.pos[2] = 0.6, 0.0                    # exactly on the inset line
    m.command("resume")
    run(m, v, cfg, lambda m, v, o: m.state != State.HOLD)
    assert m.state == State.FLOW and m.reason.cause == Cause.FLEET_RESUME


def test_a_geofence_return_does_not_end_at_the_edge_of_the_map(walled):
    # the return's hysteresis: back in a CV is not enough, it flies on until clear of the wall
    cfg, m, v = make(walled, geofence="return")
    _fly_to_flow(m, v, cfg)
    v.pos[1], v.pos[2] = 1.2, 0.0                    # 0.2 m outside the side face
    seen = []
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW and seen, max_s=v.t + 5,
        hook=lambda m, v, o: seen.append((m.state, o.cv_id, math.hypot(v.pos[1], v.pos[2]))))
    returning_inside = [r for st, cv, r in seen if st == State.RETURN and cv >= 0]
    assert returning_inside and min(returning_inside) > 0.6 - 0.2   # in the map, still returning
    assert m.reason.cause == Cause.BACK_IN_MAP


def test_a_fleet_hold_at_the_wall_keeps_a_spot_clear_of_it_and_a_geofence_hold_its_own(walled):
    # a fleet hold begun in the rejoin inset keeps the point straight in from where it began (0.6 m inset:
    # target radius 1.2 - 2 x 0.6 = 0, the axis here), so the autopilot's own hold begins clear of the wall
    cfg, m, v = make(walled)
    _fly_to_flow(m, v, cfg)
    v.pos[1], v.pos[2] = 0.9, 0.1
    m.command("hold")
    x0 = v.pos[0]
    run(m, v, cfg, lambda m, v, o: m.state == State.HOLD)
    run(m, v, cfg, lambda m, v, o: o.want_mode == "hold", max_s=v.t + cfg.hold_grace_s + 1)
    assert math.hypot(v.pos[1], v.pos[2]) < 0.6 and abs(v.pos[0] - x0) < 0.5
    # a geofence hold (policy hold) stops where it left the map, as its policy says
    cfg, m, v = make(walled, geofence="hold")
    _fly_to_flow(m, v, cfg)
    v.pos[1], v.pos[2] = 1.1, 0.0
    run(m, v, cfg, lambda m, v, o: m.state == State.HOLD)
    spot = tuple(v.pos)
    run(m, v, cfg, lambda m, v, o: o.want_mode == "hold", max_s=v.t + cfg.hold_grace_s + 1)
    assert m.hold_cause == HoldCause.GEOFENCE and distance(tuple(v.pos), spot) < 0.3


def test_a_geofence_return_beside_a_walled_map_flies_straight_in(walled):
    cfg, m, v = make(walled, geofence="return")
    _fly_to_flow(m, v, cfg)
    v.pos[1], v.pos[2] = 1.3, 0.0                    # 0.3 m outside the side face, 0.1 m beyond the wall
    outs = run(m, v, cfg, lambda m, v, o: m.state == State.RETURN)
    vel = outs[-1].velocity_m_s
    assert abs(vel[0]) < 1e-9 and vel[1] == pytest.approx(-cfg.return_speed_m_s) and abs(vel[2]) < 1e-9
    t0 = v.t
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, max_s=v.t + 3)
    assert v.t - t0 < 1.2                            # 0.7 m at 1 m/s, then the proportional tail


def test_link_loss_holds_latched_and_requests_hold_mode_when_back(sfield):
    cfg, m, v = make(sfield)
    _fly_to_flow(m, v, cfg)
    v.mute = True
    run(m, v, cfg, lambda m, v, o: m.state == State.HOLD)
    assert m.reason == "position stale"             # positions stop first
    run(m, v, cfg, lambda m, v, o: m.reason == "link lost")
    assert v.t - v.last_hb > cfg.link_timeout_s
    outs = run_for(m, v, cfg, 1.0)                  # blind: nothing streamed, not even the handover's zero
    assert v.mode == "offboard" and all(o.velocity_m_s is None and o.want_mode == "hold" for o in outs)
    v.mute = False
    outs = run(m, v, cfg, lambda m, v, o: True)
    assert outs[-1].want_mode == "hold" and m.state == State.HOLD
    m.command("resume")
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, max_s=v.t + 5)


def test_fleet_hold_resume_and_land(sfield):
    cfg, m, v = make(sfield)
    run(m, v, cfg, lambda m, v, o: m.state == State.JOIN)
    m.command("hold")
    outs = run(m, v, cfg, lambda m, v, o: True)
    assert m.state == State.HOLD and m.reason == "fleet hold"
    assert outs[-1].velocity_m_s == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)   # at its spot (KEEPING_SPOT)
    run(m, v, cfg, lambda m, v, o: o.want_mode == "hold")
    m.command("resume")
    run(m, v, cfg, lambda m, v, o: True)
    assert m.state == State.JOIN
    m.command("land")
    run(m, v, cfg, lambda m, v, o: m.state == State.DONE)
    assert states(m)[-2:] == [State.LAND, State.DONE]
    with pytest.raises(ValueError, match="fleet command"):
        m.command("dance")


def test_pilot_override_is_hands_off(sfield):
    cfg, m, v = make(sfield)
    _fly_to_flow(m, v, cfg)
    v.mode = "other"                                 # pilot flips to POSCTL / LOITER on the RC
    outs = run(m, v, cfg, lambda m, v, o: m.state == State.HOLD)
    assert m.reason.startswith("pilot override") and "hands off" in m.reason
    outs = run_for(m, v, cfg, 4.0)
    assert all(o.want_mode is None and o.velocity_m_s is None for o in outs) and v.mode == "other"
    m.command("resume")                              # a swarm-wide resume does not take the vehicle back
    outs = run_for(m, v, cfg, 2.0)
    assert m.hands_off and all(o.want_mode is None and o.velocity_m_s is None for o in outs)
    m.command(FleetOrder(MissionCommand.RESUME, addressed=True))   # one addressed to this agent does
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, max_s=v.t + 10)
    assert m.authority == Authority.COMMAND


def test_mode_taken_during_a_hold_is_respected(sfield):
    cfg, m, v = make(sfield, hold_grace_s=5.0)
    _fly_to_flow(m, v, cfg)
    m.command("hold")
    run_for(m, v, cfg, 1.0)                          # zero-velocity stage, still in offboard
    v.mode = "other"
    outs = run_for(m, v, cfg, 6.0)
    assert m.reason.startswith("pilot override") and v.mode == "other"
    assert all(o.want_mode is None for o in outs[2:])


def test_autopilot_failsafe_mode_while_landing_is_respected(sfield):
    cfg, m, v = make(sfield)
    _fly_to_flow(m, v, cfg)
    m.command("land")
    run_for(m, v, cfg, 0.5)
    v.mode = "other"                                 # e.g. the pilot takes over during the descent
    outs = run_for(m, v, cfg, 2.0)
    assert m.state == State.HOLD and "in LAND" in m.reason and outs[-1].want_mode is None


def test_arming_timeout_fails_the_mission(sfield):
    cfg, m, v = make(sfield, command_timeout_s=2.0)
    v.apply = lambda out, cfg: setattr(v, "t", v.t + DT)   # autopilot ignores everything
    run(m, v, cfg, lambda m, v, o: m.state == State.DONE)
    assert m.reason.startswith("failed") and m.reason.cause == Cause.ARM_FAILED and m.failed


def test_reasons_are_text_with_a_typed_cause_that_survives_pickling():
    r = Reason(HoldCause.PILOT_OVERRIDE, "pilot override: mode changed to other outside the agent, hands off")
    back = pickle.loads(pickle.dumps(r))
    assert back == r and back.cause == HoldCause.PILOT_OVERRIDE and isinstance(back, Reason)
    assert Reason(Cause.LANDED) == "landed and disarmed" and Reason(Cause.LANDED).cause == Cause.LANDED
    assert json.loads(json.dumps({"reason": r}))["reason"] == str(r)  # status JSON keeps the text


def test_disarm_in_flight_ends_the_mission(sfield):
    cfg, m, v = make(sfield)
    _fly_to_flow(m, v, cfg)
    v.armed = False
    run(m, v, cfg, lambda m, v, o: m.state == State.DONE, max_s=v.t + 1)
    assert "disarmed" in m.reason


def test_map_swap_during_join_replans(sfield, tunnel_map):
    from agent_testkit import tunnel_map_bytes
    from fisc_agent.map.codec import decode_map

    cfg, m, v = make(sfield)
    run(m, v, cfg, lambda m, v, o: m.state == State.JOIN)
    longer = ScalarField(CommandField.from_map(decode_map(tunnel_map_bytes(length_m=4.0, map_version=2))))
    m.set_map(longer)
    assert m.geom.x_outlet_m == pytest.approx(4.0)
    run(m, v, cfg, lambda m, v, o: m.state == State.EXIT)
    assert v.pos[0] >= 4.0


def test_restart_in_the_air_does_not_take_over(sfield):
    """An agent (re)started on an armed vehicle, even with --go, sends nothing: it is not ours."""
    cfg, m, v = make(sfield)
    v.armed, v.mode, v.pos = True, "offboard", [1.0, 0.1, 0.1]
    outs = run_for(m, v, cfg, 5.0)
    assert m.state == State.STANDBY and m.authority == Authority.NOT_OURS and m.reason.cause == Cause.NOT_OURS
    assert all(o.want_mode is None and o.want_armed is None and o.velocity_m_s is None for o in outs)
    for order in (FleetOrder(MissionCommand.GO), FleetOrder(MissionCommand.RESUME, addressed=True),
                  FleetOrder(MissionCommand.TAKEOVER)):  # no go, no resume, no swarm-wide takeover hands it over
        m.command(order)
        outs = run_for(m, v, cfg, 1.0)
        assert m.authority == Authority.NOT_OURS and all(o.velocity_m_s is None for o in outs)
    m.command(FleetOrder(MissionCommand.TAKEOVER, addressed=True))   # only an addressed takeover does
    run(m, v, cfg, lambda m, v, o: True)
    assert m.state == State.FLOW and "taking over" in m.reason and m.authority == Authority.COMMAND


class ArduCopterVehicle(SimVehicle):
    """ArduPilot Copter's GUIDED takeoff, as far as the mission can tell: a velocity target
    replaces the takeoff target (zero-velocity setpoints end the climb), and MAV_CMD_NAV_TAKEOFF
    is refused once airborne ("already flying")."""

    def __init__(self):
        super().__init__("ardupilot")
        self.takeoffs_refused = 0

    def apply(self, out, cfg):
        if not self.mute and self.mode == "offboard" and out.velocity_m_s is not None:
            self.takeoff_to = None
        if out.takeoff_alt_m is not None and self.takeoff_to is None and self.pos[2] > self.ground_z + 0.05:
            self.takeoffs_refused += 1
            out = out._replace(takeoff_alt_m=None)
        super().apply(out, cfg)


def test_ardupilot_takeoff_cut_by_a_stale_hold_finishes_with_climb_setpoints(sfield):
    cfg, m, _ = make(sfield, autopilot="ardupilot", takeoff_alt_m=2.5)
    v = ArduCopterVehicle()
    run(m, v, cfg, lambda m, v, o: m.state == State.TAKEOFF and v.pos[2] > v.ground_z + 0.4)
    v.drop_position = True                           # fix lost mid-climb: zero-velocity hold ...
    run(m, v, cfg, lambda m, v, o: m.state == State.HOLD)
    assert m.reason == "position stale"
    run_for(m, v, cfg, 0.3)
    assert v.takeoff_to is None                      # ... which ended ArduPilot's takeoff climb
    stuck_z = v.pos[2]
    assert v.ground_z + 0.2 < stuck_z < v.ground_z + 0.9 * cfg.takeoff_alt_m
    v.drop_position = False
    outs = run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, max_s=v.t + 30)
    resumed = [o for o in outs if o.state == State.TAKEOFF]
    assert resumed and all(o.takeoff_alt_m is None and o.velocity_m_s[2] > 0 for o in resumed)
    assert [t.dst for t in m.transitions[-3:]] == [State.TAKEOFF, State.JOIN, State.FLOW]
    assert m.transitions[-3].reason == "position fix back"


def test_autopilot_failsafe_during_a_stale_hold_is_hands_off(sfield):
    cfg, m, v = make(sfield)
    _fly_to_flow(m, v, cfg)
    v.drop_position = True
    run(m, v, cfg, lambda m, v, o: m.state == State.HOLD)
    assert m.reason == "position stale"
    v.mode = "hold"                                  # PX4's offboard-loss failsafe switched to HOLD ...
    v.drop_position = False                          # ... and the fix comes back in the same tick
    modes_requested = list(v.modes)
    outs = run_for(m, v, cfg, 3.0)
    assert m.state == State.HOLD and m.reason.startswith("pilot override") and "hands off" in m.reason
    assert all(o.state == State.HOLD and o.want_mode is None and o.velocity_m_s is None for o in outs)
    assert v.mode == "hold" and v.modes == modes_requested
    m.command("resume")                              # a swarm-wide resume does not take the vehicle back ...
    run_for(m, v, cfg, 1.0)
    assert m.hands_off and v.modes == modes_requested
    m.command(FleetOrder(MissionCommand.RESUME, addressed=True))   # ... a resume addressed to it does
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, max_s=v.t + 10)


def test_fleet_resume_is_refused_without_a_position_fix(sfield):
    cfg, m, v = make(sfield)
    _fly_to_flow(m, v, cfg)
    m.command("hold")
    run_for(m, v, cfg, 0.5)
    v.drop_position = True
    run(m, v, cfg, lambda m, v, o: v.t - v.last_fix > cfg.stale_timeout_s)
    m.command("resume")                              # no fix: resuming would fly blind
    outs = run_for(m, v, cfg, 0.5)
    assert m.state == State.HOLD and m.reason == "fleet hold"
    assert all(o.state == State.HOLD for o in outs)
    v.drop_position = False                          # the fix back within RESUME_WAIT_S: the resume is carried
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, max_s=v.t + 1)   # out then (test_authority.py)


def _flow_track(m, v, cfg):
    """(vehicle position, parcel) at every FLOW tick of one pass."""
    track = []

    def hook(m, v, out):
        if m.state == State.FLOW and m.tracker.parcel_m is not None:
            track.append((tuple(v.pos), m.tracker.parcel_m))

    run(m, v, cfg, lambda m, v, o: m.state in (State.EXIT, State.HOLD), hook=hook)
    return track


def test_tracking_on_an_ideal_vehicle_flies_the_field_itself(sfield):
    """A vehicle that does what it is told needs no correction: every FLOW setpoint is the map's
    command at the parcel, which stays level with the vehicle (within a CV's 0.5 m)."""
    cfg, m, v = make(sfield, lookahead_auto=False)
    outs = run(m, v, cfg, lambda m, v, o: m.state == State.EXIT)
    flow = [o for o in outs if o.state == State.FLOW]
    assert len(flow) > 20
    assert m.tracker.bias_m_s == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
    assert max(math.dist(m.tracker.integral_m_s, (0, 0, 0)), 0.0) < 0.05
    assert all(math.dist(o.velocity_m_s, sfield.command(0, 0, 0, 2, "mean", o.cv_id)) < 0.3 for o in flow[2:])


@pytest.fixture(scope="module")
def default_sfield():
    from fisc_ground.maps.build import load_shipped_default_map

    return ScalarField(CommandField.from_map(load_shipped_default_map()))


def test_tracking_holds_the_streamline_against_a_velocity_estimate_bias(default_sfield):
    """Through the 15 m default duct the vehicle really moves 0.4 m/s east of what it reports (PX4
    SIH shows this with a heading error): open loop it drifts into the wall and is held by the
    geofence; tracking crosses and stays within 0.35 m of its streamline."""
    bias, sfield = (0.0, 0.4, 0.0), default_sfield
    cfg, m, v = make(sfield, origin_ned_m=(0.0, 0.0, -10.0), **OPEN_LOOP)
    v.pos = [0.0, 0.0, -10.0]
    v.ground_z = -10.0
    v.velocity_bias = bias
    run(m, v, cfg, lambda m, v, o: m.state in (State.HOLD, State.EXIT))
    assert m.state == State.HOLD and m.reason.startswith("geofence")

    cfg, m, v = make(sfield, origin_ned_m=(0.0, 0.0, -10.0), lookahead_auto=False)
    v.pos = [0.0, 0.0, -10.0]
    v.ground_z = -10.0
    v.velocity_bias = bias
    track = _flow_track(m, v, cfg)
    assert m.state == State.EXIT and len(track) > 20
    cross = [math.hypot(p[1] - q[1], p[2] - q[2]) for p, q in track]
    assert max(cross[10:]) < 0.35
    assert m.tracker.bias_m_s[1] == pytest.approx(0.4, abs=0.05)   # the bias was learnt


def test_fixes_slower_than_the_ticks_teach_no_velocity_bias(default_sfield):
    """Fixes arrive at 1/0.15 s = 6.7 Hz while the agent ticks at 20 Hz (MAVSDK's callbacks, or a
    slow telemetry stream): a fix seen by two or three ticks is not a stop followed by a jump.  The
    bias estimate stays near zero through the duct (taken at the ticks' times it ran to its 1.5 m/s bound)."""
    cfg, m, v = make(default_sfield, origin_ned_m=(0.0, 0.0, -10.0), lookahead_auto=False)
    v.pos = [0.0, 0.0, -10.0]
    v.ground_z = -10.0
    v.fix_period_s = 0.15
    biases = []
    run(m, v, cfg, lambda m, v, o: m.state in (State.HOLD, State.EXIT),
        hook=lambda m, v, o: biases.append(math.dist(m.tracker.bias_m_s, (0, 0, 0))) if m.state == State.FLOW else None)
    assert m.state == State.EXIT and len(biases) > 100
    assert max(biases) < 0.1, max(biases)


def test_an_autopilot_clock_slower_than_the_agents_is_no_velocity_bias(default_sfield):
    """The autopilot runs at 0.7 x the agent's clock (PX4 SITL on a loaded host ran at ~0.7): per
    agent-second its position advances 0.7 x its reported velocity.  Learnt on the fixes' own
    timestamps the bias stays near zero; on the agent's clock it would be 0.3 x the speed, flown as
    an overspeed (that PX4 SITL flight crossed at up to 2.08 m/s where the map asks 1.77)."""
    def bias_through_the_duct(stamped):
        cfg, m, v = make(default_sfield, origin_ned_m=(0.0, 0.0, -10.0), lookahead_auto=False)
        v.pos = [0.0, 0.0, -10.0]
        v.ground_z = -10.0
        v.clock_rate, v.stamp_fixes = 0.7, stamped
        along = []
        run(m, v, cfg, lambda m, v, o: m.state in (State.HOLD, State.EXIT), max_s=120.0,
            hook=lambda m, v, o: along.append(m.tracker.bias_m_s[0] / max(v.vel[0], 0.3)) if m.state == State.FLOW else None)
        assert m.state == State.EXIT and len(along) > 100
        return float(np.median(along))

    assert abs(bias_through_the_duct(True)) < 0.05
    # the same vehicle without stamps (MAVSDK's callbacks): the receive times read the slow clock as a bias
    assert bias_through_the_duct(False) < -0.2


def test_join_corrects_the_velocity_estimate_bias_and_crosses_at_its_entry_point(default_sfield):
    """From the takeoff on, the vehicle moves 0.4 m/s east of what it reports.  With the learnt bias
    subtracted the join crosses the inlet within 0.1 m of its entry point; without, the proportional
    approach settles bias / gain = 0.4 m beside its staging point, never within the waypoint radius
    (PX4 SITL vehicles crossed 0.5-0.85 m off their entry points)."""
    def flight(tracking):
        cfg, m, v = make(default_sfield, origin_ned_m=(0.0, 0.0, -10.0), lookahead_auto=False, tracking=tracking)
        v.pos, v.ground_z = [-6.0, 0.0, -10.0], -10.0
        v.velocity_bias, v.bias_states = (0.0, 0.4, 0.0), (State.TAKEOFF, State.JOIN, State.FLOW)
        return cfg, m, v

    cfg, m, v = flight(TrackingConfig())
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, max_s=30.0)
    assert math.hypot(v.pos[1] - m.entry[1], v.pos[2] - m.entry[2]) < 0.1
    assert m.tracker.bias_m_s[1] == pytest.approx(0.4, abs=0.05)
    cfg, m, v = flight(TrackingConfig(bias_time_constant_s=0.0))     # no bias learnt: the old join
    run_for(m, v, cfg, 30.0)
    stage = m.nav.waypoints[-2]
    assert m.state == State.JOIN and math.hypot(v.pos[1] - stage[1], v.pos[2] - stage[2]) > 0.3


def test_a_fleet_hold_keeps_its_spot_against_the_velocity_estimate_bias(default_sfield):
    """The vehicle moves 0.35 m/s east and 0.4 m/s up of what it reports, from the take-off on (a stock
    PX4 SIH in a fleet hold drifted so, 1.2 m in 3 s, and left the duct).  A fleet hold's first stage
    keeps the spot where the hold began, the learnt bias subtracted: within 0.2 m of it to the end of
    the grace (a braking overshoot, then back); zero velocity alone drifts with the bias, as a hold
    outside ``KEEPING_SPOT`` (an agent fault's) still does."""
    bias = (0.0, 0.35, 0.4)

    def held(cause):
        cfg, m, v = make(default_sfield, origin_ned_m=(0.0, 0.0, -10.0), lookahead_auto=False)
        v.pos, v.ground_z = [-6.0, 0.0, -10.0], -10.0
        v.velocity_bias, v.bias_states = bias, (State.TAKEOFF, State.JOIN, State.FLOW, State.HOLD)
        run(m, v, cfg, lambda m, v, o: m.state == State.FLOW and v.pos[0] > 3.0, max_s=40.0)
        if cause == "fleet":
            m.command("hold")
        else:
            m.fault(v.t, "a test")
        spot, t0 = tuple(v.pos), v.t
        outs = run(m, v, cfg, lambda m, v, o: v.t - t0 >= cfg.hold_grace_s - 2 * DT)
        assert m.state == State.HOLD and all(o.want_mode == "offboard" for o in outs)
        return outs, distance(tuple(v.pos), spot), m

    outs, drift_m, m = held("fleet")
    assert m.hold_cause == HoldCause.FLEET and m.tracker.bias_m_s[2] == pytest.approx(0.4, abs=0.05)
    assert drift_m < 0.2, drift_m
    late = outs[-1].velocity_m_s      # at the spot again: the bias's opposite, so the vehicle stays
    assert late[1] == pytest.approx(-0.35, abs=0.1) and late[2] == pytest.approx(-0.4, abs=0.1)
    outs, drift_m, m = held("fault")
    assert m.hold_cause == HoldCause.AGENT_FAULT and all(o.velocity_m_s == (0.0, 0.0, 0.0) for o in outs)
    assert drift_m > 0.8, drift_m     # 0.53 m/s for ~1.9 s: 0.98 m


def test_entry_slots_stagger_agents_on_the_shared_clock():
    from fisc_agent.flight.spacing import entry_slot_open

    open_at = {i: [t / 10 for t in range(0, 240) if entry_slot_open(1000.0 + t / 10, i, 2.0, 6)] for i in range(6)}
    assert all(open_at[i] for i in range(6))
    for i in range(6):
        for j in range(i + 1, 6):  # different windows: never open at the same time, >= 1.5 s apart
            assert min(abs(a - b) for a in open_at[i] for b in open_at[j]) >= 1.5 - 1e-9
    assert all(9 <= len(open_at[i]) <= 11 for i in range(6))  # a quarter of 2 s, twice in 24 s, at 0.1 s
    assert entry_slot_open(5.0, 3, 0.0, 8)      # no stagger: always open


def test_a_staged_agent_waits_for_its_window_then_enters(sfield):
    cfg, m, v = make(sfield, entry_stagger_s=2.0, entry_slots=4, agent_id=1, lookahead_auto=False)
    wall0 = 1_000_000.0 + 2.0 * 2  # the cycle is 8 s; agent 1 may start in [2, 2.5) s of it: first open 6 s later
    entered_at = []

    def status():
        st = v.status()
        return st._replace(wall_time_s=wall0 + v.t)

    while v.t < 60.0 and m.state != State.FLOW:
        out = m.step(status())
        v.apply(out, cfg)
    assert m.state == State.FLOW
    entered_at.append(next(t.t_s for t in m.transitions if t.dst == State.FLOW))
    phase = (wall0 + entered_at[0]) % 8.0
    assert 2.0 <= phase < 5.0, phase     # crossed the inlet plane after its window opened (1.5 m from staging)


def test_staggered_agents_wait_above_their_launch_points_and_enter_the_windows_they_own(sfield):
    """Three agents launched 3 m apart, 4 s windows: each waits for its window above its own launch
    point, leaves early by its own flight to the staging point, and so crosses the inlet the same
    time after its window opens as the others do, without stopping on the way; neighbouring
    windows' entries are >= 3 s apart."""
    wall0, stagger = 1_000_000.0 * 12.0, 4.0   # a cycle (3 windows of 4 s) starts at wall0
    entered, waited_at, moved_after = {}, {}, {}
    for agent_id in range(3):
        cfg, m, v = make(sfield, agent_id=agent_id, entry_stagger_s=stagger, entry_slots=3, lookahead_auto=False)
        v.pos = [0.0, 3.0 * agent_id, -3.0]
        v.ground_z = -3.0
        track = []

        def status():
            return v.status()._replace(wall_time_s=wall0 + v.t)

        while v.t < 60.0 and m.state != State.FLOW:
            out = m.step(status())
            v.apply(out, cfg)
            track.append((v.t, m.state, tuple(v.pos), math.hypot(*v.vel)))
        assert m.state == State.FLOW
        entered[agent_id] = wall0 + next(t.t_s for t in m.transitions if t.dst == State.FLOW)
        join = [(t, p, speed) for t, st, p, speed in track if st == State.JOIN]
        first = np.array(join[0][1])
        waiting = [t for t, p, speed in join if np.linalg.norm(np.array(p) - first) < 0.3]
        waited_at[agent_id] = waiting[-1] - waiting[0]
        moved_after[agent_id] = min(speed for t, p, speed in join if t > waiting[-1] + 1.0 and p[0] < -0.5)
        assert abs(first[1] - 3.0 * agent_id) < 0.1      # it waited above its own launch point
    assert max(waited_at.values()) > 2.0, waited_at      # someone had to wait for a window
    assert min(moved_after.values()) > 0.25, moved_after  # then flew to the inlet without stopping (crawl 0.3)
    # the time from its window's opening to the crossing is the same for all (each left early by its own
    # flight), up to the window's open part: an agent at its wait point after its time to leave (here
    # agent 2, 3 m farther, with the join's lag allowance) leaves while the window is still open
    delay = [(entered[i] - wall0 - stagger * i) % (3 * stagger) for i in range(3)]
    assert max(delay) - min(delay) <= ENTRY_OPEN_FRACTION * stagger, delay
    order = sorted(entered.values())
    assert min(b - a for a, b in zip(order, order[1:])) >= 0.75 * stagger - 0.5, entered


def test_staggered_laps_wait_for_their_window_above_their_launch_points(sfield):
    """Exit ``loop``, 8 windows of 4 s, launch points 3 m apart: a lap's return flies back over the
    tunnel and waits for its window where its first join waited, above its own launch point, never at
    its staging point (those lie decimetres apart), and crosses the inlet the same time after its
    window opens as on its first pass."""
    geom = MapGeometry.from_field(sfield.field)
    wall0, stagger, slots = 1_000_000.0 * 32.0, 4.0, 8
    waited_s = {}
    for agent_id in range(3):
        cfg, m, v = make(sfield, agent_id=agent_id, entry_stagger_s=stagger, entry_slots=slots, exit_policy="loop",
                         laps=2, lookahead_auto=False)
        v.pos = [0.0, 3.0 * agent_id, -3.0]
        v.ground_z = -3.0
        above_launch = np.array([0.0, 3.0 * agent_id, -3.0 + cfg.takeoff_alt_m])
        track = []
        while v.t < 300.0 and m.laps < 2:
            out = m.step(v.status()._replace(wall_time_s=wall0 + v.t))
            v.apply(out, cfg)
            track.append((v.t, m.state, m.laps, np.array(v.pos), math.hypot(*v.vel)))
        assert m.laps == 2, m.transitions
        lap_join = [(t, p, speed) for t, st, laps, p, speed in track if st == State.JOIN and laps == 1]
        # the waits: stretches of >= 1 s at (almost) no speed
        waits, run_ = [], []
        for t, p, speed in lap_join + [(np.inf, None, np.inf)]:
            if speed < 0.05:
                run_.append((t, p))
                continue
            if run_ and run_[-1][0] - run_[0][0] >= 1.0:
                waits.append(run_)
            run_ = []
        # it waited only above its launch point: never at its staging point, never past the outlet
        assert all(np.linalg.norm(p - above_launch) < cfg.waypoint_radius_m + 0.1 for w in waits for _, p in w), \
            (above_launch, [w[0] for w in waits])
        waited_s[agent_id] = sum(w[-1][0] - w[0][0] for w in waits)
        # on the way back, until it waited, it flew over the tunnel's keep-out box, and it came down
        # only above its own launch point (the others wait above theirs, 3 m apart)
        arrived = next(t for t, p, speed in lap_join if np.linalg.norm(p - above_launch) < cfg.waypoint_radius_m + 0.1)
        back = [p for t, p, speed in lap_join if t < arrived and geom.x_inlet_m + 0.5 <= p[0] <= geom.x_outlet_m]
        assert back and min(p[2] for p in back) > geom.hi_m[2] + cfg.keepout_margin_m - 0.5, min(p[2] for p in back)
        for other in range(3):
            if other != agent_id:
                their_wait = np.array([0.0, 3.0 * other, -3.0 + cfg.takeoff_alt_m])
                assert min(np.linalg.norm(p - their_wait) for t, p, speed in lap_join if t < arrived) > 2.5
        # it crossed the inlet the same time after its window opened as on its first pass (both
        # flights to the staging point were led by their own approach time), up to the window's open
        # part (a first join that reached its wait point after its time to leave)
        first, second = [(wall0 + tr.t_s - stagger * agent_id) % (slots * stagger)
                         for tr in m.transitions if tr.dst == State.FLOW][:2]
        assert abs(second - first) <= ENTRY_OPEN_FRACTION * stagger, (first, second)
    assert max(waited_s.values()) > 1.0, waited_s                  # someone had to wait for a window


def test_a_failed_identification_is_tried_once_and_logged_once(sfield, caplog):
    """A vehicle that gives too little excitation (a hover-like join) is not identified; the agent
    says so once and flies on with the given look-ahead (no warning per tick of the final leg)."""
    cfg, m, v = make(sfield)
    m.nav.recorder.max_samples = 0          # nothing recorded: the fit must refuse
    with caplog.at_level("WARNING", logger="fisc_agent.flight.mission"):
        run(m, v, cfg, lambda m, v, o: m.state == State.FLOW)
    assert m.response is None
    assert sum("not identified" in r.getMessage() for r in caplog.records) == 1


def test_by_default_agents_enter_in_their_windows_of_the_maps_admission_budget():
    """``entry_stagger_s`` None (``--entry-stagger auto``, the default): the shipped map's admission
    period and budget set the windows (``spacing.entry_schedule``); agents 2 and 3 cross the inlet one
    period apart, each when its timed final leg aims: the start of the window it owns plus the leg
    from its staging point at the crawl; ``0`` enters at once."""
    from fisc_agent.flight.spacing import EntrySchedule, ScheduleSource
    from fisc_agent.map.separation import map_separation
    from fisc_ground.maps.build import load_shipped_default_map

    cmap = load_shipped_default_map()
    sep = map_separation(cmap.body)
    sf = ScalarField(CommandField.from_map(cmap), separation=sep)
    period, slots = sep.admission_period_s, sep.max_in_tunnel
    cycle = period * slots
    wall0 = math.ceil(1e6 / cycle) * cycle            # a cycle starts at wall0
    phases = {}
    for agent_id in (2, 3):
        cfg, m, v = make(sf, agent_id=agent_id, lookahead_auto=False)
        assert cfg.entry_stagger_s is None and cfg.entry_slots is None
        assert m.nav.schedule == EntrySchedule(period, slots, ScheduleSource.MAP)
        while v.t < 120.0 and m.state != State.FLOW:
            v.apply(m.step(v.status()._replace(wall_time_s=wall0 + v.t)), cfg)
        assert m.state == State.FLOW
        t_in = next(t.t_s for t in m.transitions if t.dst == State.FLOW)
        leg_s = distance(m.nav.waypoints[-2], m.nav.waypoints[-1]) / m.nav._crawl_m_s()
        phases[agent_id] = math.fmod(wall0 + t_in, cycle) - (agent_id * period + leg_s)
    for agent_id, late_s in phases.items():   # its aim: at most a lag late, never early
        assert -0.3 <= late_s <= 1.0, (agent_id, late_s, period)
    assert phases[3] - phases[2] == pytest.approx(0.0, abs=0.5)   # one period apart
    cfg, m, v = make(sf, agent_id=2, lookahead_auto=False, entry_stagger_s=0.0)
    assert m.nav.schedule.stagger_s == 0.0 and m.nav.schedule.source is ScheduleSource.GIVEN


def _held_and_moved(sfield, dy_m):
    """A vehicle flowing on the tunnel's axis, held by the fleet, then moved ``dy_m`` across the stream (the
    autopilot's own hold drifting), still in a CV: (cfg, mission, vehicle, the parcel before the hold)."""
    cfg, m, v = make(sfield)
    _fly_to_flow(m, v, cfg)
    before = m.tracker.parcel_m
    m.command("hold")
    run(m, v, cfg, lambda m, v, o: o.want_mode == "hold", max_s=v.t + cfg.hold_grace_s + 1)
    v.pos[1] += dy_m
    assert sfield.cv_of(*v.pos) >= 0
    return cfg, m, v, before


def test_a_fleet_resume_flies_back_onto_the_streamline_it_held_on(sfield):
    cfg, m, v, before = _held_and_moved(sfield, 0.4)
    integral = m.tracker.integral_m_s
    m.command("resume")
    outs = run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, max_s=v.t + 1)
    assert m.reason.cause == Cause.FLEET_RESUME
    assert m.tracker.parcel_m[1:] == pytest.approx(before[1:], abs=0.01)       # the streamline, not the drift
    assert outs[-1].velocity_m_s[1] < -0.4 * cfg.tracking.gain_1_s + 0.05     # pulled back across the stream
    assert abs(m.tracker.integral_m_s[1] - integral[1]) < 0.05                # the hold's time not integrated
    off = []
    run(m, v, cfg, lambda m, v, o: m.state != State.FLOW, max_s=v.t + 5,
        hook=lambda m, v, o: off.append(v.pos[1] - before[1]))
    assert min(off) < 0.1                            # most of the way back before the (short) tunnel's outlet


def test_the_tracking_integrates_nothing_until_the_autopilot_flies_the_setpoints_again(sfield):
    # PX4 took 2.7 s to leave its hold mode after a resume (tests/faults, 2026-12-06): the cross-stream
    # offset meanwhile wound the integral up, and the vehicle then overshot its streamline by 0.75 m
    cfg, m, v, before = _held_and_moved(sfield, 0.4)
    integral = m.tracker.integral_m_s
    m.command("resume")
    assert v.mode == "hold"
    for _ in range(40):                              # 2 s still in the autopilot's hold mode, drifting on
        out = step(m, v.status())
        v.t += DT
        v.pos[1] += 0.002
    assert m.state == State.FLOW and m.authority == Authority.COMMAND and out.want_mode == "offboard"
    assert m.tracker.integral_m_s == integral
    run_for(m, v, cfg, 2 * DT)                       # in offboard: it integrates again
    assert m.tracker.integral_m_s[1] < integral[1]


def test_a_takeover_and_a_new_pass_start_a_new_streamline(sfield):
    cfg, m, v, before = _held_and_moved(sfield, 0.4)
    v.mode = "other"                                 # a pilot takes the vehicle during the hold ...
    run(m, v, cfg, lambda m, v, o: m.hands_off, max_s=v.t + 2)
    m.command(FleetOrder(MissionCommand.RESUME, addressed=True))   # ... and gives it back where it is
    run(m, v, cfg, lambda m, v, o: m.state == State.FLOW, max_s=v.t + 2)
    assert m.reason.cause == Cause.TAKING_OVER
    assert m.tracker.parcel_m[1] == pytest.approx(v.pos[1], abs=0.05) and abs(m.tracker.parcel_m[1] - before[1]) > 0.3
    cfg, m, v = make(sfield, exit_policy="loop")
    _fly_to_flow(m, v, cfg)
    run(m, v, cfg, lambda m, v, o: m.state == State.JOIN)
    assert m.tracker.parcel_m is None                # the pass is over: the next one starts its own
