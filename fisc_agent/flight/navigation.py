"""Where the vehicle flies (the mission's navigation, pure): the map's geometry and entry point,
the join and return plans, streamline tracking and the in-flight identification that tunes it.

``fisc_agent.flight.mission`` decides *when* (states, authority, failsafes); a ``Navigator``
answers *where to* and *how fast*: waypoints to the inlet, the field's command, the velocity
towards a point corrected for the velocity-estimate bias.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace

from fisc_agent.config import AgentConfig
from fisc_agent.flight.control import (ZERO, MapGeometry, ScalarField, Vec, approach_time_s, distance, entry_point,
                                       goto_velocity, hold_point, speed_for_arrival)
from fisc_agent.flight.routes import exit_waypoints, give_up_waypoints, join_waypoints, lap_return_waypoints
from fisc_agent.flight.mission_types import KEEPING_SPOT, Cause, HoldCause
from fisc_agent.flight.identify import OnlineGain, ResponseRecorder, VehicleResponse, feedforward_from_gain
from fisc_agent.flight.spacing import (ENTRY_TIMING_TOLERANCE_S, JOIN_LEG_ALLOWANCE_S, MAX_LEAD_LEARNT_S, EntrySchedule,
                                      entry_schedule, entry_slot_open, final_leg_speed_m_s, schedule_messages)
from fisc_agent.flight.point_command import PointCommand, point_command, tracked_mode
from fisc_agent.flight.tracking import DeviationFn, KineticAxes, ParcelTracker
from fisc_agent.map.separation import Separation
from fisc_agent.map.wall import rejoin_point

log = logging.getLogger("fisc_agent.flight.mission")
_NO_BUDGET = Separation()
"""A map's separation before the map is known (no budget)."""


EXIT_CORNER_RADIUS_M = 1.0
"""The exit route turns to its next leg this far from a corner (``Navigator.exit_velocity``) [m]."""
EXIT_CORNER_GAIN_1_S = 3.0
"""Approach gain towards an exit corner: full speed until ``speed / gain`` from it [1/s]."""
EXIT_SETTLE_SPEED_M_S = 0.25
"""The exit holds at its spot only once the vehicle is slower than this (``Navigator.exit_arrived``) [m/s]."""


class Navigator:
    """The map-dependent plans of one vehicle's mission."""

    def __init__(self, cfg: AgentConfig) -> None:
        self.cfg = cfg
        self.sfield: ScalarField | None = None
        self.geom: MapGeometry | None = None
        self.entry: Vec | None = None
        self.tracker = ParcelTracker(cfg.tracking)
        self.tracked_mode = "mean"
        self.kinetic = False
        self._point_cmd: PointCommand | None = None
        """The map's command in ``tracked_mode`` at a point (``point_command``; None before a map)."""
        self.response: VehicleResponse | None = None
        """The vehicle's velocity response identified during take-off and join (``lookahead_auto``)."""
        self.recorder = ResponseRecorder()
        self._identify_tried = False
        self.online_gain: OnlineGain | None = None
        """The gain learnt again through the passes (``adapt``), once the response is identified."""
        self._logged_feedforward = math.nan
        self.waypoints: list[Vec] = []
        self.wp_index = 0
        self.wait_index = 0
        self.entry_lead_s = 0.0
        self.entry_cleared = False
        self.staging_due_s: float | None = None
        """When (shared clock) the join, cleared to leave, is due at its staging point (``join_step``)."""
        self.entry_on_time = False
        """The join reached its staging point in time and may cross the inlet (``_late_at_staging``)."""
        self.crossing_due_s: float | None = None
        """When (shared clock) the join, on time at its staging point, is due across the inlet plane: the
        staging point's due time plus the final leg at the inlet's crawl and ``JOIN_LEG_ALLOWANCE_S``."""
        self.late_entries = 0
        """Entries given up: at the staging point, or across the inlet plane, more than
        ``ENTRY_TIMING_TOLERANCE_S`` after the due time."""
        self.lead_learnt_s = 0.0
        """Added to every join's lead: what this vehicle's arrivals at its staging point taught it, the
        lateness of each one more than ``ENTRY_TIMING_TOLERANCE_S`` late added, the earliness of each one
        more than that early taken off (within 0 and ``MAX_LEAD_LEARNT_S``; ``_late_at_staging``)."""
        self.leg_lead_s = 0.0
        """How much before its staging point's due time this vehicle starts its final leg, learnt as
        ``lead_learnt_s`` is from its crossings of the inlet plane (``_late_across``): a vehicle slower than
        the inlet's crawl then crosses when due.  Also added to every join's lead."""
        self.target: Vec | None = None
        self.exit_route: list[Vec] = []
        """The exit's waypoints (``plan_exit``), ending at ``target``, the agent's hold spot."""
        self.exit_index = 0
        self.schedule = entry_schedule(cfg.entry_stagger_s, cfg.entry_slots, _NO_BUDGET)
        """The entry windows in use (``spacing.entry_schedule``): the configured ones, or the map's budget."""

    def set_map(self, sfield: ScalarField) -> None:
        """Use a new map (the mission re-plans a join or return in progress)."""
        self.sfield = sfield
        self.geom = MapGeometry.from_field(sfield.field)
        self.entry = entry_point(self.cfg.agent_id, self.geom, sfield, self.cfg.entry_radius_fraction)
        schedule = entry_schedule(self.cfg.entry_stagger_s, self.cfg.entry_slots, sfield.separation)
        if schedule != self.schedule:
            for level, message in schedule_messages(schedule, sfield.separation, self.cfg.agent_id):
                log.log(level, message)
        self.schedule = schedule
        self.tracker.x_outlet_m = self.geom.x_outlet_m
        self.tracker.clear()  # a parcel of the old map means nothing in the new one
        mode = sfield.settings(self.cfg.mode).mode
        # kinetic under streamline tracking: the parcel follows the staggered field and carries the
        # agent's deviation (ParcelTracker.step), turned before the map's real wall where it has one
        wall_known = sfield.wall is not None and self.cfg.wall_margin_m is not None
        self.tracked_mode, self.kinetic = tracked_mode(mode, self.cfg.mode, wall_known)
        self._point_cmd = point_command(sfield, self.tracked_mode, self.cfg.agent_id)
        if mode == "kinetic" and not self.kinetic and self.cfg.tracking.gain_1_s > 0.0:
            log.warning("the map recommends mode kinetic but carries no real wall (duct_wall_m) to turn its deviations "
                        "before (or --wall-margin is off): flying the map's staggered field without them; an explicit "
                        "--mode kinetic flies them turning at the CV staircase (docs/deployment.md)")
        if self.response is None:
            self.tracker.cfg = replace(self.tracker.cfg, lookahead_s=self.lookahead_s())

    # ---- identification ------------------------------------------------------------------
    def record_response(self, t: float, sp_m_s: Vec, vel_m_s: Vec) -> None:
        """Record a streamed setpoint and the measured velocity for identification."""
        if self.response is None:
            self.recorder.add(t, (sp_m_s[0], sp_m_s[1]), (vel_m_s[0], vel_m_s[1]))

    def adapt(self, t: float, sp_m_s: Vec, vel_m_s: Vec) -> None:
        """FLOW: learn the vehicle's steady gain again from the setpoint streamed and the velocity
        measured (``identify.OnlineGain``) and fly its feed-forward gain (only with the response
        identified in flight, ``feedforward_auto`` and ``online_gain_time_s`` > 0)."""
        tau = self.tracker.cfg.online_gain_time_s
        if self.response is None or tau <= 0.0 or not self.tracker.cfg.feedforward_auto:
            return
        if self.online_gain is None:
            self.online_gain = OnlineGain(self.response.lookahead_s, tau)
        self.online_gain.update(t, (sp_m_s[0], sp_m_s[1]), (vel_m_s[0], vel_m_s[1]))
        g = self.online_gain.gain
        if g is None:
            return
        ff = feedforward_from_gain(g)
        if abs(ff - self.tracker.cfg.feedforward_gain) >= 0.005:
            self.tracker.cfg = replace(self.tracker.cfg, feedforward_gain=ff)
        if not abs(ff - self._logged_feedforward) < 0.05:
            self._logged_feedforward = ff
            log.info("velocity gain learnt in the pass: %.2f -> feed-forward gain %.2f", g, ff)

    def identify_again(self) -> None:
        """Identify the response anew from the next take-off or join (the loop changed: the drag's feed-forward
        came on, ``fisc_agent.flight.drag``); until then the look-ahead given, or the map's."""
        self.response, self.online_gain, self._identify_tried, self.recorder = None, None, False, ResponseRecorder()
        self.tracker.cfg = replace(self.tracker.cfg, lookahead_s=self.lookahead_s())

    def identify(self) -> None:
        """Fit the velocity response once (``lookahead_auto``): the tracker's look-ahead, and its feed-forward
        gain with ``feedforward_auto``."""
        if not self.cfg.lookahead_auto or self._identify_tried:
            return
        self._identify_tried = True  # once: the final leg calls this every tick
        resp = self.recorder.fit()
        if resp is None:
            log.warning("velocity response not identified (%d samples, too little excitation); flying with "
                        "look-ahead %.2f s, feed-forward gain %.2f", len(self.recorder),
                        self.tracker.cfg.lookahead_s, self.tracker.cfg.feedforward_gain)
            return
        self.response = resp
        cfg = self.tracker.cfg
        self.tracker.cfg = replace(cfg, lookahead_s=resp.lookahead_s,
                                   feedforward_gain=resp.feedforward_gain if cfg.feedforward_auto else cfg.feedforward_gain)
        log.info("velocity response identified from %d samples: lag %.2f s, dead time %.2f s, gain %.2f (bound over "
                 "halves %.2f), rise time %.2f s, max accel %.1f m/s^2 -> look-ahead %.2f s, feed-forward gain %.2f",
                 resp.n_samples, resp.lag_s, resp.dead_time_s, resp.gain, resp.gain_bound, resp.rise_time_s,
                 resp.max_accel_m_s2, resp.lookahead_s, resp.feedforward_gain)

    # ---- plans ---------------------------------------------------------------------------
    def plan_join(self, pos: Vec, home: Vec | None, wait_where_planned: bool) -> None:
        """Waypoints from ``pos`` to the agent's entry point (via its wait point with a stagger)."""
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
        if self.schedule.stagger_s > 0:
            if wait_where_planned:
                wait_at = pos
            elif home is not None:
                wait_at = (home[0], home[1], home[2] + cfg.takeoff_alt_m)
                route = lap_return_waypoints(pos, wait_at, self.geom, cfg.keepout_margin_m, cfg.staging_m)[:-1]
        self._plan_join_via(pos, route, wait_at)

    def _plan_join_via(self, pos: Vec, route: list[Vec], wait_at: Vec | None) -> None:
        """The join's waypoints: ``route``, the wait point ``wait_at`` (None: no wait), then on to the entry."""
        cfg = self.cfg
        path = join_waypoints(pos if wait_at is None else wait_at, self.entry, self.geom, cfg.staging_m,
                              cfg.keepout_margin_m)
        self.waypoints = route + ([] if wait_at is None else [wait_at]) + path
        self.wait_index = len(self.waypoints) - 2 if wait_at is None else len(route)
        legs = self.waypoints[self.wait_index:-1]
        self.entry_lead_s = self.lead_learnt_s + self.leg_lead_s + sum(
            approach_time_s(distance(a, b), cfg.join_speed_m_s, cfg.waypoint_radius_m) + JOIN_LEG_ALLOWANCE_S
            for a, b in zip(legs, legs[1:]))
        self.wp_index = 0
        self.entry_cleared = False
        self.staging_due_s = None
        self.entry_on_time = False
        self.crossing_due_s = None

    def _crawl_m_s(self) -> float:
        """The final leg's least speed along x: the flow's own at the entry point (times the feed-forward
        gain), at least 0.3 m/s."""
        v_in = self.field_command(*self.waypoints[-1])
        return 0.3 if v_in is None else max(0.3, self.tracker.cfg.feedforward_gain * v_in[0])

    def _give_up_window(self, pos: Vec, late_s: float, where: str) -> None:
        """Not entering in this window: back to the wait point for the next one by its own join route, its
        part in the staging plane flown back upstream of it (``routes.give_up_waypoints``); counted in
        ``late_entries``.  (Up over the tunnel from where it gave up, a vehicle 3.9 s late at its staging
        point climbed beside the next one arriving at its own: 0.58 m apart by SIH's ground truth, eight
        stock PX4.)"""
        log.warning("%s %.1f s after its due time (more than %.1f s): not entering; back to the wait point for "
                    "the next entry window", where, late_s, ENTRY_TIMING_TOLERANCE_S)
        self.late_entries += 1
        wait_at = self.waypoints[self.wait_index]
        passed = self.waypoints[self.wait_index + 1:self.wp_index]
        self._plan_join_via(pos, give_up_waypoints(pos, passed, wait_at, self.geom, self.cfg.staging_m)[:-1], wait_at)

    def _late_across(self, pos: Vec, wall_time_s: float) -> bool:
        """On the final leg, not yet across the inlet plane more than ``ENTRY_TIMING_TOLERANCE_S`` after
        ``crossing_due_s``?  Then the agent gives its window up (``_give_up_window``), as at the staging
        point: the admission budget spaces the crossings, not the departures from the staging points.
        (Emulated stock PX4: two vehicles on time at their staging points were held back by the net behind
        a jam at the inlet and crossed it 0.2 s apart, then came within 0.6 m.)  The lateness is learnt into
        ``leg_lead_s``: a vehicle slower than the crawl starts its final leg that much earlier next time."""
        late_s = wall_time_s - self.crossing_due_s
        if late_s <= ENTRY_TIMING_TOLERANCE_S:
            return False
        self.leg_lead_s = min(MAX_LEAD_LEARNT_S, self.leg_lead_s + late_s)
        self._give_up_window(pos, late_s, "not across the inlet")
        return True

    def _crossed(self, wall_time_s: float) -> None:
        """Across the inlet plane: more than ``ENTRY_TIMING_TOLERANCE_S`` before ``crossing_due_s``, the
        earliness comes off ``leg_lead_s`` (not below 0), as on early arrivals at the staging point."""
        if self.crossing_due_s is None:
            return
        late_s = wall_time_s - self.crossing_due_s
        if late_s < -ENTRY_TIMING_TOLERANCE_S:
            self.leg_lead_s = max(0.0, self.leg_lead_s + late_s)
        log.info("across the inlet %+.1f s from its due time (leg lead now %.1f s)", late_s,
                 self.leg_lead_s)

    def _final_leg_due_s(self) -> float:
        """When (shared clock) the join is due to leave its staging point on its final leg: the staging
        point's due time less ``leg_lead_s``."""
        return self.staging_due_s - self.leg_lead_s

    def _late_on_the_way(self, pos: Vec, wall_time_s: float) -> bool:
        """On its way to the staging point S, already sure to reach it more than ``ENTRY_TIMING_TOLERANCE_S``
        after its due time (the window's opening less ``leg_lead_s``)?  Sure: even the rest of the route
        flown straight at the governor's top speed, without slowing at its corners (a lower bound on the
        time it takes), would bring it there late.  Then it gives the window up where it is
        (``_give_up_window``) instead of at S, where the join routes meet: decided at S, a join late by
        about one window turned back just as the next vehicle arrived at its own staging point.  It
        learns (``lead_learnt_s``) the lateness of its arrival at top speed as the join's lead counts
        the legs (``approach_time_s``, slowing at each corner): more than the sure lateness, less than
        what it would have shown at S."""
        last = len(self.waypoints) - 1
        path = [pos] + self.waypoints[self.wp_index:last]   # on to S = waypoints[-2]
        legs = [distance(a, b) for a, b in zip(path, path[1:])]
        hi = self._top_join_speed_m_s()
        due_s = self._final_leg_due_s()
        sure_s = wall_time_s + sum(legs) / hi - due_s
        if sure_s <= ENTRY_TIMING_TOLERANCE_S:
            return False   # (approach_time_s stops a waypoint radius short: it can be less than sure_s)
        modelled_s = wall_time_s + sum(approach_time_s(d, hi, self.cfg.waypoint_radius_m) for d in legs) - due_s
        late_s = max(sure_s, modelled_s)
        self.lead_learnt_s = min(MAX_LEAD_LEARNT_S, self.lead_learnt_s + late_s)
        self._give_up_window(pos, late_s, "on its way: at top speed at the staging point")
        return True

    def _late_at_staging(self, pos: Vec, wall_time_s: float) -> bool:
        """At the staging point later than ``ENTRY_TIMING_TOLERANCE_S`` after its due time (the window's
        opening less ``leg_lead_s``, when the final leg starts; held up on the
        way: the safety net, a lag beyond the governor's reach)?  Then the agent does not enter: entering
        late, it would start across next to the vehicle of the following window (on eight real PX4 one
        so delayed 4 s by the net entered 1.8 s before the next, and the two came within 0.47 m by SIH's
        ground truth).  It flies back by its own route to its wait point (``_give_up_window``) and
        waits for its next window; counted in ``late_entries``.  Its joins then leave earlier by the
        delay (``lead_learnt_s``) and the arrival governor (``_join_speed``) aims that much before the
        due time, so a vehicle late by habit reaches the staging point when due (stock PX4 with the net
        acting on the way were 2.6-7.8 s late on every lap, paced to the due time itself).  An arrival
        more than the tolerance early takes its earliness off the learnt lead: a delay that has gone (the
        net no longer acting on the way) stops sending the vehicle early, to wait at its staging point
        beside the one entering before it."""
        late_s = wall_time_s - self._final_leg_due_s()
        if late_s <= ENTRY_TIMING_TOLERANCE_S:
            self.entry_on_time = True
            if late_s < -ENTRY_TIMING_TOLERANCE_S:
                self.lead_learnt_s = max(0.0, self.lead_learnt_s + late_s)
            leg_m = distance(self.waypoints[-2], self.waypoints[-1])
            self.crossing_due_s = self.staging_due_s + leg_m / self._crawl_m_s() + JOIN_LEG_ALLOWANCE_S
            log.info("at the staging point %+.1f s from its due time: entering (learnt lead %.1f s)", late_s,
                     self.lead_learnt_s)
            return False
        self.lead_learnt_s = min(MAX_LEAD_LEARNT_S, self.lead_learnt_s + late_s)
        self._give_up_window(pos, late_s, "at the staging point")
        return True

    def join_step(self, pos: Vec, cv: int, wall_time_s: float, vel_m_s: Vec | None = None) -> Vec | None:
        """JOIN's velocity: along the waypoints, waiting at the wait point for the agent's entry window
        (on the shared clock ``wall_time_s``), then across the inlet plane at the flow's own speed;
        None once the last waypoint is passed inside the map (the vehicle has entered the flow)."""
        cfg = self.cfg
        last = len(self.waypoints) - 1
        while self.wp_index < last and distance(pos, self.waypoints[self.wp_index]) < cfg.waypoint_radius_m:
            self.wp_index += 1
        if self.wp_index > self.wait_index and not self.entry_cleared:  # at the wait point (or past a copy)
            if not entry_slot_open(wall_time_s + self.entry_lead_s, cfg.agent_id, self.schedule.stagger_s,
                                   self.schedule.slots):
                return self.goto(pos, self.waypoints[self.wait_index], cfg.join_speed_m_s)
            self.entry_cleared = True
            if self.schedule.stagger_s > 0:
                self.staging_due_s = wall_time_s + self.entry_lead_s
                log.info("entry slot open: on to the inlet")
        if (self.wp_index < last and self.staging_due_s is not None and not self.entry_on_time
                and self._late_on_the_way(pos, wall_time_s)):
            return self.join_step(pos, cv, wall_time_s)   # on the way back (no due time: once)
        if (self.wp_index == last and self.staging_due_s is not None and not self.entry_on_time
                and self._late_at_staging(pos, wall_time_s)):
            return self.join_step(pos, cv, wall_time_s)   # on the way back (no due time: once)
        if self.wp_index == last and cv >= 0:
            self._crossed(wall_time_s)
            return None
        if self.entry_on_time and self.crossing_due_s is not None and self._late_across(pos, wall_time_s):
            return self.join_step(pos, cv, wall_time_s)
        if (self.wp_index == last and self.staging_due_s is not None
                and wall_time_s < self._final_leg_due_s()):
            return self.goto(pos, self.waypoints[last - 1], cfg.join_speed_m_s)   # early at S: wait until due
        vel = self.goto(pos, self.waypoints[self.wp_index], speed := self._join_speed(pos, wall_time_s))
        if self.wp_index == last:  # final leg: across the inlet plane at the flow's own speed (final_leg_speed_m_s)
            self.identify()
            vx = final_leg_speed_m_s(self.geom.x_inlet_m - pos[0], self._crawl_m_s(), self.lookahead_s(), speed,
                                     time_left_s=None if self.crossing_due_s is None
                                     else self.crossing_due_s - JOIN_LEG_ALLOWANCE_S - wall_time_s,
                                     vx_m_s=None if vel_m_s is None else vel_m_s[0])
            vel = (self.unbiased((vx, 0.0, 0.0))[0], vel[1], vel[2])
        return vel

    def _top_join_speed_m_s(self) -> float:
        """The arrival governor's top speed (``_join_speed``): 1.5 x the join speed, within the speed limit."""
        return min(self.cfg.max_speed_m_s, 1.5 * self.cfg.join_speed_m_s)

    def _join_speed(self, pos: Vec, wall_time_s: float) -> float:
        """The join's speed: with entry windows, from the wait point to the staging point the one
        that brings the vehicle there when it is due (``control.speed_for_arrival``, up to 1.5 x the
        join speed and the speed limit), else the join speed.  It aims ``lead_learnt_s`` before the due
        time: the delay this vehicle showed (slower than commanded, held by the net) then brings it
        there when due; an early arrival waits at the staging point until due."""
        cfg, last = self.cfg, len(self.waypoints) - 1
        if self.staging_due_s is None or self.wp_index >= last:
            return cfg.join_speed_m_s
        path = [pos] + self.waypoints[self.wp_index:last]   # on to the staging point S = waypoints[-2]
        legs = [distance(a, b) for a, b in zip(path, path[1:])]
        hi = self._top_join_speed_m_s()
        aim_s = self._final_leg_due_s() - self.lead_learnt_s
        return speed_for_arrival(legs, aim_s - wall_time_s, cfg.waypoint_radius_m,
                                 min(0.3, hi), hi)

    def plan_exit(self, pos: Vec, min_z_m: float | None) -> None:
        """The exit from past the outlet ``pos`` to the agent's hold spot (``target``), over the spots
        of the others (``routes.exit_waypoints``).  ``min_z_m``: the spot's least altitude."""
        assert self.geom is not None
        cfg = self.cfg
        self.target = hold_point(cfg.agent_id, self.geom, self.geom.x_outlet_m + cfg.exit_clearance_m,
                                 cfg.exit_spacing_m, min_z_m=min_z_m)
        self.exit_route = exit_waypoints(pos, self.target, self.geom, cfg.exit_clearance_m, cfg.exit_spacing_m,
                                         cfg.keepout_margin_m)
        self.exit_index = 0

    def exit_arrived(self, pos: Vec, vel_m_s: Vec | None) -> bool:
        """At the hold spot: within the waypoint radius and slower than ``EXIT_SETTLE_SPEED_M_S`` (the
        exit comes down onto its spot; an ArduCopter that started its hold still descending at the
        radius settled 0.92 m lower, beyond the hold test's 0.5 m)."""
        if self.target is None or distance(pos, self.target) >= self.cfg.waypoint_radius_m:
            return False
        return vel_m_s is None or distance(vel_m_s, ZERO) < EXIT_SETTLE_SPEED_M_S

    def exit_velocity(self, pos: Vec) -> Vec:
        """EXIT's velocity: along ``exit_route`` at the join speed, through its corners without slowing
        (within ``EXIT_CORNER_RADIUS_M`` of one, on to the next): a leader that slowed at the climb
        point let the vehicle exiting behind it come within 0.39 m on real PX4."""
        last = len(self.exit_route) - 1
        while self.exit_index < last and distance(pos, self.exit_route[self.exit_index]) < EXIT_CORNER_RADIUS_M:
            self.exit_index += 1
        gain = 1.0 if self.exit_index == last else EXIT_CORNER_GAIN_1_S
        return self.goto(pos, self.exit_route[self.exit_index], self.cfg.join_speed_m_s, gain)

    def plan_return(self, pos: Vec) -> None:
        """Geofence return: head for the CV nearest to ``pos``."""
        assert self.sfield is not None
        self.target = self.sfield.centers[self.sfield.nearest_cv(*pos)]

    # ---- velocities ----------------------------------------------------------------------
    def return_velocity(self, pos: Vec) -> Vec:
        """Geofence ``return``: near the map, rejoin the flow of the nearest CV (the simulator's rule,
        ``ScalarField.return_command``), or where the map carries the wall fly straight in across the stream
        (``rejoin_velocity``: on stock PX4 SIH the flow and its inward pull kept a vehicle 0.3-0.5 m beyond
        the wall for 6 s, the straight line brings it in at the return speed); farther, fly straight back
        to the CV chosen on leaving."""
        near = self.sfield.return_command(pos)
        if near is None:
            return self.goto(pos, self.target, self.cfg.return_speed_m_s)
        inward = self.rejoin_velocity(pos)  # also in the map while not yet clear of its wall
        return self.unbiased(near) if inward is None else inward

    def hold_spot(self, pos: Vec | None, cause: HoldCause | Cause) -> Vec | None:
        """Where a hold that began at ``pos`` keeps the vehicle in its first stage: None (zero velocity) unless
        its cause is in ``KEEPING_SPOT``; that spot, except that a fleet hold at the wall keeps the point
        straight in from it (``rejoin_target``), so that the autopilot's own hold begins clear of the wall
        (a geofence hold keeps the spot where it left the map: its policy is to stop there)."""
        if cause not in KEEPING_SPOT:
            return None
        inward = self.rejoin_target(pos) if pos is not None and cause == HoldCause.FLEET else None
        return pos if inward is None else inward

    def rejoin_target(self, pos: Vec) -> Vec | None:
        """The point straight in from ``pos`` where a vehicle too near the map's wall, or beyond it, rejoins the
        flow (``fisc_agent.map.wall.rejoin_point``, with the wall margin ``wall_margin_m``); None when clear of
        the wall, or when the map carries no wall or no margin is set (then the CVs alone decide)."""
        wall, margin = (None, None) if self.sfield is None else (self.sfield.wall, self.cfg.wall_margin_m)
        return None if wall is None or margin is None else rejoin_point(wall, pos, margin)

    def rejoin_velocity(self, pos: Vec) -> Vec | None:
        """Towards ``rejoin_target`` across the stream at the return speed; None where there is none."""
        point = self.rejoin_target(pos)
        return None if point is None else self.goto(pos, point, self.cfg.return_speed_m_s)

    def goto(self, pos: Vec, target: Vec, speed_m_s: float, gain_1_s: float = 1.0) -> Vec:
        """``goto_velocity`` towards ``target``, corrected for the velocity-estimate bias (``unbiased``)."""
        return self.unbiased(goto_velocity(pos, target, speed_m_s, gain_1_s))

    def unbiased(self, v: Vec) -> Vec:
        """``v`` minus the bias of the autopilot's velocity estimate learnt so far (``ParcelTracker.observe``,
        every tick).  An autopilot holds its *estimated* velocity at the setpoint, so with a biased estimate
        (PX4 SIH early in a flight, and after a hold: up to 0.8 m/s) a proportional approach settles
        bias / gain short of its waypoint.  Measured on PX4 SITL (the three-vehicle fleet test): the
        vehicles crossed the inlet 0.54-0.85 m off their entry points without it (one then flew along
        the wall and left the converging section), 0.20-0.28 m with it.  Streamline tracking subtracts
        the same bias while flowing."""
        b = self.tracker.bias_m_s
        return (v[0] - b[0], v[1] - b[1], v[2] - b[2])

    def field_command(self, x: float, y: float, z: float) -> Vec | None:
        """The map's command at a point in the tracked mode (None outside the map's CVs)."""
        return self._point_cmd(x, y, z)

    def enter_flow(self, t: float, pos: Vec | None, back_to_streamline: bool) -> None:
        """Entering FLOW: identify the response (once), then keep the pass's streamline
        (``ParcelTracker.resume``, ``mission_types.BACK_TO_STREAMLINE``) or start a new parcel at ``pos``."""
        self.identify()
        if back_to_streamline:
            self.tracker.resume(t)
        elif pos is not None:
            self.tracker.reset(pos, t)

    def flow_velocity(self, t: float, pos: Vec, vel: Vec | None, cv: int, flown: bool = True) -> Vec | None:
        """The FLOW setpoint: the simulator's command function open loop (tracking gain 0), else the
        tracked parcel's (with the kinetic deviation when flying ``--mode kinetic``).  ``flown`` False: the
        autopilot does not fly the setpoints yet (PX4 took 2.7 s to leave its hold mode after a resume), so its
        drift meanwhile is not the tracking's to integrate."""
        cfg = self.cfg
        if not flown:
            self.tracker.resume(t)
        if cfg.tracking.gain_1_s == 0.0:
            return self.sfield.flight(pos, vel, cfg.agent_id, t, cfg.mode, self.lookahead_s(), cv)
        deviation = self._deviation_fn(t, vel) if self.kinetic else None
        out = self.tracker.step(t, pos, self._point_cmd, deviation)
        if out is None:  # the parcel's CV vanished with a new map: fly the field where we are
            self.tracker.reset(pos, t)
            out = self.field_command(*pos)
        return out

    def _deviation_fn(self, t: float, vel: Vec | None) -> DeviationFn:
        """The ``kinetic`` deviation at time ``t`` for ``ParcelTracker.step`` (the vehicle's velocity sets the
        wall-reflection zone; the field's direction turns it with ``TrackingConfig.kinetic_axes`` cross-stream)."""
        cross = self.cfg.tracking.kinetic_axes is KineticAxes.CROSS_STREAM
        return lambda p, s: self.sfield.deviation(p, vel, self.cfg.agent_id, t, self.cfg.wall_margin_m, s if cross else None)

    def lookahead_s(self) -> float:
        """Look-ahead in use: identified in flight (``lookahead_auto``), else given, else the map's."""
        if self.response is not None:
            return self.response.lookahead_s
        if self.cfg.lookahead_s is not None:
            return float(self.cfg.lookahead_s)
        return self.sfield.settings().lookahead_s if self.sfield is not None else 0.0
