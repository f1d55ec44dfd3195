"""The mission state machine (pure: no I/O, time comes in with each status).

::

    WAIT_POSITION -> STANDBY (no go / not ours) -> ARM -> TAKEOFF -> JOIN -> FLOW -> EXIT -> HOLD / LAND / JOIN
                                                                      ^        |
                                                                      +-- RETURN
    any flying state -> HOLD (failsafe or fleet "hold") -> previous state (auto or "resume")
    any armed state  -> LAND (fleet "land", low battery, take-off timeout);  disarmed in flight -> DONE

Who is in charge is the authority model of ``fisc_agent.flight.authority`` (docs/deployment.md, "Authority"): the
agent arms only after a go, never takes over a vehicle armed by someone else (unless a takeover addressed to it says
so), and a mode change it did not ask for (pilot, ground station, autopilot failsafe) puts it hands-off, in every
state, until a command addressed to it.

Each ``step(status)`` returns a ``MissionOutput``: the map-frame velocity to stream (None: do not stream), the
autopilot mode and arming state wanted (reconciled by ``adapters.Commander``), and, for ArduPilot, the takeoff height.
Velocities are *unclamped*; the runner clamps every setpoint.  Every transition is logged and kept in ``transitions``.

Holds: a first stage in offboard/guided for ``hold_grace_s`` (keeping a spot, ``Navigator.hold_spot``, or
zero velocity), then the autopilot's hold/loiter mode is requested.  A hold caused by a stale position or
a position jump resumes by itself once the fix is good again (a stale one only before that escalation);
every other hold (escalated, link lost, geofence, exit, fleet, pilot override) waits for a fleet ``resume``.
A resume and the geofence's RETURN end clear of the map's wall (``Navigator.rejoin_target``).
"""

from __future__ import annotations

import logging

from fisc_agent.config import AgentConfig, ExitPolicy
from fisc_agent.flight.authority import AuthorityCause, ModeWatch
from fisc_agent.flight.control import ZERO, ScalarField, Vec, goto_velocity
from fisc_agent.flight.failsafe import GeofenceVerdict, Handover, PositionHealth, geofence, link_ok, position_health
from fisc_agent.flight.fleet_orders import FleetOrders
from fisc_agent.flight.mission_types import (AUTO_RESUMING, BACK_TO_STREAMLINE, FLYING, HOLD_KEEP_SPEED_M_S,
                                             JUMP_HOLD_GRACE_S, Authority, Cause, FleetOrder, HoldCause, HoldOutput,
                                             MissionCommand, MissionOutput, Reason, State, Transition, VehicleStatus)
from fisc_agent.flight.navigation import Navigator
from fisc_agent.flight.readiness import arming_blockers, battery_low
from fisc_agent.flight.state_file import AgentState
from fisc_agent.mavlink.adapters import ModeClass
from fisc_agent.flight.health import LandedState

log = logging.getLogger(__name__)


AIRBORNE_ABOVE_HOME_M = 0.2
"""Height above home from which a vehicle counts as airborne (an interrupted takeoff then
finishes with climb setpoints: ArduPilot refuses a takeoff command once flying)."""


class Mission(FleetOrders):
    """One vehicle's mission.  Feed ``step`` a ``VehicleStatus`` at the control rate."""

    def __init__(self, cfg: AgentConfig, sfield: ScalarField | None = None, restored: AgentState | None = None) -> None:
        self.cfg = cfg
        self.state = State.WAIT_POSITION
        self.reason = Reason(Cause.START)
        self.transitions: list[Transition] = []
        self.laps = 0
        self.authority = Authority.WAITING
        self.authority_cause = AuthorityCause.START
        self._go_given = cfg.go
        self._modes = ModeWatch()
        self._pending: list[FleetOrder] = []
        self._t_state = 0.0
        self._home: Vec | None = None
        self._climb_by_velocity = False
        self._wait_where_planned = False
        self._restored_fleet_hold = False
        # hold bookkeeping
        self._resume_state = State.WAIT_POSITION
        self._hold_latched = False
        self._hold_escalated = False
        self._handover = Handover()
        self._hold_armed = False
        self._hold_spot: Vec | None = None
        self.nav = Navigator(cfg)
        self._last_pos: Vec | None = None
        if restored is not None:
            self.restore(restored)
        if sfield is not None:
            self.set_map(sfield)

    # ---- views of the navigator (fisc_agent.flight.navigation) ----------------------------
    sfield = property(lambda self: self.nav.sfield, doc="The map's single-agent field in use (None before a map).")
    geom = property(lambda self: self.nav.geom, doc="The map's geometry (inlet disc, outlet plane, bounding box).")
    entry = property(lambda self: self.nav.entry, doc="This agent's entry point in the inlet disc (map frame).")
    tracker = property(lambda self: self.nav.tracker, doc="The streamline tracker.")
    response = property(lambda self: self.nav.response, doc="The identified velocity response (None until then).")

    # ---- inputs from outside -----------------------------------------------------------
    def restore(self, saved: AgentState) -> None:
        """Start from what a previous process of this agent saved (``fisc_agent.flight.state_file``)."""
        self.laps = saved.laps
        self._restored_fleet_hold = saved.fleet_hold
        if saved.hands_off:
            self._set_authority(Authority.HANDS_OFF, AuthorityCause.RESTORED_HANDS_OFF)

    def saved_state(self) -> AgentState:
        """What a restarted process must not forget (without the command floors, which the runner adds)."""
        return AgentState(hands_off=self.hands_off, fleet_hold=self.fleet_held(), laps=self.laps)

    def fleet_held(self) -> bool:
        """A fleet hold is in force (in the air, on the ground, or restored from the state file and not yet lifted)."""
        cause = self.hold_cause
        return cause in (HoldCause.FLEET, HoldCause.FLEET_ON_GROUND) or (
            self._restored_fleet_hold and self.state in (State.WAIT_POSITION, State.STANDBY))

    def set_map(self, sfield: ScalarField) -> None:
        """Use a new map from the next step (plans depending on the map are redone)."""
        self.nav.set_map(sfield)
        if self._last_pos is not None and self.state == State.JOIN:
            self._plan_join(self._last_pos)
        if self._last_pos is not None and self.state == State.RETURN:
            self.nav.plan_return(self._last_pos)

    def observe_response(self, t: float, sp_m_s: Vec, vel_m_s: Vec) -> None:
        """A streamed setpoint and the measured velocity: identification (TAKEOFF, JOIN), the gain (FLOW)."""
        if self.state in (State.TAKEOFF, State.JOIN):
            self.nav.record_response(t, sp_m_s, vel_m_s)
        elif self.state == State.FLOW:
            self.nav.adapt(t, sp_m_s, vel_m_s)

    def command(self, order: FleetOrder | MissionCommand | str) -> None:
        """Queue a fleet order (a bare command or name is a swarm-wide one); applied at the next step."""
        if not isinstance(order, FleetOrder):
            order = FleetOrder(MissionCommand.parse(order))
        self._pending.append(order)

    # ---- transitions ---------------------------------------------------------------------
    @property
    def hands_off(self) -> bool:
        """Someone else (pilot, ground station, autopilot failsafe) took the vehicle: no modes, no
        setpoints until a command addressed to this agent."""
        return self.authority == Authority.HANDS_OFF

    @property
    def hold_cause(self) -> HoldCause | None:
        """Why the mission holds; None outside HOLD."""
        cause = self.reason.cause
        return cause if self.state == State.HOLD and isinstance(cause, HoldCause) else None

    @property
    def failed(self) -> bool:
        """The mission ended without flying (could not arm in offboard/guided)."""
        return self.state == State.DONE and self.reason.cause == Cause.ARM_FAILED

    def _set_authority(self, authority: Authority, cause: AuthorityCause) -> None:
        if authority == self.authority and cause == self.authority_cause:
            return
        log.info("authority %s -> %s (%s)", self.authority.value, authority.value, cause.value)
        self.authority, self.authority_cause = authority, cause
        if authority != Authority.COMMAND:
            self._modes.forget()

    def _go(self, t: float, dst: State, reason: Reason) -> None:
        if dst == self.state and reason == self.reason:
            return
        self.transitions.append(Transition(t, self.state, dst, reason))
        log.info("mission %s -> %s (%s)", self.state.value, dst.value, reason)
        if dst == State.FLOW and self.state != State.FLOW:
            self.nav.enter_flow(t, self._last_pos, back_to_streamline=reason.cause in BACK_TO_STREAMLINE)
        elif self.state == State.FLOW and dst in (State.JOIN, State.EXIT):
            self.nav.tracker.clear()  # the pass is over: its streamline ends at the outlet
        if dst == State.DONE and self.authority in (Authority.COMMAND, Authority.HANDS_OFF):
            self._set_authority(Authority.RELEASED, AuthorityCause.FLIGHT_OVER)
        self.state, self.reason, self._t_state = dst, reason, t
        self._handover.reset()

    def _hold(self, t: float, reason: Reason, latched: bool, armed: bool) -> None:
        self._hold_latched = (self._hold_latched and self.state == State.HOLD) or latched
        if self.state != State.HOLD:
            self._resume_state, self._hold_escalated = self.state, False
            self._hold_spot = self.nav.hold_spot(self._last_pos, reason.cause)
        self._hold_armed = armed
        self._go(t, State.HOLD, reason)

    def _hands_off_now(self, t: float, mode: ModeClass, armed: bool) -> None:
        """A mode the agent did not ask for: hands off for the rest of the flight."""
        where = self.state.value
        self._set_authority(Authority.HANDS_OFF, AuthorityCause.MODE_CHANGED)
        log.warning("mode changed to %s outside the agent (in %s): hands off, no mode request and no setpoint "
                    "until a command addressed to this agent", mode, where)
        self._hold(t, Reason(HoldCause.PILOT_OVERRIDE, f"pilot override: mode changed to {mode} in {where}, hands off"),
                   latched=True, armed=armed)
        self._hold_escalated = True

    def _plan_join(self, pos: Vec) -> None:
        self.nav.plan_join(pos, self._home, self._wait_where_planned)

    def _enter(self, t: float, dst: State, reason: Reason, pos: Vec | None) -> None:
        if dst == State.JOIN and pos is not None:
            self._wait_where_planned = self.state not in (State.FLOW, State.RETURN)  # not a lap's return
            self._plan_join(pos)
        elif dst == State.RETURN and pos is not None:
            self.nav.plan_return(pos)
        elif dst == State.EXIT and pos is not None and self.geom is not None:
            floor = None if self._home is None else self._home[2] + self.cfg.takeoff_alt_m  # never below take-off height
            self.nav.plan_exit(pos, floor)
        elif dst == State.TAKEOFF:  # resuming an interrupted takeoff (a hold cuts ArduPilot's climb short)
            self._climb_by_velocity = (pos is not None and self._home is not None
                                       and pos[2] > self._home[2] + AIRBORNE_ABOVE_HOME_M)
        self._go(t, dst, reason)

    # ---- the step ------------------------------------------------------------------------
    def step(self, s: VehicleStatus) -> MissionOutput:
        """Advance the mission by one tick on the vehicle status ``s``: the state, the setpoint and any request."""
        t, cfg, nav = s.t_s, self.cfg, self.nav
        pos = s.pos_m
        if pos is not None:
            self._last_pos = pos
        cv = self.sfield.cv_of(*pos) if (pos is not None and self.sfield is not None) else -1
        ph = position_health(s.position_age_s, cfg.stale_timeout_s, cfg.hold_grace_s)
        lk = link_ok(s.heartbeat_age_s, cfg.link_timeout_s)
        foreign = self._modes.observe(t, s.mode) if lk else None
        seen = s.mode if lk else ModeClass.UNKNOWN  # the mode as last heard, not while the link is lost

        for order in self._pending:
            self._fleet(t, order, s, pos, ph)
        self._pending.clear()
        self._retry_resume(t, pos, ph, s.armed)

        # -- who is in charge ------------------------------------------------------------------
        landed = not s.armed and (self.state in FLYING or self.state in (State.LAND, State.HOLD))
        if foreign is not None and self.authority == Authority.COMMAND and self.state != State.DONE and not landed:
            # (a mode change that comes with the disarm ends the flight, below: PX4 reports OFFBOARD again
            # on the HEARTBEAT that says it disarmed after its landing)
            self._hands_off_now(t, foreign, s.armed or self._hold_armed)
        if pos is not None and s.vel_m_s is not None and s.position_age_s <= cfg.stale_timeout_s and s.integrity_ok:
            # at the fix's own time, the autopilot's where it gives one: the ticks and the autopilot's
            # messages run on different clocks (a fix seen by two ticks would read as a stop and a
            # jump), and an autopilot whose clock runs slow against ours (PX4 SITL on a loaded host
            # ran at ~0.75 x real time) would read as a velocity bias of a quarter of the speed
            fix_t = s.fix_t_s if s.fix_t_s is not None else t - s.position_age_s
            nav.tracker.observe(fix_t, pos, s.vel_m_s, s.gnss_vel_m_s)
        # -- failsafes in the air ------------------------------------------------------------
        if self.state in FLYING or self.state == State.HOLD:
            if not s.armed and (self.state in FLYING or self._hold_armed) and lk:
                self._go(t, State.DONE, Reason(Cause.DISARMED_IN_FLIGHT))
            elif self.hands_off or self.state == State.HOLD and not self._hold_armed:
                pass  # not ours to fly: no failsafe of ours either
            elif not lk:
                if self.hold_cause != HoldCause.LINK_LOST:
                    log.warning("link lost: no autopilot HEARTBEAT for %.1f s; the autopilot's offboard-loss "
                                "failsafe is in charge", s.heartbeat_age_s)
                    self._hold(t, Reason(HoldCause.LINK_LOST), latched=True, armed=s.armed or self._hold_armed)
                    self._hold_escalated = True
            elif ph != PositionHealth.OK:
                if self.state != State.HOLD:
                    self._hold(t, Reason(HoldCause.POSITION_STALE), latched=False, armed=s.armed)
                # escalate only while the autopilot is heard: blind, a hold-mode request could land on
                # a failsafe's Land (the link-lost hold follows at --link-timeout)
                if ph == PositionHealth.LOST and not self._hold_escalated and s.heartbeat_age_s <= cfg.stale_timeout_s:
                    self._hold_escalated = True
                    self._hold_latched = True
                    log.warning("position lost for %.1f s: requesting the autopilot's hold mode", s.position_age_s)
            elif not s.integrity_ok:
                if self.state != State.HOLD:
                    log.warning("position integrity: %s; holding until the track is consistent again",
                                s.integrity_reason or "estimator reset")
                    nav.tracker.clear()
                    self._hold(t, Reason(HoldCause.POSITION_JUMP, f"position jump: {s.integrity_reason or 'reset'}"),
                               latched=False, armed=s.armed)
            elif self.hold_cause in AUTO_RESUMING and not self._hold_latched:
                self._enter(t, self._resume_state, Reason(Cause.POSITION_BACK), pos)

        st = self.state
        vel: Vec | None = None
        want_mode: ModeClass | None = None
        want_armed: bool | None = None
        takeoff: float | None = None
        by_command = s.autopilot == "ardupilot"

        if st == State.WAIT_POSITION:
            if lk and s.autopilot and ph == PositionHealth.OK and self.sfield is not None and pos is not None:
                if self._restored_fleet_hold and not s.armed:
                    self._hold(t, Reason(HoldCause.FLEET_ON_GROUND, "fleet hold (restored from the state file)"),
                               latched=True, armed=False)
                    self._resume_state = State.STANDBY
                else:
                    self._standby(t, s, pos)
        elif self.state == State.STANDBY:
            self._standby(t, s, pos)
        st = self.state
        if st == State.ARM:
            vel = None if by_command else ZERO
            want_mode, want_armed = ModeClass.OFFBOARD, True
            if s.armed and s.mode == ModeClass.OFFBOARD:
                self._climb_by_velocity = False
                self._go(t, State.TAKEOFF, Reason(Cause.ARMED))
            elif t - self._t_state > cfg.command_timeout_s:
                self._go(t, State.DONE, Reason(Cause.ARM_FAILED,
                                               f"{Cause.ARM_FAILED.value} after {cfg.command_timeout_s:.0f} s"))
        elif st == State.TAKEOFF:
            want_mode, want_armed = ModeClass.OFFBOARD, True
            home = self._home if self._home is not None else pos
            target_z = home[2] + cfg.takeoff_alt_m
            if by_command and not self._climb_by_velocity:
                takeoff = cfg.takeoff_alt_m
                done = pos[2] >= home[2] + 0.9 * cfg.takeoff_alt_m
            else:
                vx, vy, _ = goto_velocity(pos, home, cfg.join_speed_m_s)
                vel = (vx, vy, min(cfg.climb_speed_m_s, max(0.2, 1.5 * (target_z - pos[2]))))
                done = pos[2] >= target_z - 0.1
            done = done and s.health.landed not in (LandedState.ON_GROUND, LandedState.LANDING)
            if done:
                self._enter(t, State.JOIN, Reason(Cause.TAKEOFF_DONE,
                                                  f"takeoff height {cfg.takeoff_alt_m:.1f} m reached"), pos)
            elif t - self._t_state > cfg.takeoff_timeout_s:
                self._go(t, State.LAND, Reason(Cause.TAKEOFF_TIMEOUT, f"take-off not done after "
                                                                      f"{cfg.takeoff_timeout_s:.0f} s: landing"))
                st = State.LAND
        elif st == State.JOIN:
            want_mode = ModeClass.OFFBOARD
            if battery_low(s.health, cfg.min_battery_pct):
                self._go(t, State.LAND, Reason(Cause.LOW_BATTERY, f"battery {s.health.battery_pct:.0f} % below "
                                                                  f"{cfg.min_battery_pct:.0f} %: no new pass, landing"))
                st = State.LAND
            else:
                vel = nav.join_step(pos, cv, s.wall_time_s, s.vel_m_s)
                if vel is None:
                    self._go(t, State.FLOW, Reason(Cause.ENTERED_MAP, f"entered the map at CV {cv}"))
                    st = State.FLOW
        elif st == State.RETURN:
            want_mode = ModeClass.OFFBOARD
            if cv >= 0 and nav.rejoin_target(pos) is None:  # in the map and clear of its wall
                self._go(t, State.FLOW, Reason(Cause.BACK_IN_MAP, f"back in the map at CV {cv}, clear of the wall"))
                st = State.FLOW
            elif pos[0] >= self.geom.x_outlet_m and cv < 0:  # carried past the outlet while rejoining: lap done
                vel = self._passed_outlet(t, pos, s)
            else:
                vel = nav.return_velocity(pos)
        elif st == State.EXIT:
            want_mode = ModeClass.OFFBOARD
            vel = nav.exit_velocity(pos)
            if nav.exit_arrived(pos, s.vel_m_s):
                low = battery_low(s.health, cfg.min_battery_pct)  # then the low-battery action, not the exit policy
                if (cfg.low_battery_action if low else cfg.exit_policy) is ExitPolicy.LAND:
                    self._go(t, State.LAND, Reason(Cause.EXIT_LAND))
                    st = State.LAND
                else:
                    self._hold(t, Reason(HoldCause.EXIT), latched=True, armed=s.armed)
                    self._hold_escalated = True
                    st = State.HOLD
        if st == State.FLOW:
            want_mode = ModeClass.OFFBOARD
            verdict = geofence(cv, pos[0], self.geom.x_outlet_m, cfg.geofence)
            if verdict == GeofenceVerdict.INSIDE:
                vel = nav.flow_velocity(t, pos, s.vel_m_s, cv, flown=seen == ModeClass.OFFBOARD)
            elif verdict == GeofenceVerdict.EXIT:
                vel = self._passed_outlet(t, pos, s)
            elif verdict == GeofenceVerdict.RETURN:
                self._enter(t, State.RETURN, Reason(Cause.GEOFENCE_RETURN), pos)
                vel = nav.return_velocity(pos)
            else:
                self._hold(t, Reason(HoldCause.GEOFENCE), latched=True, armed=s.armed)
                vel = None
        if self.state == State.HOLD:
            fresh = pos if ph == PositionHealth.OK and s.integrity_ok else None
            heard = s.heartbeat_age_s <= cfg.stale_timeout_s
            vel, want_mode, want_armed, takeoff = self._hold_output(t, heard, fresh, seen, s.armed)
        elif self.state == State.LAND:
            vel, want_mode = self._handover.velocity(t, seen), ModeClass.LAND
            if not s.armed:
                self._go(t, State.DONE, Reason(Cause.LANDED))
        if self.state in (State.DONE, State.STANDBY, State.WAIT_POSITION) or self.authority != Authority.COMMAND:
            vel, want_mode, want_armed, takeoff = None, None, None, None
        self._modes.want(t, want_mode)
        return MissionOutput(self.state, vel, want_mode, want_armed, takeoff, cv, self.reason)

    def fault(self, t: float, what: str) -> MissionOutput:
        """A tick of the agent failed (``what``): hold (latched; a resume flies on), output the hold."""
        if self.state in FLYING or (self.state == State.HOLD and self._hold_armed):
            self._hold(t, Reason(HoldCause.AGENT_FAULT, f"agent fault: {what}"), latched=True, armed=True)
        vel, mode, armed, takeoff = self._hold_output(t) if self.state == State.HOLD else (None, None, None, None)
        return MissionOutput(self.state, vel, mode, armed, takeoff, -1, self.reason)

    def _standby(self, t: float, s: VehicleStatus, pos: Vec | None) -> None:
        """Not in command: watch who has the vehicle, and arm on a go when it is ready."""
        if self.authority == Authority.HANDS_OFF:
            return
        if s.armed:
            if self.authority != Authority.NOT_OURS:
                if self._go_given:
                    log.warning("the go is withdrawn: the vehicle was armed by someone else")
                self._go_given = False
                self._set_authority(Authority.NOT_OURS, AuthorityCause.ARMED_BY_OTHER)
                self._go(t, State.STANDBY, Reason(Cause.NOT_OURS))
            return
        if self.authority == Authority.NOT_OURS:
            self._set_authority(Authority.WAITING, AuthorityCause.DISARMED)
        if not self._go_given:
            self._go(t, State.STANDBY, Reason(Cause.WAITING_GO))
            return
        blockers = arming_blockers(s.health, self.cfg, pos, self.geom)
        if blockers:
            self._go(t, State.STANDBY, Reason(Cause.NOT_READY, "not arming: " + "; ".join(blockers)))
            return
        self._home = pos
        self._set_authority(Authority.COMMAND, AuthorityCause.ARMING)
        self.laps = 0
        self._go(t, State.ARM, Reason(Cause.AUTOPILOT_FOUND, f"go; position and {s.autopilot} heartbeat received"))

    def _passed_outlet(self, t: float, pos: Vec, s: VehicleStatus) -> Vec:
        """A lap is done: back to the inlet (exit policy ``loop``, laps left, battery above the minimum)
        or on to the exit."""
        cfg = self.cfg
        self.laps += 1
        low = battery_low(s.health, cfg.min_battery_pct)
        if cfg.exit_policy is ExitPolicy.LOOP and not low and (cfg.laps == 0 or self.laps < cfg.laps):
            self._enter(t, State.JOIN, Reason(Cause.LAP_DONE, f"lap {self.laps} done: back to the inlet"), pos)
        elif low:
            self._enter(t, State.EXIT, Reason(Cause.LOW_BATTERY, f"battery {s.health.battery_pct:.0f} % below "
                                                                 f"{cfg.min_battery_pct:.0f} % after lap {self.laps}: "
                                                                 f"to the exit, then {cfg.low_battery_action.value}"), pos)
        else:
            self._enter(t, State.EXIT, Reason(Cause.PASSED_OUTLET, f"passed the outlet (lap {self.laps})"), pos)
        if self.state == State.JOIN:
            return self.nav.goto(pos, self.nav.waypoints[0], cfg.join_speed_m_s)
        return self.nav.exit_velocity(pos)

    def _hold_output(self, t: float, heard: bool = True, pos: Vec | None = None, mode=ModeClass.UNKNOWN,
                     armed: bool = False) -> HoldOutput:
        """The hold's output: offboard/guided for ``hold_grace_s`` (from a fresh ``pos`` back to the hold's spot,
        ``Navigator.hold_spot``; else zero velocity), then the autopilot's hold mode (``Handover`` in the vehicle's
        ``mode``), not while the autopilot is unheard (blind, it could land on a failsafe's Land); on the ground,
        ``FleetOrders.ground_hold_output``."""
        on_ground = self.ground_hold_output(t, armed)
        if on_ground is not None:
            return on_ground
        if self.hands_off or not self._hold_armed:
            return None, None, None, None
        jump = self.hold_cause == HoldCause.POSITION_JUMP  # an estimator reset ends by itself: no escalation before
        grace = max(self.cfg.hold_grace_s, JUMP_HOLD_GRACE_S) if jump else self.cfg.hold_grace_s
        if not self._hold_escalated and heard and t - self._t_state >= grace:
            self._hold_escalated = True
            # a position jump ends when the track is consistent again, however long the estimator takes
            # (a real EKF3 GPS glitch: 15 s); every other escalated hold waits for a resume
            self._hold_latched = self._hold_latched or self.hold_cause != HoldCause.POSITION_JUMP
            log.info("hold: grace over, requesting the autopilot's hold mode")
        if self._hold_escalated:
            return self._handover.velocity(t, mode), ModeClass.HOLD, None, None
        spot = self._hold_spot
        vel = self.nav.goto(pos, spot, HOLD_KEEP_SPEED_M_S) if pos is not None and spot is not None else ZERO
        return vel, ModeClass.OFFBOARD, None, None
