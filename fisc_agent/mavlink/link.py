"""The MAVLink link (pymavlink): ``MavlinkLink`` implements the runner's ``interfaces.VehicleLink``
(``mavsdk_backend.MavsdkLink`` is the alternative).  It takes commands at the level of intent (``arm``,
``set_mode``, ``takeoff``, ``hold``, ``land``), encodes them as COMMAND_LONGs through the autopilot's
adapter (``use_adapter``), turns COMMAND_ACKs into ``CommandResult``s and reports the mode as a
``ModeClass``.  Non-blocking: ``poll()`` drains whatever arrived; the control loop never waits on it.

Positions: LOCAL_POSITION_NED (EKF local frame), or, with a ``GeodeticAnchor``, GLOBAL_POSITION_INT
converted to NED relative to the anchor; the receiver's own velocity from GPS_RAW_INT (``gnss``).  Times
are local monotonic receive times (age = now - receive time): a delayed or frozen stream reads as stale.

Hostile or broken input (``fisc_agent.mavlink.framing``): on UDP the link owns its socket and parses each
datagram on its own (a partial or garbage frame is dropped with its datagram and cannot desynchronise
the parser), and it sends only to the autopilot's address (``udpout``: the configured one; ``udpin``: the
address the autopilot's HEARTBEATs come from; nothing before that), never to every sender.  On every
transport only the autopilot's own system, component (and UDP address) change its armed state, mode and
type or deliver positions and acks.  Every position fix passes ``fisc_agent.flight.position_gate``
(finite, reachable from the last accepted fix) before it becomes ``latest_position``.  Refusals are
counted in ``rlog`` and logged at most once per 5 s per kind.

One vehicle per link: ``target_system`` (``--target-system``) names the only system id the link listens
to; without it the first PX4/ArduPilot heard is pinned for the life of the link (``framing.AutopilotTracker``).
Messages of other systems are ignored and counted (``other_system_messages``).  A COMMAND_ACK is used only
when it is addressed to us (its target_system/target_component are our source ids) and answers a command
we sent in the last ``ACK_WINDOW_S``.  Datagrams are decoded by ``fast_codec.fast_decoder``.

Health and integrity: ``health`` (``VehicleHealth``, from ``health_reader.HealthReader``) and ``integrity``
(``IntegrityVerdict`` of ``fisc_agent.flight.integrity.IntegrityMonitor`` over the gated fixes, the ODOMETRY
reset counter and the estimator flags).  The link asks for the streams these need
(``health_reader.stream_requests``) on locking on and again after an autopilot reboot.

The link cannot die: an ``OSError`` of the socket, serial port or TCP connection never leaves ``poll`` or
a send; it is counted (``errors``, ``last_error``), logged at most every 5 s, and the transport is
reopened on a later poll (every ``REOPEN_PERIOD_S``).
"""

from __future__ import annotations

import logging
import os
import time
from typing import Callable

from pymavlink.dialects.v20.ardupilotmega import (MAV_AUTOPILOT_INVALID, MAV_CMD_SET_MESSAGE_INTERVAL,
                                                  MAV_FRAME_LOCAL_NED, MAV_RESULT_ACCEPTED, MAV_STATE_ACTIVE,
                                                  MAV_TYPE_ONBOARD_CONTROLLER)

from fisc_agent.mavlink.adapters import (Adapter, CommandLong, CommandResult, ModeClass, arm_command,
                                         autopilot_from_heartbeat, command_result, is_armed)
from fisc_agent.mavlink.endpoints import Endpoint, parse_endpoint
from fisc_agent.mavlink.fast_codec import fast_decoder
from fisc_agent.mavlink.gnss import gnss_velocity
from fisc_agent.mavlink.interfaces import (GnssVelocity, PositionSample, PositionSource, SetpointSink, ThrustAccel,
                                           VehicleLink)
from fisc_agent.flight.drag import thrust_accel_ne
from fisc_agent.flight.frames import GeodeticAnchor
from fisc_agent.mavlink.framing import NON_VEHICLE_TYPES, AutopilotTracker, HeartbeatVerdict, parse_datagram
from fisc_agent.mavlink.health_reader import HealthReader, stream_requests
from fisc_agent.mavlink.setpoint_codec import TYPEMASK_VELOCITY_ACCEL, TYPEMASK_VELOCITY_ONLY, send_velocity_setpoint
from fisc_agent.mavlink.transport import MavutilStreamTransport, TcpClientTransport, UdpTransport
from fisc_agent.flight.health import VehicleHealth
from fisc_agent.flight.integrity import IntegrityConfig, IntegrityMonitor, IntegrityVerdict
from fisc_agent.flight.position_gate import PositionGate, PositionGateConfig
from fisc_agent.common.ratelimit import RateLimitedLog

__all__ = ["MavlinkLink", "PositionSample", "PositionSource", "SetpointSink", "VehicleLink", "UdpTransport",
           "TYPEMASK_VELOCITY_ONLY", "TYPEMASK_VELOCITY_ACCEL"]

log = logging.getLogger(__name__)

MAX_MESSAGES_PER_POLL = 2000
POLL_BUDGET_S = 0.01
"""At most this long per ``poll`` (a flood of datagrams must not stretch a control tick)."""
RELOCK_AFTER_S = 3.0
"""A disarmed autopilot silent this long may be replaced by another vehicle (``AutopilotTracker``)."""
MAX_ACKS_KEPT = 32
LOG_PERIOD_S = 5.0
REOPEN_PERIOD_S = 1.0
"""A failed transport is reopened at most this often [s]."""
ACK_WINDOW_S = 30.0
"""A COMMAND_ACK answers a command of ours only if we sent that command id within this long [s]."""


def _import_mavutil():
    # pymavlink picks MAVLink 1 or 2 from this variable at import; PX4 and ArduPilot speak 2.
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    if getattr(mavutil, "mavlink", None) is None or getattr(mavutil.mavlink, "WIRE_PROTOCOL_VERSION", "2.0") != "2.0":
        mavutil.set_dialect("ardupilotmega")
    return mavutil


MAX_BACKLOG_DISCARD = 100_000
"""At most this many queued datagrams are dropped after a stall (a socket buffer holds far fewer)."""


class MavlinkLink:
    """pymavlink connection to one autopilot: vehicle state, health, positions, setpoints, commands."""

    def __init__(self, endpoint: Endpoint | str, source_system: int | None = None, source_component: int = 191,
                 anchor: GeodeticAnchor | None = None, position_rate_hz: float = 50.0,
                 clock: Callable[[], float] = time.monotonic,
                 position_gate: PositionGateConfig | None = None, target_system: int | None = None,
                 integrity: IntegrityConfig | None = None) -> None:
        """``target_system``: the only MAVLink system id to fly (None: the first PX4/ArduPilot heard,
        then pinned); ``integrity``: thresholds of the position integrity monitor."""
        from pymavlink.dialects.v20 import ardupilotmega as mavlink2

        self.endpoint = parse_endpoint(endpoint) if isinstance(endpoint, str) else endpoint
        self.anchor = anchor
        self.clock = clock
        self.position_rate_hz = position_rate_hz
        self._fixed_source = source_system
        self.rlog = RateLimitedLog(log, LOG_PERIOD_S, clock=clock)
        """Counters of refused MAVLink input (``mavlink:<kind>``) and their rate-limited log."""
        self.bad_bytes = 0
        """Received bytes that were not part of a valid frame."""
        self.tracker = AutopilotTracker(RELOCK_AFTER_S, target_system=target_system)
        self.position_gate = PositionGate(position_gate)
        self._integrity_cfg = integrity
        self.integrity_monitor = IntegrityMonitor(integrity)
        """Judges the gated fixes, reset counter and estimator flags (``integrity``)."""
        self.health_reader = self._new_health_reader()
        self.udp: UdpTransport | None = None
        if self.endpoint.kind in ("udpin", "udpout"):
            self.udp = UdpTransport(self.endpoint)
            self.transport = self.udp
        elif self.endpoint.kind == "tcp":
            self.transport = TcpClientTransport(self.endpoint)
        else:  # serial, tcpin: pymavlink's port handling, our parser
            self.transport = MavutilStreamTransport(self.endpoint, _import_mavutil())
        self.mav = mavlink2.MAVLink(self.transport, srcSystem=source_system or 255, srcComponent=source_component)
        self._decoder = mavlink2.MAVLink(None)
        self._decoder.robust_parsing, self._decode = True, fast_decoder(self._decoder)
        self.autopilot: str | None = None
        self.adapter: Adapter | None = None
        """Encodes intents and decodes modes (``use_adapter``)."""
        self.target_system: int | None = None
        """System id of the autopilot the link is locked on (None before the first HEARTBEAT)."""
        self.target_component: int = 1
        self.armed, self.base_mode, self.custom_mode = False, 0, 0
        self.last_heartbeat_t: float | None = None
        self.heartbeats = 0
        self._position: PositionSample | None = None
        self._gnss: GnssVelocity | None = None
        self._thrust: ThrustAccel | None = None
        self._acks: list[tuple[int, int]] = []
        self._sent_commands: dict[int, float] = {}
        self.status_texts: list[str] = []
        self.setpoints_sent = 0
        self.other_system_messages = 0
        """Messages from other MAVLink system ids (another vehicle, a GCS), ignored."""
        self.stream_requests_refused = 0
        """SET_MESSAGE_INTERVAL requests the autopilot refused (ArduPilot: ESTIMATOR_STATUS, ODOMETRY; PX4:
        EKF_STATUS_REPORT: expected)."""
        self._poll_errors, self._last_reopen_s = 0, None

    def _new_health_reader(self) -> HealthReader:
        return HealthReader(None if self.anchor is None else self.anchor.geodetic_to_ned)

    # ---- health, integrity, errors --------------------------------------------------------
    @property
    def health(self) -> VehicleHealth:
        """The autopilot's own view of its health (``VehicleHealth``; unknown where it reports none)."""
        return self.health_reader.health

    @property
    def integrity(self) -> IntegrityVerdict:
        """Whether the position may be flown on: ``ok``, or the disruption's typed ``reason`` and since when."""
        return self.integrity_monitor.verdict

    mode_t_s = property(lambda self: self.last_heartbeat_t, doc="When the newest HEARTBEAT, which carries the mode, "
                        "arrived [s, ``clock``]; None: never (``VehicleLink.mode_t_s``).")

    @property
    def errors(self) -> int:
        """Transport errors so far (receive, send, reopen: a serial re-enumeration, a TCP reset...)."""
        return self.transport.errors + self._poll_errors

    @property
    def send_drops(self) -> int:
        """Sends dropped because the peer could not be reached right then (not a transport fault)."""
        return self.transport.send_drops

    @property
    def last_error(self) -> str:
        """The newest transport error, in words ("" if none)."""
        return self.transport.last_error

    @property
    def transport_ok(self) -> bool:
        """False while the transport has failed and is not reopened yet."""
        return not self.transport.failed

    # ---- receive -------------------------------------------------------------------------
    def poll(self) -> int:
        """Drain received messages (non-blocking, at most ``POLL_BUDGET_S``); returns how many
        were handled.  Never raises on a transport error (see ``errors``)."""
        errors_before = self.errors
        try:
            n = self._drain()
        except OSError as exc:  # belt and braces: the transports catch their own
            self._poll_errors += 1
            self.transport.failed, self.transport.last_error = True, f"poll: {exc}"
            n = 0
        if self.errors != errors_before:
            self.rlog.event("mavlink:transport_error", logging.WARNING, "MAVLink %s: %s (%d errors so far); "
                            "reopening", self.endpoint, self.last_error, self.errors)
        if self.transport.failed:
            now = self.clock()
            if self._last_reopen_s is None or now - self._last_reopen_s >= REOPEN_PERIOD_S:
                self._last_reopen_s = now
                if self.transport.reopen():
                    log.warning("MAVLink %s reopened after: %s", self.endpoint, self.last_error)
        return n

    def _drain(self) -> int:
        n = 0
        t_end = time.monotonic() + POLL_BUDGET_S
        while n < MAX_MESSAGES_PER_POLL and time.monotonic() < t_end:
            if self.udp is not None:
                got = self.udp.recv()
                if got is None:
                    break
                data, addr = got
                scan = parse_datagram(data, self._decode)
                if scan.bad_bytes:
                    self.bad_bytes += scan.bad_bytes
                    self.rlog.event("mavlink:bad_bytes", logging.WARNING, "MAVLink: %d bad bytes in a %d-byte datagram "
                                    "from %s:%d dropped (garbage, partial or corrupted frames)", scan.bad_bytes,
                                    len(data), *addr)
                for msg in scan.messages:
                    n += 1
                    self._handle_safely(msg, addr)
                continue
            data = self.transport.recv()
            if data is None:
                break
            for msg in self._decoder.parse_buffer(data) or ():
                n += 1
                if msg.get_type() == "BAD_DATA":
                    self.bad_bytes += len(msg.get_msgbuf())
                    self.rlog.event("mavlink:bad_bytes", logging.WARNING, "MAVLink: bad data dropped (%s)",
                                    getattr(msg, "reason", "?"))
                    continue
                self._handle_safely(msg, None)
        return n

    def _handle_safely(self, msg, addr) -> None:
        try:
            self._handle(msg, addr)
        except Exception as exc:  # a message we cannot digest must not stop the control loop
            self.rlog.event("mavlink:handler_error", logging.ERROR, "MAVLink: %s from system %d could not be "
                            "handled: %r", msg.get_type(), msg.get_srcSystem(), exc)

    def _handle(self, msg, addr=None) -> None:
        mtype = msg.get_type()
        src = msg.get_srcSystem()
        if src == 0:  # no sender has system id 0 (the broadcast address); PX4 SITL emits a few such frames
            self.rlog.event("mavlink:system_0", logging.DEBUG, "MAVLink: %s from system id 0 ignored", mtype)
            return
        pinned = self.tracker.pinned_system
        if pinned is not None and src != pinned:
            if mtype == "HEARTBEAT" and (msg.type in NON_VEHICLE_TYPES or msg.autopilot == MAV_AUTOPILOT_INVALID):
                return  # a ground station or companion: normal on a shared link
            self.other_system_messages += 1
            vehicle = mtype == "HEARTBEAT"
            self.rlog.event("mavlink:other_system", logging.WARNING if vehicle else logging.INFO,
                            "MAVLink: %s from system %d ignored (this agent flies system %d only)%s", mtype, src,
                            pinned, ": another vehicle on this link" if vehicle else "")
            return
        if mtype == "HEARTBEAT":
            self._on_heartbeat(msg, addr)
            return
        if not self.tracker.is_autopilot(src, msg.get_srcComponent(), addr):
            self.rlog.event("mavlink:foreign_message", logging.DEBUG, "MAVLink: %s from system %d component %d "
                            "(not the autopilot) ignored", mtype, src, msg.get_srcComponent())
            return
        if mtype == "LOCAL_POSITION_NED":
            if self.anchor is None:
                self._offer_position(PositionSample(self.clock(), (msg.x, msg.y, msg.z), (msg.vx, msg.vy, msg.vz),
                                                    msg.time_boot_ms * 1e-3))
        elif mtype == "GLOBAL_POSITION_INT":
            if self.anchor is not None:
                ned = self.anchor.geodetic_to_ned(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
                self._offer_position(PositionSample(self.clock(), ned, (msg.vx * 0.01, msg.vy * 0.01, msg.vz * 0.01),
                                                    msg.time_boot_ms * 1e-3))
        elif mtype == "GPS_RAW_INT":
            self._gnss = gnss_velocity(msg, self.clock()) or self._gnss
        elif mtype == "COMMAND_ACK":
            self._on_ack(msg)
        elif mtype == "ODOMETRY":  # PX4: its attitude (the drag's identification), then its reset counter
            acc = thrust_accel_ne(tuple(msg.q))
            if acc is not None:
                self._thrust = ThrustAccel(self.clock(), acc)
            self._on_health(msg)
        elif mtype == "STATUSTEXT":
            text = str(msg.text).rstrip("\x00")
            self.status_texts.append(text)
            del self.status_texts[:-50]
            log.info("autopilot: %s", text)
        else:
            self._on_health(msg)

    def _on_ack(self, msg) -> None:
        command, result = int(msg.command), int(msg.result)
        ours = (int(msg.target_system), int(msg.target_component)) == (self.mav.srcSystem, self.mav.srcComponent)
        sent = self._sent_commands.get(command)
        if not ours or sent is None or self.clock() - sent > ACK_WINDOW_S:
            self.rlog.event("mavlink:unmatched_ack", logging.WARNING, "MAVLink: COMMAND_ACK of command %d to system "
                            "%d component %d ignored (%s)", command, msg.target_system, msg.target_component,
                            "not addressed to us" if not ours else "no such command sent")
            return
        if command == MAV_CMD_SET_MESSAGE_INTERVAL:  # stream requests are the link's own business
            if result != MAV_RESULT_ACCEPTED:
                self.stream_requests_refused += 1
            return
        self._acks.append((command, result))
        del self._acks[:-MAX_ACKS_KEPT]  # bounded even if nobody pops them

    def _on_health(self, msg) -> None:
        now = self.clock()
        update = self.health_reader.on_message(msg, now)
        if update.rebooted:
            log.warning("autopilot system %s rebooted (its boot time went backwards, %d reboots seen): streams "
                        "requested again", self.target_system, self.health.autopilot_reboots)
            self._request_streams()
            self.integrity_monitor.on_reboot(now)
        if update.reset_steps:
            self.integrity_monitor.on_reset(now, update.reset_steps)
        if update.estimator is not None:
            self.integrity_monitor.on_estimator(now, *update.estimator)
        self._log_integrity()

    def _log_integrity(self) -> None:
        for event in self.integrity_monitor.pop_events():
            v = event.verdict
            if v.ok:
                log.warning("position integrity OK again: re-anchored at NED %s after a consistent track of %.1f s",
                            tuple(round(float(x), 2) for x in event.reanchored_ned_m or ()),
                            self.integrity_monitor.cfg.consistent_s)
            else:
                log.warning("position integrity DISRUPTED (%s): %s", v.reason.value, v.detail)

    def _offer_position(self, sample: PositionSample) -> None:
        verdict = self.position_gate.check(sample.t_s, sample.pos_ned_m, sample.vel_ned_m_s)
        if verdict.accepted:
            self._position = sample
            self.integrity_monitor.on_fix(sample.t_s, sample.pos_ned_m, sample.vel_ned_m_s, sample.autopilot_t_s)
            self._log_integrity()
        else:
            self.rlog.event(f"position:{verdict.value}", logging.WARNING, "position fix rejected (%s): NED %s",
                            verdict.value, tuple(round(float(v), 2) for v in sample.pos_ned_m))

    def _on_heartbeat(self, msg, addr=None) -> None:
        src, comp = msg.get_srcSystem(), msg.get_srcComponent()
        pinned_before = self.tracker.pinned_system
        verdict = self.tracker.on_heartbeat(src, comp, addr, msg.type, msg.autopilot, is_armed(msg.base_mode),
                                            self.clock())
        if verdict == HeartbeatVerdict.NOT_A_VEHICLE:
            return
        if verdict == HeartbeatVerdict.FOREIGN:
            self.rlog.event("mavlink:foreign_heartbeat", logging.WARNING, "MAVLink: HEARTBEAT from system %d "
                            "component %d (type %d, autopilot %d, base_mode %d) is not the autopilot's (system %d "
                            "component %d): ignored", src, comp, msg.type, msg.autopilot, msg.base_mode,
                            self.target_system, self.target_component)
            return
        if verdict == HeartbeatVerdict.LOCKED:
            relock = self.target_system is not None
            self.target_system, self.target_component = src, comp
            self.autopilot = autopilot_from_heartbeat(msg.autopilot)
            self._position = None  # never mix fixes of two vehicles (or of two boots)
            self.position_gate = PositionGate(self.position_gate.cfg)
            self.integrity_monitor = IntegrityMonitor(self._integrity_cfg)
            self.health_reader = self._new_health_reader()
            self.armed, self.last_heartbeat_t = False, None
            (log.warning if relock else log.info)(
                "autopilot %s: system %d component %d (%s)%s", "changed to" if relock else "found", src, comp,
                self.autopilot or f"MAV_AUTOPILOT {msg.autopilot}",
                f" at {addr[0]}:{addr[1]}" if isinstance(addr, tuple) else "")
            if self.udp is not None and self.udp.listening:
                self.udp.peer = addr  # replies go to the autopilot only
            if self._fixed_source is None:
                self.mav.srcSystem = src
            self._request_streams()
        if pinned_before is None and self.tracker.pinned_system is not None:
            log.info("flying MAVLink system %d only from now on (pinned: the first autopilot heard)",
                     self.tracker.pinned_system)
        self.health_reader.on_message(msg, self.clock())
        self.base_mode, self.custom_mode = int(msg.base_mode), int(msg.custom_mode)
        self.armed = is_armed(msg.base_mode)
        self.last_heartbeat_t = self.clock()
        self.heartbeats += 1

    def _request_streams(self) -> None:
        """Ask the autopilot for the position and health streams (``health_reader.stream_requests``)."""
        for msg_id, rate_hz in stream_requests(self.autopilot, self.anchor is not None, self.position_rate_hz):
            self.send_command(CommandLong(MAV_CMD_SET_MESSAGE_INTERVAL, (float(msg_id), 1e6 / rate_hz, 0, 0, 0, 0, 0),
                                          "message interval"))

    def latest_position(self) -> PositionSample | None:
        """The newest gated position fix, or None if none arrived yet."""
        return self._position

    def latest_gnss_velocity(self) -> GnssVelocity | None:
        """The GNSS receiver's newest velocity with a 3D fix (GPS_RAW_INT), or None."""
        return self._gnss

    def latest_thrust_accel(self) -> ThrustAccel | None:
        """The thrust's horizontal acceleration from the newest attitude (PX4's ODOMETRY), or None."""
        return self._thrust

    def pop_results(self) -> list[CommandResult]:
        """The COMMAND_ACKs received since the last call, as ``CommandResult``s."""
        acks, self._acks = self._acks, []
        return [command_result(command, result) for command, result in acks]

    @property
    def mode(self) -> ModeClass:
        """The vehicle's mode class from its last HEARTBEAT (``UNKNOWN`` before one, or before ``use_adapter``)."""
        if self.adapter is None or self.last_heartbeat_t is None:
            return ModeClass.UNKNOWN
        return self.adapter.classify_mode(self.base_mode, self.custom_mode)

    def use_adapter(self, adapter: Adapter) -> None:
        """The autopilot flavour (PX4 or ArduPilot) that encodes intents and decodes modes."""
        self.adapter = adapter

    def send_velocity_ned(self, vn: float, ve: float, vd: float) -> None:
        """Send one velocity-only SET_POSITION_TARGET_LOCAL_NED [m/s] (``setpoint_codec``)."""
        send_velocity_setpoint(self.mav, int(self.clock() * 1000) & 0xFFFFFFFF, self.target_system or 1,
                               self.target_component, MAV_FRAME_LOCAL_NED, TYPEMASK_VELOCITY_ONLY, vn, ve, vd)
        self.setpoints_sent += 1

    def send_velocity_accel_ned(self, vn: float, ve: float, vd: float, an: float, ae: float, ad: float) -> None:
        """Send one SET_POSITION_TARGET_LOCAL_NED with velocity [m/s] and acceleration feed-forward [m/s^2]."""
        send_velocity_setpoint(self.mav, int(self.clock() * 1000) & 0xFFFFFFFF, self.target_system or 1,
                               self.target_component, MAV_FRAME_LOCAL_NED, TYPEMASK_VELOCITY_ACCEL, vn, ve, vd,
                               an, ae, ad)
        self.setpoints_sent += 1

    # ---- intents (adapters.VehicleCommands) as COMMAND_LONGs --------------------------------
    def _adapter(self) -> Adapter:
        if self.adapter is None:
            raise RuntimeError("MavlinkLink: no adapter yet (use_adapter) to encode a mode or takeoff command")
        return self.adapter

    def arm(self) -> None:
        """Request arming (COMMAND_LONG MAV_CMD_COMPONENT_ARM_DISARM)."""
        self.send_command(arm_command())

    def set_mode(self, mode: ModeClass) -> None:
        """Request ``mode`` in the adapter's encoding (PX4 custom mode or ArduPilot mode number)."""
        self.send_command(self._adapter().set_mode(mode))

    def takeoff(self, alt_m: float) -> None:
        """Request a take-off to ``alt_m`` metres (PX4: none to send, the climb is flown in OFFBOARD)."""
        cmd = self._adapter().takeoff(alt_m)
        if cmd is not None:  # PX4: the takeoff is a climb in OFFBOARD, there is no command to send
            self.send_command(cmd)

    def hold(self) -> None:
        """Request the adapter's hold mode."""
        self.set_mode(ModeClass.HOLD)

    def land(self) -> None:
        """Request the autopilot's land mode."""
        self.set_mode(ModeClass.LAND)

    def send_command(self, cmd: CommandLong) -> None:
        """Send one COMMAND_LONG to the autopilot (its answer comes back through ``pop_results``)."""
        p = cmd.params
        self._sent_commands[int(cmd.command)] = self.clock()
        self.mav.command_long_send(self.target_system or 1, self.target_component, cmd.command, 0,
                                   p[0], p[1], p[2], p[3], p[4], p[5], p[6])

    def send_heartbeat(self) -> None:
        """Send our HEARTBEAT as an onboard controller."""
        self.mav.heartbeat_send(MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE)

    def discard_backlog(self) -> int:
        """Read and drop what queued up on the socket or port while the agent stalled (bounded)."""
        n = 0
        try:
            while n < MAX_BACKLOG_DISCARD:
                got = self.udp.recv() if self.udp is not None else self.transport.recv()
                if got is None:
                    break
                n += 1
        except OSError as exc:
            self.rlog.event("mavlink:discard", logging.WARNING, "MAVLink: discarding the backlog failed: %s", exc)
        if n:
            log.warning("discarded %d datagrams that queued up while the agent stalled (an old view of the vehicle)", n)
        return n

    def close(self) -> None:
        """Release the socket or port."""
        self.transport.close()
