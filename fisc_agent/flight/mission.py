"""The mission state machine (pure: no I/O, time comes in with each status).

::

    WAIT_POSITION -> ARM -> TAKEOFF -> JOIN -> FLOW -> EXIT -> (hold) HOLD
                                        ^        |  \\        -> (land) LAND -> DONE
                                        |     RETURN \\-------> (loop) JOIN ...
                                        +--------------------------------+
    any flying state -> HOLD (failsafe or fleet "hold") -> previous state (auto or "resume")
    any armed state  -> LAND (fleet "land");  disarmed in flight -> DONE

Each ``step(status)`` returns a ``MissionOutput``: the map-frame velocity to stream (None: do
not stream), the autopilot mode and arming state wanted (reconciled by
``adapters.Commander``), and, for ArduPilot, the takeoff height.  Velocities are *unclamped*;
the runner clamps every setpoint.  Every transition is logged and kept in ``transitions``.

Holds: ``zero`` stage (zero-velocity setpoints, the vehicle stays in offboard/guided) for
``hold_grace_s``, then the autopilot's hold/loiter mode is requested.  A hold caused by a stale
position resumes by itself if the fix returns before that escalation; every other hold
(escalated, link lost, geofence, exit, fleet, pilot override) waits for a fleet ``resume``.
If a mode the agent asked for and got is changed by someone else (the pilot's mode switch, an
autopilot failsafe such as PX4's offboard loss or a battery RTL), the agent stops requesting
modes and streaming ("hands off") until a fleet ``resume``: it never fights the pilot.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Callable

from fisc_agent.mavlink.adapters import ModeClass
from fisc_agent.config import AgentConfig, ExitPolicy
from fisc_agent.flight.control import (ZERO, MapGeometry, ScalarField, Vec, approach_time_s, distance, entry_point,
                                entry_slot_open, goto_velocity, hold_point, join_waypoints, lap_return_waypoints)
from fisc_agent.flight.failsafe import GeofenceVerdict, PositionHealth, geofence, link_ok, position_health
from fisc_agent.flight.identify import ResponseRecorder, VehicleResponse
from fisc_agent.map.lookup import POINT_MODES
from fisc_agent.flight.mission_types import (FLYING, Cause, HoldCause, MissionCommand, MissionOutput, Reason, State,
                                      Transition, VehicleStatus)
from fisc_agent.flight.tracking import ParcelTracker

log = logging.getLogger(__name__)



AIRBORNE_ABOVE_HOME_M = 0.2
"""Height above home from which a vehicle counts as airborne (an interrupted takeoff then
finishes with climb setpoints: ArduPilot refuses a takeoff command once flying)."""


class Mission:
    """One vehicle's mission.  Feed ``step`` a ``VehicleStatus`` at the control rate."""

    def __init__(self, cfg: AgentConfig, sfield: ScalarField | None = None) -> None:
        self.cfg = cfg
        self.state = State.WAIT_POSITION
        self.reason = Reason(Cause.START)
        self.transitions: list[Transition] = []
        self.laps = 0
        self._pending: list[MissionCommand] = []
        self._t_state = 0.0
        self._home: Vec | None = None
        self._climb_by_velocity = False
        self._waypoints: list[Vec] = []
        self._wp_index = 0
        self._wait_index = 0
        self._entry_lead_s = 0.0
        self._wait_where_planned = False
        self._entry_cleared = False
        self._target: Vec | None = None
        self._last_want: ModeClass | None = None
        self._want_seen = False
        # hold bookkeeping
        self._resume_state = State.WAIT_POSITION
        self._hold_latched = False
        self._hold_escalated = False
        self._hands_off = False
        self._hold_armed = False
        self.sfield: ScalarField | None = None
        self.geom: MapGeometry | None = None
        self.entry: Vec | None = None
        self.tracker = ParcelTracker(cfg.tracking)
        self._tracked_mode = "mean"
        self._kinetic = False
        self.response: VehicleResponse | None = None
        """The vehicle's velocity response identified during take-off and join (``lookahead_auto``)."""
        self._recorder = ResponseRecorder()
        self._identify_tried = False
        self._last_pos: Vec | None = None
        if sfield is not None:
            self.set_map(sfield)

    # ---- inputs from outside -----------------------------------------------------------
    def set_map(self, sfield: ScalarField) -> None:
        """Use a new map from the next step (plans depending on the map are redone)."""
        self.sfield = sfield
        self.geom = MapGeometry.from_field(sfield.field)
        self.entry = entry_point(self.cfg.agent_id, self.geom, sfield, self.cfg.entry_radius_fraction)
        self.tracker.x_outlet_m = self.geom.x_outlet_m
        self.tracker.clear()  # a parcel of the old map means nothing in the new one
        mode = sfield.settings(self.cfg.mode).mode
        # kinetic under streamline tracking: the parcel follows the staggered field and carries the
        # agent's deviation (ParcelTracker.step), when the mode was asked for explicitly
        self._tracked_mode = "staggered" if mode == "kinetic" else mode
        self._kinetic = mode == "kinetic" and self.cfg.mode == "kinetic"
        if mode == "kinetic" and not self._kinetic and self.cfg.tracking.gain_1_s > 0.0:
            log.warning("the map recommends mode kinetic; under streamline tracking its deviations are flown only "
                        "with an explicit --mode kinetic (which turns them within --wall-margin of the map's real "
                        "wall: docs/deployment.md); flying the map's staggered field")
        if self.response is None:
            self.tracker.cfg = replace(self.tracker.cfg, lookahead_s=self._lookahead_s())
        if self._last_pos is not None and self.state == State.JOIN:
            self._plan_join(self._last_pos)
        if self._last_pos is not None and self.state == State.RETURN:
            self._plan_return(self._last_pos)

    def observe_response(self, t: float, sp_m_s: Vec, vel_m_s: Vec) -> None:
        """Record a streamed setpoint and the measured velocity (TAKEOFF and JOIN) for identification."""
        if self.state in (State.TAKEOFF, State.JOIN) and self.response is None:
            self._recorder.add(t, (sp_m_s[0], sp_m_s[1]), (vel_m_s[0], vel_m_s[1]))

    def _identify(self) -> None:
        """Fit the velocity response once (``lookahead_auto``) and tune the tracker's feed-forward."""
        if not self.cfg.lookahead_auto or self._identify_tried:
            return
        self._identify_tried = True  # once: the final leg calls this every tick
        resp = self._recorder.fit()
        if resp is None:
            log.warning("velocity response not identified (%d samples, too little excitation); flying with "
                        "look-ahead %.2f s, feed-forward gain %.2f", len(self._recorder),
                        self.tracker.cfg.lookahead_s, self.tracker.cfg.feedforward_gain)
            return
        self.response = resp
        self.tracker.cfg = replace(self.tracker.cfg, lookahead_s=resp.lookahead_s,
                                   feedforward_gain=resp.feedforward_gain)
        log.info("velocity response identified from %d samples: lag %.2f s, dead time %.2f s, gain %.2f (bound over "
                 "halves %.2f), rise time %.2f s, max accel %.1f m/s^2 -> look-ahead %.2f s, feed-forward gain %.2f",
                 resp.n_samples, resp.lag_s, resp.dead_time_s, resp.gain, resp.gain_bound, resp.rise_time_s,
                 resp.max_accel_m_s2, resp.lookahead_s, resp.feedforward_gain)

    def command(self, name: MissionCommand | str) -> None:
        """Queue a fleet command (``hold``, ``resume``, ``land``); applied at the next step."""
        self._pending.append(MissionCommand.parse(name))

    # ---- transitions ---------------------------------------------------------------------
    @property
    def hands_off(self) -> bool:
        """Someone else (pilot, autopilot failsafe) took the vehicle: no modes, no setpoints until a resume."""
        return self._hands_off

    @property
    def hold_cause(self) -> HoldCause | None:
        """Why the mission holds; None outside HOLD."""
        cause = self.reason.cause
        return cause if self.state == State.HOLD and isinstance(cause, HoldCause) else None

    @property
    def failed(self) -> bool:
        """The mission ended without flying (could not arm in offboard/guided)."""
        return self.state == State.DONE and self.reason.cause == Cause.ARM_FAILED

    def _go(self, t: float, dst: State, reason: Reason) -> None:
        if dst == self.state and reason == self.reason:
            return
        self.transitions.append(Transition(t, self.state, dst, reason))
        log.info("mission %s -> %s (%s)", self.state.value, dst.value, reason)
        if dst == State.FLOW and self.state != State.FLOW:
            self._identify()
            if self._last_pos is not None:
                self.tracker.reset(self._last_pos, t)  # a new parcel where the vehicle (re-)enters the flow
        self.state, self.reason, self._t_state = dst, reason, t

    def _hold(self, t: float, reason: Reason, latched: bool, armed: bool, hands_off: bool = False) -> None:
        if self.state != State.HOLD:
            self._resume_state = self.state
            self._hold_escalated = False
        if self.state == State.HOLD:
            self._hold_latched = self._hold_latched or latched
        else:
            self._hold_latched = latched
        self._hands_off = hands_off or (self._hands_off and self.state == State.HOLD)
        self._hold_armed = armed
        self._go(t, State.HOLD, reason)

    def _plan_join(self, pos: Vec) -> None:
        assert self.geom is not None and self.entry is not None
        cfg = self.cfg
        # With a stagger, a join waits for its window where it starts (after take-off: above the
        # vehicle's own launch point; after a hold: where it held), and leaves early by its flight to
        # the staging point S: it reaches S as its window opens and flies on without stopping.
        # Waiting at S, the agents stood at their entry points' (y, z), decimetres apart (PX4 SITL:
        # 0.19 m by SIH's ground truth).  A lap's return waits where its first join did, above its
        # launch point, reached over the tunnel (``lap_return_waypoints``).
        wait_at: Vec | None = None
        route: list[Vec] = []
        if cfg.entry_stagger_s > 0:
            if self._wait_where_planned:
                wait_at = pos
            elif self._home is not None:
                wait_at = (self._home[0], self._home[1], self._home[2] + cfg.takeoff_alt_m)
                route = lap_return_waypoints(pos, wait_at, self.geom, cfg.keepout_margin_m)[:-1]
        path = join_waypoints(pos if wait_at is None else wait_at, self.entry, self.geom, cfg.staging_m,
                              cfg.keepout_margin_m)
        self._waypoints = route + ([] if wait_at is None else [wait_at]) + path
        self._wait_index = len(self._waypoints) - 2 if wait_at is None else len(route)
        legs = self._waypoints[self._wait_index:-1]
        self._entry_lead_s = sum(approach_time_s(distance(a, b), cfg.join_speed_m_s, cfg.waypoint_radius_m)
                                 for a, b in zip(legs, legs[1:]))
        self._wp_index = 0
        self._entry_cleared = False

    def _plan_return(self, pos: Vec) -> None:
        assert self.sfield is not None
        self._target = self.sfield.centers[self.sfield.nearest_cv(*pos)]

    def _enter(self, t: float, dst: State, reason: Reason, pos: Vec | None) -> None:
        if dst == State.JOIN and pos is not None:
            self._wait_where_planned = self.state not in (State.FLOW, State.RETURN)  # not a lap's return
            self._plan_join(pos)
        elif dst == State.RETURN and pos is not None:
            self._plan_return(pos)
        elif dst == State.EXIT and pos is not None and self.geom is not None:
            self._target = hold_point(self.cfg.agent_id, self.geom, self.geom.x_outlet_m + self.cfg.exit_clearance_m,
                                      self.cfg.exit_spacing_m)
        elif dst == State.TAKEOFF:  # resuming an interrupted takeoff (a hold cuts ArduPilot's climb short)
            self._climb_by_velocity = (pos is not None and self._home is not None
                                       and pos[2] > self._home[2] + AIRBORNE_ABOVE_HOME_M)
        self._go(t, dst, reason)

    # ---- the step ------------------------------------------------------------------------
    def step(self, s: VehicleStatus) -> MissionOutput:
        """Advance the mission by one tick on the vehicle status ``s``: the state, the setpoint and any request."""
        t, cfg = s.t_s, self.cfg
        pos = s.pos_m
        if pos is not None:
            self._last_pos = pos
        cv = self.sfield.cv_of(*pos) if (pos is not None and self.sfield is not None) else -1
        ph = position_health(s.position_age_s, cfg.stale_timeout_s, cfg.hold_grace_s)
        lk = link_ok(s.heartbeat_age_s, cfg.link_timeout_s)

        for name in self._pending:
            self._fleet(t, name, s, pos, ph)
        self._pending.clear()

        # -- failsafes in the air ------------------------------------------------------------
        if pos is not None and s.vel_m_s is not None and s.position_age_s <= cfg.stale_timeout_s:
            # at the fix's own time, the autopilot's where it gives one: the ticks and the autopilot's
            # messages run on different clocks (a fix seen by two ticks would read as a stop and a
            # jump), and an autopilot whose clock runs slow against ours (PX4 SITL on a loaded host
            # ran at ~0.75 x real time) would read as a velocity bias of a quarter of the speed
            fix_t = s.fix_t_s if s.fix_t_s is not None else t - s.position_age_s
            self.tracker.observe(fix_t, pos, s.vel_m_s)
        if self.state in FLYING or self.state == State.HOLD:
            if not s.armed and (self.state in FLYING or self._hold_armed) and lk:
                self._go(t, State.DONE, Reason(Cause.DISARMED_IN_FLIGHT))
            elif not lk:
                if self.hold_cause != HoldCause.LINK_LOST:
                    log.warning("link lost: no autopilot HEARTBEAT for %.1f s; the autopilot's offboard-loss "
                                "failsafe is in charge", s.heartbeat_age_s)
                    self._hold(t, Reason(HoldCause.LINK_LOST), latched=True, armed=s.armed or self._hold_armed)
                    self._hold_escalated = True
            elif ph != PositionHealth.OK:
                if self.state != State.HOLD:
                    self._hold(t, Reason(HoldCause.POSITION_STALE), latched=False, armed=s.armed)
                if ph == PositionHealth.LOST and not self._hold_escalated and not self._hands_off:
                    self._hold_escalated = True
                    self._hold_latched = True
                    log.warning("position lost for %.1f s: requesting the autopilot's hold mode", s.position_age_s)
            elif self._mode_taken(s):  # checked before the auto-resume: never resume into a failsafe's mode
                self._hold(t, Reason(HoldCause.PILOT_OVERRIDE,
                                     f"pilot override: mode changed to {s.mode} outside the agent, hands off"),
                           latched=True, armed=s.armed, hands_off=True)
            elif self.hold_cause == HoldCause.POSITION_STALE and not self._hold_latched:
                self._auto_resume(t, pos)
        elif self.state == State.LAND and lk and s.armed and self._mode_taken(s):
            self._hold(t, Reason(HoldCause.PILOT_OVERRIDE,
                                 f"pilot override: mode changed to {s.mode} while landing, hands off"),
                       latched=True, armed=True, hands_off=True)

        st = self.state

        vel: Vec | None = None
        want_mode: ModeClass | None = None
        want_armed: bool | None = None
        takeoff: float | None = None
        by_command = s.autopilot == "ardupilot"

        if st == State.WAIT_POSITION:
            if lk and s.autopilot and ph == PositionHealth.OK and self.sfield is not None and pos is not None:
                if s.armed:
                    self._enter(t, State.FLOW if cv >= 0 else State.JOIN, Reason(Cause.TAKING_OVER), pos)
                else:
                    self._home = pos
                    self._go(t, State.ARM, Reason(Cause.AUTOPILOT_FOUND,
                                                  f"position and {s.autopilot} heartbeat received"))
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
            if done:
                self._enter(t, State.JOIN, Reason(Cause.TAKEOFF_DONE,
                                                  f"takeoff height {cfg.takeoff_alt_m:.1f} m reached"), pos)
        elif st == State.JOIN:
            want_mode = ModeClass.OFFBOARD
            last = len(self._waypoints) - 1
            while self._wp_index < last and distance(pos, self._waypoints[self._wp_index]) < cfg.waypoint_radius_m:
                self._wp_index += 1
            waiting = False
            if self._wp_index > self._wait_index and not self._entry_cleared:  # at the wait point (or past a copy)
                waiting = not entry_slot_open(s.wall_time_s + self._entry_lead_s, cfg.agent_id, cfg.entry_stagger_s,
                                              cfg.entry_slots)
                if not waiting:
                    self._entry_cleared = True
                    if cfg.entry_stagger_s > 0:
                        log.info("entry slot open: on to the inlet")
            if waiting:
                vel = self._goto(pos, self._waypoints[self._wait_index], cfg.join_speed_m_s)
            elif self._wp_index == last and cv >= 0:
                self._go(t, State.FLOW, Reason(Cause.ENTERED_MAP, f"entered the map at CV {cv}"))
                st = State.FLOW
            else:
                vel = self._goto(pos, self._waypoints[self._wp_index], cfg.join_speed_m_s)
                if self._wp_index == last:  # final leg: cross the inlet plane at the flow's own speed
                    self._identify()
                    v_in = self._field_command(*self._waypoints[last])
                    crawl = 0.3 if v_in is None else max(0.3, self.tracker.cfg.feedforward_gain * v_in[0])
                    vel = (max(vel[0], crawl), vel[1], vel[2])
        elif st == State.RETURN:
            want_mode = ModeClass.OFFBOARD
            if cv >= 0:
                self._go(t, State.FLOW, Reason(Cause.BACK_IN_MAP, f"back in the map at CV {cv}"))
                st = State.FLOW
            elif pos[0] >= self.geom.x_outlet_m:  # carried past the outlet while rejoining: that lap is done
                vel = self._passed_outlet(t, pos)
            else:
                vel = self._return_velocity(pos)
        elif st == State.EXIT:
            want_mode = ModeClass.OFFBOARD
            vel = self._goto(pos, self._target, cfg.join_speed_m_s)
            if distance(pos, self._target) < cfg.waypoint_radius_m:
                if cfg.exit_policy is ExitPolicy.LAND:
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
                if cfg.tracking.gain_1_s == 0.0:  # open loop: the simulator's own command function
                    vel = self.sfield.flight(pos, s.vel_m_s, cfg.agent_id, t, cfg.mode, self._lookahead_s(), cv)
                else:
                    deviation = self._deviation_fn(t, s.vel_m_s) if self._kinetic else None
                    vel = self.tracker.step(t, pos, self._field_command, deviation)
                    if vel is None:  # the parcel's CV vanished with a new map: fly the field where we are
                        self.tracker.reset(pos, t)
                        vel = self._field_command(*pos)
            elif verdict == GeofenceVerdict.EXIT:
                vel = self._passed_outlet(t, pos)
            elif verdict == GeofenceVerdict.RETURN:
                self._enter(t, State.RETURN, Reason(Cause.GEOFENCE_RETURN), pos)
                vel = self._return_velocity(pos)
            else:
                self._hold(t, Reason(HoldCause.GEOFENCE), latched=True, armed=s.armed)
                st = State.HOLD
                vel = None
        if self.state == State.HOLD:
            vel, want_mode, want_armed, takeoff = self._hold_output(t)
        elif self.state == State.LAND:
            vel, want_mode = None, ModeClass.LAND
            if not s.armed:
                self._go(t, State.DONE, Reason(Cause.LANDED))
        if self.state == State.DONE:
            vel, want_mode, want_armed, takeoff = None, None, None, None
        if want_mode != self._last_want:
            self._last_want, self._want_seen = want_mode, want_mode is not None and s.mode == want_mode
        elif want_mode is not None and s.mode == want_mode:
            self._want_seen = True
        return MissionOutput(self.state, vel, want_mode, want_armed, takeoff, cv, self.reason)

    def _passed_outlet(self, t: float, pos: Vec) -> Vec:
        """A lap is done: back to the inlet (exit policy ``loop``, laps left) or on to the exit."""
        cfg = self.cfg
        self.laps += 1
        if cfg.exit_policy is ExitPolicy.LOOP and (cfg.laps == 0 or self.laps < cfg.laps):
            self._enter(t, State.JOIN, Reason(Cause.LAP_DONE, f"lap {self.laps} done: back to the inlet"), pos)
        else:
            self._enter(t, State.EXIT, Reason(Cause.PASSED_OUTLET, f"passed the outlet (lap {self.laps})"), pos)
        return self._goto(pos, self._waypoints[0] if self.state == State.JOIN else self._target, cfg.join_speed_m_s)

    def _return_velocity(self, pos: Vec) -> Vec:
        """Geofence ``return``: near the map, rejoin the flow of the nearest CV (the simulator's rule,
        ``ScalarField.return_command``); farther, fly straight back to the CV chosen on leaving."""
        near = self.sfield.return_command(pos)
        return self._goto(pos, self._target, self.cfg.return_speed_m_s) if near is None else self._unbiased(near)

    def _goto(self, pos: Vec, target: Vec, speed_m_s: float) -> Vec:
        """``goto_velocity`` towards ``target``, corrected for the velocity-estimate bias (``_unbiased``)."""
        return self._unbiased(goto_velocity(pos, target, speed_m_s))

    def _unbiased(self, v: Vec) -> Vec:
        """``v`` minus the bias of the autopilot's velocity estimate learnt so far (``ParcelTracker.observe``,
        every tick).  An autopilot holds its *estimated* velocity at the setpoint, so with a biased estimate
        (PX4 SIH early in a flight, and after a hold: up to 0.8 m/s) a proportional approach settles
        bias / gain short of its waypoint.  Measured on PX4 SITL (the three-vehicle fleet test): the
        vehicles crossed the inlet 0.54-0.85 m off their entry points without it (one then flew along
        the wall and left the converging section), 0.20-0.28 m with it.  Streamline tracking subtracts
        the same bias while flowing."""
        b = self.tracker.bias_m_s
        return (v[0] - b[0], v[1] - b[1], v[2] - b[2])

    def _field_command(self, x: float, y: float, z: float) -> Vec | None:
        """The map's command at a point in the tracked mode (None outside the map's CVs)."""
        mode = self._tracked_mode
        if mode in POINT_MODES:
            return self.sfield.command(x, y, z, self.cfg.agent_id, mode)
        return self.sfield.flight((x, y, z), None, self.cfg.agent_id, 0.0, mode, 0.0)

    def _deviation_fn(self, t: float, vel: Vec | None) -> Callable[[Vec], Vec]:
        """The ``kinetic`` deviation at time ``t`` as a function of the parcel's position (for
        ``ParcelTracker.step``; the vehicle's velocity sets the wall-reflection zone)."""
        return lambda p: self.sfield.deviation(p, vel, self.cfg.agent_id, t, self.cfg.wall_margin_m)

    def _lookahead_s(self) -> float:
        """Look-ahead in use: identified in flight (``lookahead_auto``), else given, else the map's."""
        if self.response is not None:
            return self.response.lookahead_s
        if self.cfg.lookahead_s is not None:
            return float(self.cfg.lookahead_s)
        return self.sfield.settings().lookahead_s if self.sfield is not None else 0.0

    def _mode_taken(self, s: VehicleStatus) -> bool:
        """The mode we asked for was reached and has since been changed by someone else
        (the pilot's switch or an autopilot failsafe): do not fight it."""
        return (self._want_seen and self._last_want is not None and not self._hands_off
                and s.mode not in (self._last_want, ModeClass.UNKNOWN))

    def _hold_output(self, t: float) -> tuple[Vec | None, ModeClass | None, bool | None, float | None]:
        if self._hands_off or not self._hold_armed:
            return None, None, None, None
        if not self._hold_escalated and t - self._t_state >= self.cfg.hold_grace_s:
            self._hold_escalated = True
            self._hold_latched = True
            log.info("hold: zero-velocity grace over, requesting the autopilot's hold mode")
        if self._hold_escalated:
            return None, ModeClass.HOLD, None, None
        return ZERO, ModeClass.OFFBOARD, None, None

    def _auto_resume(self, t: float, pos: Vec | None) -> None:
        self._enter(t, self._resume_state, Reason(Cause.POSITION_BACK), pos)

    def _fleet(self, t: float, name: MissionCommand, s: VehicleStatus, pos: Vec | None, ph: PositionHealth) -> None:
        log.info("fleet command %s in state %s", name.value, self.state.value)
        if name == MissionCommand.HOLD:
            if self.state in FLYING or self.state == State.HOLD:
                self._hold(t, Reason(HoldCause.FLEET), latched=True, armed=s.armed or self._hold_armed)
            elif self.state in (State.WAIT_POSITION, State.ARM):
                self._hold(t, Reason(HoldCause.FLEET_ON_GROUND), latched=True, armed=s.armed)
                self._resume_state = State.WAIT_POSITION
        elif name == MissionCommand.LAND:
            if s.armed and self.state != State.DONE:
                self._go(t, State.LAND, Reason(Cause.FLEET_LAND))
            elif self.state != State.DONE:
                self._go(t, State.DONE, Reason(Cause.FLEET_LAND_DISARMED))
        elif name == MissionCommand.RESUME:
            if self.state != State.HOLD:
                return
            if ph != PositionHealth.OK:
                log.warning("fleet resume refused: position is %s", ph.value)
                return
            nxt = self._resume_state
            if self.hold_cause == HoldCause.GEOFENCE:
                nxt = State.RETURN
            elif self.hold_cause == HoldCause.EXIT:
                nxt = State.JOIN
            elif nxt == State.FLOW and self.sfield is not None and pos is not None and self.sfield.cv_of(*pos) < 0:
                nxt = State.RETURN
            self._hands_off = False
            self._enter(t, nxt, Reason(Cause.FLEET_RESUME), pos)
