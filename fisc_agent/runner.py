"""The agent loop: link -> mission -> clamp -> transform -> setpoint, at a steady rate.

``Runner.step()`` is one tick (non-blocking); ``Runner.run()`` calls it on a monotonic-deadline
schedule (no drift: deadlines are ``start + k * period``; an overrun of more than a period
re-synchronises instead of bursting).  Other threads (the Zenoh side) talk to a running
``Runner`` only through three thread-safe methods:

- ``offer_map(cmap)``: a new map; checked now, swapped in atomically between two ticks.
- ``fleet_command(order)``: a ``FleetOrder`` (or a bare ``hold`` / ``resume`` / ``land`` / ``go``, swarm-wide),
  applied at the next tick.
- ``snapshot()``: the latest ``AgentSnapshot`` (frozen; replaced whole every tick; before the
  first tick, the agent waiting on the ground).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Callable

from fisc_agent.mavlink.adapters import Adapter, Commander, ModeClass, adapter_for
from fisc_agent.config import AgentConfig
from fisc_agent.flight.drag import DragFeedForward
from fisc_agent.flight.control import ZERO, ScalarField, Vec, check_map, clamp_velocity, max_command_speed
from fisc_agent.mavlink.link import PositionSample, VehicleLink
from fisc_agent.map.lookup import CommandField
from fisc_agent.map.codec import CommandMap, MapError, MapErrorKind
from fisc_agent.flight.mission import (FLYING, Mission, MissionCommand, MissionOutput, State,
                                VehicleStatus)
from fisc_agent.flight.mission_types import FleetOrder
from fisc_agent.flight.tick import NET_STATES, AgentSnapshot, TickRecord, failsafe_active, outside_map
from fisc_agent.flight.tracking import GNSS_FRESH_S, saturate
from fisc_agent.flight.safety_net import DuctAxis, NeighbourSource, NetAction, keep_apart
from fisc_agent.flight.readiness import health_problems
from fisc_agent.flight.state_file import AgentState, default_state_path, load_state, save_state
from fisc_agent.flight.position_gate import GateVerdict, PositionGate, PositionGateConfig
from fisc_agent.common.ratelimit import RateLimitedLog
from fisc_agent.map.separation import map_separation
from fisc_agent.map.wall import map_wall

log = logging.getLogger(__name__)

HEARTBEAT_PERIOD_S = 1.0
LOG_PERIOD_S = 5.0


class Runner:
    """Wires a ``VehicleLink``, a ``Mission`` and the control core together."""

    def __init__(self, cfg: AgentConfig, link: VehicleLink, cmap: CommandMap | None = None,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep,
                 wall_clock: Callable[[], float] = time.time,
                 on_tick: Callable[[AgentSnapshot], None] | None = None, swarm: str | None = None) -> None:
        self.cfg = cfg
        self.link = link
        self.clock, self.sleep, self.wall_clock = clock, sleep, wall_clock
        self.on_tick = on_tick
        """Called with the snapshot after every tick (the flight log); None: nothing."""
        self.transform = cfg.transform
        self.command_floors: dict[str, int] = {}
        """Newest accepted fleet-command sequence per ground key (kept in the state file)."""
        restored = None
        self.state_path = (str(default_state_path(cfg.agent_id, swarm)) if cfg.state_file == "auto"
                           else cfg.state_file)
        """The state file in use (``cfg.state_file`` with ``auto`` resolved for ``swarm``); None: none."""
        if self.state_path:
            restored = load_state(self.state_path)
            self.command_floors = dict(restored.command_floors)
            log.info("state file %s: hands-off %s, fleet hold %s, laps %d, command floors %s", self.state_path,
                     restored.hands_off, restored.fleet_hold, restored.laps, restored.command_floors or "none")
        self._saved: AgentState | None = restored
        self.mission = Mission(cfg, restored=restored)
        self.adapter: Adapter | None = None
        self.commander: Commander | None = None
        self.cmap: CommandMap | None = None
        self._lock = threading.Lock()
        self._pending_map: tuple[CommandMap, ScalarField] | None = None
        self._pending_cmds: list[MissionCommand] = []
        self._last_tick: TickRecord | None = None
        self._last_sp: Vec = ZERO
        self._last_sp_t = 0.0
        self._stream_start: float | None = None
        self.drag = DragFeedForward(cfg.drag)
        """The vehicle's drag identified in flight and fed forward (``fisc_agent.flight.drag``)."""
        self._last_hb_sent = -math.inf
        self._link_was_ok = False
        self.position_gate = PositionGate(PositionGateConfig.for_speed_clamp(cfg.max_speed_m_s))
        self.rlog = RateLimitedLog(log, LOG_PERIOD_S, clock=clock)
        """Counters of rejected position fixes (``position:<verdict>``) and their rate-limited log."""
        self._seen_sample: PositionSample | None = None
        self._good_sample: PositionSample | None = None
        self.ticks = 0
        self.overruns = 0
        self.faults = 0
        """Ticks that raised (caught: the vehicle holds, the loop goes on)."""
        self._last_tick_s: float | None = None
        self.neighbours: NeighbourSource | None = None
        """Where the safety net hears the other vehicles (``connect_runner`` sets the Zenoh
        ``NeighbourTable``); None: no neighbours known, the net does nothing."""
        if cmap is not None:
            if not self.offer_map(cmap):
                raise MapError(MapErrorKind.OTHER, "map was refused (see the log)")
            self._apply_pending()

    # ---- thread-safe API ---------------------------------------------------------------
    def offer_map(self, cmap: CommandMap) -> bool:
        """Check a map and queue it for an atomic swap at the next tick.

        Refused (False, reason logged) when it fails the agent's checks or is older
        (``map_version``) than the map in use; the same map again is accepted as a no-op.
        """
        if not self._newer_than_current(cmap):
            return cmap.sha256 == self._current_map_sha()
        try:
            field = CommandField.from_map(cmap)
            for w in check_map(field, self.cfg.mode):
                log.warning("map %s: %s", cmap.sha256[:12], w)
        except (MapError, ValueError, KeyError) as exc:
            log.error("map %s refused: %s", cmap.sha256[:12], exc)
            return False
        vmax = max_command_speed(field, self.cfg.mode)
        if vmax > self.cfg.max_speed_m_s:
            log.warning("map commands up to %.2f m/s, above max speed %.2f m/s: setpoints will be clamped",
                        vmax, self.cfg.max_speed_m_s)
        sfield = ScalarField(field, wall=map_wall(cmap.arrays), separation=map_separation(cmap.body))
        if self.cfg.mode == "kinetic" and self.cfg.wall_margin_m is not None and sfield.wall is None:
            log.warning("map %s carries no real wall (duct_wall_m): the kinetic deviations turn at the CV "
                        "staircase only, whose outer cubes lie partly outside a real duct", cmap.sha256[:12])
        with self._lock:  # re-check: another thread may have offered a newer map meanwhile
            if not self._newer_than_current(cmap):
                return cmap.sha256 == self._current_map_sha()
            self._pending_map = (cmap, sfield)
        return True

    def _current_map(self) -> CommandMap | None:
        pending = self._pending_map
        return pending[0] if pending is not None else self.cmap

    def _current_map_sha(self) -> str | None:
        current = self._current_map()
        return current.sha256 if current is not None else None

    def _newer_than_current(self, cmap: CommandMap) -> bool:
        """False for the map in use (same sha256) and for any other map not above its version (logged):
        another map of the same version is refused as the Zenoh link and docs/zenoh.md refuse it."""
        current = self._current_map()
        if current is None:
            return True
        if cmap.sha256 == current.sha256:
            return False
        if cmap.map_version <= current.map_version:
            log.warning("map %s refused: version %d is not above %d in use", cmap.sha256[:12], cmap.map_version,
                        current.map_version)
            return False
        return True

    def fleet_command(self, order: FleetOrder | MissionCommand | str) -> None:
        """Queue a fleet order (a bare command or name: swarm-wide) for the next tick; its sequence
        number becomes its ground key's floor (saved in the state file)."""
        if not isinstance(order, FleetOrder):
            order = FleetOrder(MissionCommand.parse(order))
        with self._lock:
            self._pending_cmds.append(order)
            if order.seq > self.command_floors.get(order.key_id, 0):
                self.command_floors[order.key_id] = order.seq

    def unix_time(self) -> float:
        """UNIX time [s] on the best clock the agent has: the autopilot's GNSS time when it reports one
        (SYSTEM_TIME), else the companion computer's clock (fleet-command freshness, entry windows)."""
        gps = self.link.health.unix_time_at(self.clock())
        return gps if gps is not None else self.wall_clock()

    def snapshot(self) -> AgentSnapshot:
        """The latest telemetry snapshot; before the first tick, the agent waiting on the ground
        (the mission's initial state, the map in use if any, no position, no autopilot yet)."""
        k = self._last_tick
        if k is None:
            cmap = self.cmap
            return AgentSnapshot(
                time_s=self.clock(), wall_time_s=self.wall_clock(), agent_id=self.cfg.agent_id,
                state=self.mission.state.value, reason=self.mission.reason, position_map_m=None,
                velocity_map_m_s=None, setpoint_map_m_s=None, cv_id=-1, map_sha256=cmap.sha256 if cmap else None,
                map_version=cmap.map_version if cmap else None, link_ok=False, heartbeat_age_s=math.inf,
                position_age_s=math.inf, autopilot=None, armed=False, mode=ModeClass.UNKNOWN.value, laps=0,
                failsafe=False, outside_map=False, authority=self.mission.authority.value)
        cmap, state, reason = k.cmap, k.out.state, k.out.reason
        return AgentSnapshot(
            time_s=k.now_s, wall_time_s=k.wall_time_s, agent_id=self.cfg.agent_id, state=state.value,
            reason=reason, position_map_m=k.position_map_m, velocity_map_m_s=k.velocity_map_m_s,
            setpoint_map_m_s=k.setpoint_map_m_s, cv_id=k.out.cv_id, map_sha256=cmap.sha256 if cmap else None,
            map_version=cmap.map_version if cmap else None, link_ok=k.link_ok, heartbeat_age_s=k.heartbeat_age_s,
            position_age_s=k.position_age_s, autopilot=k.autopilot, armed=k.armed, mode=k.mode.value,
            laps=k.laps, failsafe=failsafe_active(state, reason),
            outside_map=outside_map(state, reason, k.out.cv_id, k.position_map_m is not None and cmap is not None),
            parcel_map_m=k.parcel_map_m, authority=self.mission.authority.value, battery_pct=k.health.battery_pct,
            landed=k.health.landed.value, health_problems=health_problems(k.health, self.cfg.min_battery_pct),
            nearest_neighbour_m=k.net.nearest_m if k.net is not None else math.inf,
            net_ids=k.net.acting if k.net is not None else (), gnss_velocity_map_m_s=k.gnss_velocity_map_m_s)

    # ---- the tick ------------------------------------------------------------------------
    def _apply_pending(self) -> list[FleetOrder]:
        with self._lock:
            pending, self._pending_map = self._pending_map, None
            cmds, self._pending_cmds = self._pending_cmds, []
        if pending is not None:
            old = self.cmap
            self.cmap = pending[0]
            self.mission.set_map(pending[1])
            log.info("map in use: version %d sha256 %s (%d CVs)%s", self.cmap.map_version, self.cmap.sha256[:12],
                     self.cmap.n_cv, f", replacing {old.sha256[:12]}" if old is not None else "")
        return cmds

    def _ensure_adapter(self) -> None:
        if self.adapter is not None:
            return
        seen = self.link.autopilot
        if self.cfg.autopilot != "auto":
            if seen is not None and seen != self.cfg.autopilot:
                log.warning("--autopilot %s given but the HEARTBEAT says %s; using %s", self.cfg.autopilot, seen,
                            self.cfg.autopilot)
            if self.link.last_heartbeat_t is None:
                return
            name = self.cfg.autopilot
        elif seen is None:
            if self.link.last_heartbeat_t is not None and self.ticks % 100 == 0:
                log.warning("autopilot is neither PX4 nor ArduPilot; pass --autopilot")
            return
        else:
            name = seen
        self.adapter = adapter_for(name)
        self.link.use_adapter(self.adapter)
        self.commander = Commander(self.adapter, self.link, self.cfg.command_retry_s)
        log.info("using the %s adapter", name)

    def _gated(self, sample: PositionSample | None) -> PositionSample | None:
        """The newest fix that passed ``position_gate`` (a rejected fix leaves the previous one,
        which then ages: the mission's stale-position hold applies).  ``MavlinkLink`` gates
        every fix it receives as well (so that bogus fixes interleaved with good ones cannot
        hide them); this gate covers every backend."""
        if sample is None or sample is self._seen_sample:
            return self._good_sample
        self._seen_sample = sample
        verdict = self.position_gate.check(sample.t_s, sample.pos_ned_m, sample.vel_ned_m_s)
        if verdict.accepted:
            if verdict == GateVerdict.REANCHORED:
                log.warning("position: a consistent track %.1f s long far from the last accepted fix is taken as "
                            "the new position (NED %s)", self.position_gate.cfg.reanchor_after_s,
                            _fmt(sample.pos_ned_m))
            self._good_sample = sample
        else:
            self.rlog.event(f"position:{verdict.value}", logging.WARNING, "position fix rejected (%s): NED %s, "
                            "velocity %s", verdict.value, _fmt(sample.pos_ned_m), _fmt(sample.vel_ned_m_s))
        return self._good_sample

    def step(self) -> MissionOutput:
        """One control tick.  A tick that raises (a flight-log write, a link error, a bug) is caught:
        logged, counted in ``faults``, and the mission holds (``HoldCause.AGENT_FAULT``, latched)."""
        try:
            out = self._tick()
        except Exception as exc:  # noqa: BLE001 - a flying agent must not die: hold and keep the link
            self.faults += 1
            if self.rlog.event("tick:fault", logging.ERROR, "control tick failed (%s: %s); holding the vehicle",
                               type(exc).__name__, exc):
                log.error("the failed tick's traceback", exc_info=True)
            out = self.mission.fault(self.clock(), f"{type(exc).__name__}: {exc}")
            self._safe_hold()
        self._save_state()
        return out

    def _safe_hold(self) -> None:
        """After a failed tick: zero-velocity setpoint while the agent flies (best effort)."""
        if self.mission.state == State.HOLD and not self.mission.hands_off and self.link.armed:
            try:
                self.link.send_velocity_ned(0.0, 0.0, 0.0)
            except Exception as exc:  # noqa: BLE001 - the link itself may be what failed
                self.rlog.event("tick:hold-send", logging.ERROR, "zero setpoint not sent: %s", exc)

    def _observe_drag(self, now: float, sample: PositionSample | None) -> None:
        """Feed the drag's identification while the vehicle flies: the thrust's horizontal acceleration (its
        attitude) and the estimate's horizontal velocity (in time with the attitude: the GNSS receiver's lagged
        it by up to 0.5 m/s in PX4 SIH's turns and read a drag of 0.5-0.8 /s for SIH's 1.0 /s; the estimate's
        slowly varying bias goes mostly into the fit's constant)."""
        thrust, est = self.link.latest_thrust_accel(), self.drag.estimator
        if (thrust is None or sample is None or now - thrust.t_s > est.cfg.fresh_s
                or now - sample.t_s > self.cfg.stale_timeout_s or not self.link.armed
                or self.mission.state not in FLYING):
            est.gap()
        else:
            est.observe(now, sample.vel_ned_m_s[:2], thrust.acc_ne_m_s2)

    def _save_state(self) -> None:
        """Write the state file when what it holds changed."""
        if not self.state_path:
            return
        m, saved = self.mission, self._saved
        hands_off, fleet_hold, laps = m.hands_off, m.fleet_held(), m.laps  # as ``Mission.saved_state`` gives them
        if (saved is not None and hands_off == saved.hands_off and fleet_hold == saved.fleet_hold
                and laps == saved.laps and self.command_floors == saved.command_floors):
            return  # unchanged (compared field by field: no AgentState, no copy of the floors every tick)
        state = AgentState(hands_off, fleet_hold, laps, dict(self.command_floors))
        if state == saved:
            return
        try:
            save_state(self.state_path, state)
            self._saved = state
        except OSError as exc:
            self.rlog.event("state-file", logging.ERROR, "state file %s not written: %s", self.state_path, exc)

    def _tick(self) -> MissionOutput:
        now = self.clock()
        if self._last_tick_s is not None and now - self._last_tick_s > self.cfg.link_timeout_s:
            # the agent itself stalled (SIGSTOP, swap, a hung thread): what queued up meanwhile is an old
            # view of the vehicle, and read now it would look current (an autopilot failsafe's Land hidden
            # behind old OFFBOARD heartbeats).  Drop it: the link reads as lost until a fresh HEARTBEAT.
            log.warning("control loop stalled for %.1f s: discarding the MAVLink backlog, holding until the "
                        "autopilot is heard afresh", now - self._last_tick_s)
            self.link.discard_backlog()
        self._last_tick_s = now
        cmds = self._apply_pending()
        for name in cmds:
            self.mission.command(name)
        link = self.link
        link.poll()
        self._ensure_adapter()
        for result in link.pop_results():
            if self.commander is not None:
                self.commander.on_result(result)
        hb_age = self._heartbeat_age_s(now)
        mode_t = link.mode_t_s
        mode_age = max(0.0, now - mode_t) if mode_t is not None else math.inf
        mode = link.mode if self.adapter is not None else ModeClass.UNKNOWN
        sample = self._gated(link.latest_position())
        tf = self.transform
        if sample is not None:
            pos: Vec | None = tf.ned_to_map_xyz(*sample.pos_ned_m)
            vel: Vec | None = tf.vel_ned_to_map_xyz(*sample.vel_ned_m_s)
            pos_age = max(0.0, now - sample.t_s)
        else:
            pos = vel = None
            pos_age = math.inf
        gnss = link.latest_gnss_velocity()
        gnss_xy: tuple[float, float] | None = None
        if gnss is not None and now - gnss.t_s <= GNSS_FRESH_S:
            gx, gy, _ = tf.vel_ned_to_map_xyz(gnss.vel_ne_m_s[0], gnss.vel_ne_m_s[1], 0.0)
            gnss_xy = (gx, gy)
        self._observe_drag(now, sample)
        link_ok = hb_age <= self.cfg.link_timeout_s
        if link_ok != self._link_was_ok:
            (log.info if link_ok else log.warning)("autopilot link %s", "up" if link_ok else "LOST")
            self._link_was_ok = link_ok
        health = link.health
        integrity = link.integrity
        gps_unix = health.unix_time_at(now)
        status = VehicleStatus(now, pos, vel, pos_age, hb_age, self.adapter.name if self.adapter else None,
                               link.armed, mode, gps_unix if gps_unix is not None else self.wall_clock(),
                               None if sample is None else sample.autopilot_t_s, health,
                               integrity.ok, "" if integrity.ok else f"{integrity.reason.value}: {integrity.detail}",
                               gnss_xy)
        out = self.mission.step(status)
        net = self._safety_net(out, pos, pos_age)

        sp: Vec | None = None
        # stopped within this tick (SIGSTOP) past the link timeout: a setpoint sent now would end a failsafe's Land
        # (PX4 falls back to OFFBOARD when setpoints come back); the next tick finds the stall
        stalled_s = self.clock() - now
        stopped = stalled_s > self.cfg.link_timeout_s
        if stopped:
            log.warning("control tick stopped for %.1f s mid-way: its setpoint and commands are not sent", stalled_s)
        elif out.velocity_m_s is not None:
            if self._stream_start is None:
                self._stream_start = now
                v_prev = vel if (vel is not None and pos_age <= self.cfg.stale_timeout_s) else ZERO
                dt = self.cfg.period_s
            else:
                v_prev = self._last_sp
                dt = min(now - self._last_sp_t, 2.0 * self.cfg.period_s)
            wanted = net.velocity_m_s if net is not None else out.velocity_m_s
            sp = clamp_velocity(wanted, v_prev, dt, self.cfg.max_speed_m_s, self.cfg.max_accel_m_s2)
            ned = tf.vel_map_to_ned_xyz(*sp)
            c, switched_on = self.drag.for_setpoint(ned[:2], self.adapter.name if self.adapter else None)
            if switched_on:  # the loop with the feed-forward lags less: identify its response again
                log.info("drag identified in flight: %.2f /s (%d windows); fed forward with every setpoint from now "
                         "on", c, self.drag.estimator.windows)
                self.mission.nav.identify_again()
            if c is None:
                link.send_velocity_ned(*ned)
            else:  # the thrust the drag at this velocity takes, fed forward (PX4 adds it to its PID's output)
                an, ae = saturate((c * ned[0], c * ned[1], 0.0), self.cfg.max_accel_m_s2)[:2]
                link.send_velocity_accel_ned(ned[0], ned[1], ned[2], an, ae, 0.0)
            self._last_sp, self._last_sp_t = sp, now
            if vel is not None and pos_age <= self.cfg.stale_timeout_s and mode == out.want_mode:
                # only while the autopilot flies our setpoints: after a fleet resume PX4 streams them
                # for ~1.5 s in its hold mode before it takes OFFBOARD, which read as a 1.27 s lag
                self.mission.observe_response(now, sp, vel)
        else:
            self._stream_start = None
        stream_s = now - self._stream_start if self._stream_start is not None else 0.0
        if self.commander is not None and link_ok and not stopped:
            self.commander.reconcile(now, out.want_mode, out.want_armed, out.takeoff_alt_m, link.armed, mode,
                                     stream_s, mode_age)
        if now - self._last_hb_sent >= HEARTBEAT_PERIOD_S:
            link.send_heartbeat()
            self._last_hb_sent = now
        self._last_tick = TickRecord(
            now_s=now, wall_time_s=self.wall_clock(), out=out, position_map_m=pos, velocity_map_m_s=vel,
            setpoint_map_m_s=sp, cmap=self.cmap, link_ok=link_ok, heartbeat_age_s=hb_age, position_age_s=pos_age,
            autopilot=self.adapter.name if self.adapter else None, armed=link.armed, mode=mode,
            laps=self.mission.laps, parcel_map_m=self.mission.tracker.parcel_m if out.state == State.FLOW else None,
            health=health, net=net, gnss_velocity_map_m_s=gnss_xy)
        self.ticks += 1
        if self.on_tick is not None:
            self.on_tick(self.snapshot())
        return out

    def _safety_net(self, out: MissionOutput, pos: Vec | None, pos_age_s: float) -> NetAction | None:
        """The safety net on this tick's command (``fisc_agent.flight.safety_net``): only while the
        agent flies its own velocities in the air (``NET_STATES``) from a fresh position, with a map
        (its d_min and its duct) and neighbours to hear; None otherwise.  Its horizon adapts to the
        vehicle's lag as the agent knows it (the look-ahead in use)."""
        net_cfg, sfield = self.cfg.safety_net, self.mission.sfield
        if (net_cfg is None or self.neighbours is None or sfield is None or out.velocity_m_s is None
                or out.state not in NET_STATES or pos is None or pos_age_s > self.cfg.stale_timeout_s):
            return None
        geom = self.mission.geom
        duct = DuctAxis(geom.x_inlet_m, geom.x_outlet_m, geom.inlet_center_yz_m) if geom is not None else None
        net = keep_apart(pos, out.velocity_m_s, self.cfg.agent_id, self.neighbours.reports(self.cfg.agent_id),
                         sfield.separation.d_min_m, net_cfg, self.mission.nav.lookahead_s(), duct)
        if net.active:
            self.rlog.event("net:active", logging.INFO, "safety net: d_min %.2f m, acting on agent(s) %s "
                            "(nearest %.2f m); command %s -> %s", sfield.separation.d_min_m,
                            ",".join(map(str, net.acting)), net.nearest_m, _fmt(out.velocity_m_s),
                            _fmt(net.velocity_m_s))
        return net

    # ---- loop and shutdown ---------------------------------------------------------------
    def run(self, stop: threading.Event | None = None, until_done: bool = True,
            max_duration_s: float | None = None) -> State:
        """Tick at ``cfg.rate_hz`` until ``stop`` is set, the mission is DONE (``until_done``),
        or ``max_duration_s`` passed.  Returns the final mission state."""
        stop = stop or threading.Event()
        period = self.cfg.period_s
        start = next_t = self.clock()
        while not stop.is_set():
            self.step()
            if until_done and self.mission.state == State.DONE:
                break
            now = self.clock()
            if max_duration_s is not None and now - start >= max_duration_s:
                break
            next_t += period
            if next_t < now - period:
                self.overruns += 1
                log.debug("control loop overrun (%.1f ms late); re-synchronising", (now - next_t) * 1e3)
                next_t = now
            elif next_t > now:
                try:
                    self.sleep(next_t - now)
                except (OSError, ValueError) as exc:  # a broken clock or sleep must not end the loop in flight
                    self.rlog.event("loop:sleep", logging.ERROR, "control loop sleep failed (%s); ticking on", exc)
        return self.mission.state

    def _heartbeat_age_s(self, now: float) -> float:
        """Age of the last HEARTBEAT at ``now`` (>= 0: one got in this tick's poll is newer), inf before one."""
        t = self.link.last_heartbeat_t
        return max(0.0, now - t) if t is not None else math.inf

    def shutdown(self, settle_s: float = 0.3) -> None:
        """Leave the vehicle safe: zero-velocity setpoints, then the autopilot's hold mode.

        Called on SIGINT/SIGTERM and at the end of ``run``.  Only a vehicle heard within ``link_timeout_s``
        flying the agent's setpoints (OFFBOARD / GUIDED) is touched: landing, disarmed, under pilot control,
        holding or unheard (a failsafe may be landing it: a setpoint would end that Land), it is left alone.
        """
        link = self.link
        try:
            link.poll()
            state = self.mission.state
            heard = self._heartbeat_age_s(self.clock()) <= self.cfg.link_timeout_s
            flying = (heard and link.armed and link.mode == ModeClass.OFFBOARD
                      and (state in FLYING or (state == State.HOLD and not self.mission.hands_off)))
            if flying and self.adapter is not None:
                log.info("shutdown: zero-velocity hold, then the autopilot's hold mode")
                t_end = self.clock() + settle_s
                while True:
                    link.send_velocity_ned(0.0, 0.0, 0.0)
                    link.hold()
                    link.poll()
                    if link.mode == ModeClass.HOLD or self.clock() >= t_end:
                        break
                    self.sleep(0.05)
                if link.mode != ModeClass.HOLD:
                    log.warning("shutdown: hold mode not confirmed; the autopilot's offboard-loss failsafe applies")
        finally:
            link.close()


def _fmt(v) -> str:
    return "(" + ", ".join(f"{float(x):.2f}" for x in v) + ")"
