"""Fleet orders carried out by the mission (hold, land, go, takeover, resume): the part of
``fisc_agent.flight.mission.Mission`` that acts on what ``authority.fleet_action`` decides (pure, no I/O).

A fleet hold on the ground (``HoldCause.FLEET_ON_GROUND``) that interrupts ``ARM`` may meet the agent's own
arm request still on its way: the autopilot can arm a moment after the hold.  The vehicle is then the
agent's, armed in offboard/guided, and must not be left without setpoints (PX4's offboard-loss failsafe
would change its mode, which reads as someone else's).  So for ``ARM_ANSWER_S`` after such a hold, and for
as long as the vehicle is armed while the agent is in command, the hold streams zero velocity in
offboard/guided (``ground_hold_output``).  Disarmed again (the autopilot's pre-flight disarm), the
vehicle simply waits on the ground; a ``resume`` while it is still armed goes on to the take-off
(``ARM``), otherwise to ``STANDBY`` and a new arming.  (A stock PX4 (SIH), 2026-12-07: a hold 0.6 s after the
arm request left the vehicle armed without setpoints; PX4 changed its mode within 1 s, the agent went
hands-off and the flight ended when PX4 disarmed it.)
"""

from __future__ import annotations

import logging
import math

from fisc_agent.flight.authority import AuthorityCause, FleetAction, fleet_action
from fisc_agent.flight.control import ZERO, Vec
from fisc_agent.flight.failsafe import PositionHealth
from fisc_agent.flight.mission_types import (Authority, Cause, FleetOrder, HoldCause, HoldOutput, Reason, State,
                                             VehicleStatus, FLYING)
from fisc_agent.mavlink.adapters import ModeClass

log = logging.getLogger("fisc_agent.flight.mission")
"""The mission's logger: fleet orders are logged as the mission's own lines."""


ARM_ANSWER_S = 3.0
"""How long after a fleet hold interrupts ``ARM`` the agent's own arm request may still be answered [s]
(the request waits up to a second for a fresh HEARTBEAT, the autopilot answers within about one more):
the hold keeps the offboard stream alive that long even while the vehicle is still disarmed."""


RESUME_WAIT_S = 5.0
"""A fleet ``resume`` refused because the position is not good (stale or lost) is carried out if it becomes
good within this long [s]; after that it is dropped (said), and the operator sends it again.  (Sent once, a
resume refused for a moment's stale position under load left a vehicle in its hold for good.)"""


class FleetOrders:
    """Mixin of ``Mission``: the fleet orders queued by ``Mission.command``, applied by ``Mission.step``."""

    _arm_answer_until_s: float = -math.inf
    """Until when (mission time) an arm request interrupted by a fleet hold may still be answered [s]."""
    _resume_wait_until_s: float | None = None
    """A refused resume waits for a good position until then (mission time) [s]; None: none waiting."""

    def _retry_resume(self, t: float, pos: Vec | None, ph: PositionHealth, armed: bool) -> None:
        """Each step: carry out a resume refused for its position once the position is good, if still held."""
        until = self._resume_wait_until_s
        if until is None:
            return
        if self.state != State.HOLD:
            self._resume_wait_until_s = None
        elif ph == PositionHealth.OK:
            self._resume_wait_until_s = None
            log.info("fleet resume: the position is good again; resuming")
            self._resume(t, pos, ph, armed)
        elif t > until:
            self._resume_wait_until_s = None
            log.warning("fleet resume dropped: the position is still %s after %.0f s; send resume again", ph.value,
                        RESUME_WAIT_S)

    def _fleet(self, t: float, order: FleetOrder, s: VehicleStatus, pos: Vec | None, ph: PositionHealth) -> None:
        self._resume_wait_until_s = None   # a newer order replaces a resume still waiting for its position
        verdict = fleet_action(order, self.authority, s.armed, self.state == State.HOLD)
        scope = "addressed" if order.addressed else "swarm-wide"
        if verdict.note:
            log.warning("fleet command %s (%s) in state %s: %s", order.command.value, scope, self.state.value,
                        verdict.note)
        else:
            log.info("fleet command %s (%s) in state %s", order.command.value, scope, self.state.value)
        action = verdict.action
        if action == FleetAction.HOLD:
            if self.state in FLYING or self.state == State.HOLD:
                self._hold(t, Reason(HoldCause.FLEET), latched=True, armed=s.armed or self._hold_armed)
            elif self.state in (State.WAIT_POSITION, State.STANDBY, State.ARM):
                resume_to = State.STANDBY if self.state != State.WAIT_POSITION else State.WAIT_POSITION
                self._arm_answer_until_s = t + ARM_ANSWER_S if self.state == State.ARM else -math.inf
                self._hold(t, Reason(HoldCause.FLEET_ON_GROUND), latched=True, armed=s.armed)
                self._resume_state = resume_to
        elif action == FleetAction.LAND:
            if self.state != State.DONE:
                self._go(t, State.LAND, Reason(Cause.FLEET_LAND))
        elif action == FleetAction.END:
            if self.state != State.DONE:
                self._go(t, State.DONE, Reason(Cause.FLEET_LAND_DISARMED))
        elif action == FleetAction.GO:
            self._go_given = True
            self._restored_fleet_hold = False
            if self.hold_cause == HoldCause.FLEET_ON_GROUND:
                self._go(t, State.STANDBY, Reason(Cause.GO))
        elif action == FleetAction.TAKEOVER:
            self._take_over(t, s, pos, ph)
        elif action == FleetAction.RESUME:
            self._resume(t, pos, ph, s.armed)

    def ground_hold_output(self, t: float, armed: bool) -> HoldOutput | None:
        """A fleet hold on the ground's output while its vehicle is the agent's and armed, or an interrupted
        arm request may still arm it: zero velocity in offboard/guided, nothing else requested; None otherwise."""
        if self.hold_cause != HoldCause.FLEET_ON_GROUND or self.authority != Authority.COMMAND:
            return None
        if armed or t < self._arm_answer_until_s:
            return ZERO, ModeClass.OFFBOARD, None, None
        return None

    def _take_over(self, t: float, s: VehicleStatus, pos: Vec | None, ph: PositionHealth) -> None:
        """An addressed takeover or resume hands the armed vehicle to the agent."""
        if ph != PositionHealth.OK or pos is None or self.sfield is None:
            log.warning("takeover refused: no good position or no map yet")
            return
        given_back = self.authority == Authority.HANDS_OFF
        self._set_authority(Authority.COMMAND, AuthorityCause.GIVEN_BACK if given_back else AuthorityCause.TAKEOVER)
        self._modes.last_seen = s.mode  # the mode it is in now is the baseline, not a change
        cv = self.sfield.cv_of(*pos)
        if self._home is None:
            self._home = (pos[0], pos[1], pos[2] - self.cfg.takeoff_alt_m)
        self._enter(t, State.FLOW if cv >= 0 else State.JOIN, Reason(Cause.TAKING_OVER), pos)

    def _resume(self, t: float, pos: Vec | None, ph: PositionHealth, armed: bool) -> None:
        if ph != PositionHealth.OK and self.hold_cause != HoldCause.FLEET_ON_GROUND:
            log.warning("fleet resume refused: position is %s; carried out if it is good within %.0f s", ph.value,
                        RESUME_WAIT_S)
            self._resume_wait_until_s = t + RESUME_WAIT_S
            return
        nxt = self._resume_state
        if self.hold_cause == HoldCause.GEOFENCE:
            nxt = State.RETURN
        elif self.hold_cause == HoldCause.EXIT:
            nxt = State.JOIN
        elif self.hold_cause == HoldCause.FLEET_ON_GROUND and armed and self.authority == Authority.COMMAND:
            nxt = State.ARM  # its own arm landed after the hold: on to the take-off
        elif nxt == State.FLOW and self.sfield is not None and pos is not None and (
                self.sfield.cv_of(*pos) < 0 or self.nav.rejoin_target(pos) is not None):
            nxt = State.RETURN  # the hold left it outside the map or at its wall: back in first
        self._restored_fleet_hold = False
        self._enter(t, nxt, Reason(Cause.FLEET_RESUME), pos)
