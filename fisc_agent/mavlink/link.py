"""The MAVLink link (pymavlink) and the interfaces the runner depends on.

``PositionSource`` / ``SetpointSink`` / ``VehicleLink`` are the Protocols the runner uses; the
pymavlink ``MavlinkLink`` implements them (``mavsdk_backend.MavsdkLink`` is the alternative).
A link takes commands at the level of intent (``arm``, ``set_mode``, ``takeoff``, ``hold``,
``land``: ``adapters.VehicleCommands``) and reports the vehicle's mode as a ``ModeClass``; this
one encodes intents as COMMAND_LONGs through the autopilot's adapter (``use_adapter``) and turns
COMMAND_ACKs into ``CommandResult``s.
The link is non-blocking: ``poll()`` drains whatever arrived and updates the vehicle state; the
control loop never waits on the network.

Positions: LOCAL_POSITION_NED (EKF local frame), or, with a ``GeodeticAnchor``,
GLOBAL_POSITION_INT converted to NED relative to the anchor.  Times are local monotonic
receive times (age = now - receive time), so a delayed or frozen stream reads as stale.

Hostile or broken input (``fisc_agent.mavlink.framing``): on UDP the link owns its socket and
parses each datagram on its own (a partial or garbage frame is dropped with its datagram and
cannot desynchronise the parser), and it sends only to the autopilot's address (``udpout``:
the configured one; ``udpin``: the address the autopilot's HEARTBEATs come from; nothing
before that), never to every sender.  On every transport only the autopilot's own system,
component (and UDP address) change its armed state, mode and type or deliver positions and
acks.  Every position fix passes ``fisc_agent.flight.position_gate`` (finite, reachable from the last
accepted fix) before it becomes ``latest_position``.  Refusals are counted in ``rlog`` and
logged at most once per 5 s per kind.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from dataclasses import dataclass
from typing import Callable, Protocol, runtime_checkable

from pymavlink.dialects.v20.ardupilotmega import (MAV_AUTOPILOT_INVALID, MAV_CMD_SET_MESSAGE_INTERVAL,
                                                  MAV_FRAME_LOCAL_NED, MAV_STATE_ACTIVE, MAV_TYPE_ONBOARD_CONTROLLER,
                                                  MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
                                                  MAVLINK_MSG_ID_LOCAL_POSITION_NED,
                                                  POSITION_TARGET_TYPEMASK_AX_IGNORE,
                                                  POSITION_TARGET_TYPEMASK_AY_IGNORE,
                                                  POSITION_TARGET_TYPEMASK_AZ_IGNORE,
                                                  POSITION_TARGET_TYPEMASK_X_IGNORE,
                                                  POSITION_TARGET_TYPEMASK_Y_IGNORE,
                                                  POSITION_TARGET_TYPEMASK_YAW_IGNORE,
                                                  POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE,
                                                  POSITION_TARGET_TYPEMASK_Z_IGNORE)

from fisc_agent.mavlink.adapters import (Adapter, CommandLong, CommandResult, ModeClass, VehicleCommands, arm_command,
                                 autopilot_from_heartbeat, command_result, is_armed)
from fisc_agent.mavlink.endpoints import Endpoint, parse_endpoint
from fisc_agent.flight.frames import GeodeticAnchor
from fisc_agent.mavlink.framing import AutopilotTracker, HeartbeatVerdict, parse_datagram
from fisc_agent.flight.position_gate import PositionGate, PositionGateConfig
from fisc_agent.common.ratelimit import RateLimitedLog

log = logging.getLogger(__name__)

#: SET_POSITION_TARGET_LOCAL_NED type mask: use vx, vy, vz only; ignore position,
#: acceleration, yaw and yaw rate (= 3527).
TYPEMASK_VELOCITY_ONLY = (POSITION_TARGET_TYPEMASK_X_IGNORE | POSITION_TARGET_TYPEMASK_Y_IGNORE
                          | POSITION_TARGET_TYPEMASK_Z_IGNORE | POSITION_TARGET_TYPEMASK_AX_IGNORE
                          | POSITION_TARGET_TYPEMASK_AY_IGNORE | POSITION_TARGET_TYPEMASK_AZ_IGNORE
                          | POSITION_TARGET_TYPEMASK_YAW_IGNORE | POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE)
MAX_MESSAGES_PER_POLL = 2000
POLL_BUDGET_S = 0.01
"""At most this long per ``poll`` (a flood of datagrams must not stretch a control tick)."""
RELOCK_AFTER_S = 3.0
"""A disarmed autopilot silent this long may be replaced by another vehicle (``AutopilotTracker``)."""
UDP_MAX_DATAGRAM = 65535
MAX_ACKS_KEPT = 32
LOG_PERIOD_S = 5.0


@dataclass(frozen=True)
class PositionSample:
    """One position fix in local NED (or anchor NED in geodetic mode)."""

    t_s: float
    """Local monotonic receive time [s]."""
    pos_ned_m: tuple[float, float, float]
    """Position [m]."""
    vel_ned_m_s: tuple[float, float, float]
    """Velocity [m/s]."""
    autopilot_t_s: float | None = None
    """The autopilot's own time of the fix (the message's ``time_boot_ms``) [s]; None when the source
    gives none (MAVSDK's callbacks)."""


@runtime_checkable
class PositionSource(Protocol):
    """Where the runner reads the vehicle's position from."""
    def latest_position(self) -> PositionSample | None:
        """The newest fix, or None if none arrived yet."""


@runtime_checkable
class SetpointSink(Protocol):
    """Where the runner streams its velocity setpoints to."""
    def send_velocity_ned(self, vn: float, ve: float, vd: float) -> None:
        """Send one velocity-only setpoint in MAV_FRAME_LOCAL_NED [m/s]."""


class VehicleLink(PositionSource, SetpointSink, VehicleCommands, Protocol):
    """Everything the runner needs from a link to one autopilot."""

    autopilot: str | None
    """``px4`` / ``ardupilot`` as the autopilot announces itself; None while unknown."""
    armed: bool
    """Armed flag of the vehicle."""
    last_heartbeat_t: float | None
    """Local monotonic time of the newest sign of life [s]; None: never."""

    @property
    def mode(self) -> ModeClass:
        """The vehicle's mode class (``UNKNOWN`` before the first HEARTBEAT or ``use_adapter``)."""

    def use_adapter(self, adapter: Adapter) -> None:
        """The autopilot flavour to encode intents and decode modes with (chosen by the runner)."""

    def poll(self) -> int:
        """Handle whatever arrived (non-blocking); returns how many messages."""

    def pop_results(self) -> list[CommandResult]:
        """The autopilot's answers to commands since the last call, oldest first."""

    def send_heartbeat(self) -> None:
        """Our own HEARTBEAT (a no-op where the library sends its own)."""

    def close(self) -> None:
        """Release the connection."""


def _import_mavutil():
    # pymavlink picks MAVLink 1 or 2 from this variable at import; PX4 and ArduPilot speak 2.
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    if getattr(mavutil, "mavlink", None) is None or getattr(mavutil.mavlink, "WIRE_PROTOCOL_VERSION", "2.0") != "2.0":
        mavutil.set_dialect("ardupilotmega")
    return mavutil


class UdpTransport:
    """One non-blocking UDP socket that sends only to the autopilot's address.

    ``udpin``: bound to the endpoint; ``peer`` is None (nothing is sent) until the link locks on
    an autopilot and sets it.  ``udpout``: an ephemeral socket; ``peer`` is the endpoint (the
    agent talks first so that the autopilot learns its address).  ``write`` is what a pymavlink
    ``MAVLink`` encoder calls."""

    def __init__(self, endpoint: Endpoint) -> None:
        self.listening = endpoint.kind == "udpin"
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.peer: tuple[str, int] | None = None
        if self.listening:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self.sock.bind((endpoint.host, int(endpoint.port)))
        else:
            try:
                host = socket.gethostbyname(endpoint.host)
            except OSError as exc:  # no DNS yet: sendto resolves the name on each send
                log.warning("cannot resolve %s (%s); will retry on every send", endpoint.host, exc)
                host = endpoint.host
            self.peer = (host, int(endpoint.port))

    @property
    def local_address(self) -> tuple[str, int]:
        """The (host, port) this socket is bound to."""
        return self.sock.getsockname()

    def recv(self) -> tuple[bytes, tuple[str, int]] | None:
        """One datagram and its sender, or None when none is waiting."""
        try:
            return self.sock.recvfrom(UDP_MAX_DATAGRAM)
        except (BlockingIOError, InterruptedError):
            return None
        except ConnectionRefusedError:  # ICMP port unreachable from an earlier send (peer not up yet)
            return None

    def write(self, buf: bytes) -> None:
        """Send ``buf`` to the autopilot's address (dropped until the autopilot has been heard)."""
        if self.peer is None:
            return
        try:
            self.sock.sendto(buf, self.peer)
        except OSError as exc:  # peer unreachable right now: the link timeout covers it
            log.debug("MAVLink send to %s:%d failed: %s", *self.peer, exc)

    def close(self) -> None:
        """Close the socket."""
        self.sock.close()


class MavlinkLink:
    """pymavlink connection to one autopilot: vehicle state, positions, setpoints, commands."""

    def __init__(self, endpoint: Endpoint | str, source_system: int | None = None, source_component: int = 191,
                 anchor: GeodeticAnchor | None = None, position_rate_hz: float = 50.0,
                 clock: Callable[[], float] = time.monotonic,
                 position_gate: PositionGateConfig | None = None) -> None:
        self.endpoint = parse_endpoint(endpoint) if isinstance(endpoint, str) else endpoint
        self.anchor = anchor
        self.clock = clock
        self.position_rate_hz = position_rate_hz
        self._fixed_source = source_system
        self.rlog = RateLimitedLog(log, LOG_PERIOD_S, clock=clock)
        """Counters of refused MAVLink input (``mavlink:<kind>``) and their rate-limited log."""
        self.bad_bytes = 0
        """Received bytes that were not part of a valid frame."""
        self.tracker = AutopilotTracker(RELOCK_AFTER_S)
        self.position_gate = PositionGate(position_gate)
        self.udp: UdpTransport | None = None
        self.conn = None
        if self.endpoint.kind in ("udpin", "udpout"):
            from pymavlink.dialects.v20 import ardupilotmega as mavlink2

            self.udp = UdpTransport(self.endpoint)
            self.mav = mavlink2.MAVLink(self.udp, srcSystem=source_system or 255, srcComponent=source_component)
            self._decoder = mavlink2.MAVLink(None)
        else:  # serial and TCP are byte streams: pymavlink's stream parser
            mavutil = _import_mavutil()
            kwargs = dict(source_system=source_system or 255, source_component=source_component, autoreconnect=True)
            if self.endpoint.kind == "serial":
                kwargs["baud"] = self.endpoint.baud
            self.conn = mavutil.mavlink_connection(self.endpoint.device, **kwargs)
            self.mav = self.conn.mav
        self.autopilot: str | None = None
        self.adapter: Adapter | None = None
        """Encodes intents and decodes modes (``use_adapter``)."""
        self.target_system: int | None = None
        self.target_component: int = 1
        self.armed = False
        self.base_mode = 0
        self.custom_mode = 0
        self.last_heartbeat_t: float | None = None
        self.heartbeats = 0
        self._position: PositionSample | None = None
        self._acks: list[tuple[int, int]] = []
        self.status_texts: list[str] = []
        self.setpoints_sent = 0

    # ---- receive -------------------------------------------------------------------------
    def poll(self) -> int:
        """Drain received messages (non-blocking, at most ``POLL_BUDGET_S``); returns how many
        were handled."""
        n = 0
        t_end = time.monotonic() + POLL_BUDGET_S
        while n < MAX_MESSAGES_PER_POLL and time.monotonic() < t_end:
            if self.udp is not None:
                got = self.udp.recv()
                if got is None:
                    break
                data, addr = got
                scan = parse_datagram(data, self._decoder.decode)
                if scan.bad_bytes:
                    self.bad_bytes += scan.bad_bytes
                    self.rlog.event("mavlink:bad_bytes", logging.WARNING, "MAVLink: %d bad bytes in a %d-byte datagram "
                                    "from %s:%d dropped (garbage, partial or corrupted frames)", scan.bad_bytes,
                                    len(data), *addr)
                for msg in scan.messages:
                    n += 1
                    self._handle(msg, addr)
                continue
            msg = self.conn.recv_msg()
            if msg is None:
                break
            n += 1
            if msg.get_type() == "BAD_DATA":
                self.rlog.event("mavlink:bad_bytes", logging.WARNING, "MAVLink: bad data dropped (%s)",
                                getattr(msg, "reason", "?"))
                continue
            self._handle(msg, None)
        return n

    def _handle(self, msg, addr=None) -> None:
        mtype = msg.get_type()
        if mtype == "HEARTBEAT":
            self._on_heartbeat(msg, addr)
            return
        if not self.tracker.is_autopilot(msg.get_srcSystem(), msg.get_srcComponent(), addr):
            self.rlog.event("mavlink:foreign_message", logging.DEBUG, "MAVLink: %s from system %d component %d "
                            "(not the autopilot) ignored", mtype, msg.get_srcSystem(), msg.get_srcComponent())
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
        elif mtype == "COMMAND_ACK":
            self._acks.append((int(msg.command), int(msg.result)))
            del self._acks[:-MAX_ACKS_KEPT]  # bounded even if nobody pops them
        elif mtype == "STATUSTEXT":
            text = str(msg.text).rstrip("\x00")
            self.status_texts.append(text)
            del self.status_texts[:-50]
            log.info("autopilot: %s", text)

    def _offer_position(self, sample: PositionSample) -> None:
        verdict = self.position_gate.check(sample.t_s, sample.pos_ned_m, sample.vel_ned_m_s)
        if verdict.accepted:
            self._position = sample
        else:
            self.rlog.event(f"position:{verdict.value}", logging.WARNING, "position fix rejected (%s): NED %s",
                            verdict.value, tuple(round(float(v), 2) for v in sample.pos_ned_m))

    def _on_heartbeat(self, msg, addr=None) -> None:
        src, comp = msg.get_srcSystem(), msg.get_srcComponent()
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
            self._position = None  # never mix fixes of two vehicles
            self.position_gate = PositionGate(self.position_gate.cfg)
            self.armed, self.last_heartbeat_t = False, None
            (log.warning if relock else log.info)(
                "autopilot %s: system %d component %d (%s)%s", "changed to" if relock else "found", src, comp,
                self.autopilot or f"MAV_AUTOPILOT {msg.autopilot}",
                f" at {addr[0]}:{addr[1]}" if isinstance(addr, tuple) else "")
            if self.udp is not None and self.udp.listening:
                self.udp.peer = addr  # replies go to the autopilot only
            if self._fixed_source is None:
                self.mav.srcSystem = src
            self._request_position_stream()
        self.base_mode, self.custom_mode = int(msg.base_mode), int(msg.custom_mode)
        self.armed = is_armed(msg.base_mode)
        self.last_heartbeat_t = self.clock()
        self.heartbeats += 1

    def _request_position_stream(self) -> None:
        msg_id = MAVLINK_MSG_ID_GLOBAL_POSITION_INT if self.anchor is not None else MAVLINK_MSG_ID_LOCAL_POSITION_NED
        interval_us = 1e6 / self.position_rate_hz
        self.send_command(CommandLong(MAV_CMD_SET_MESSAGE_INTERVAL, (float(msg_id), interval_us, 0, 0, 0, 0, 0),
                                      "position message interval"))

    def latest_position(self) -> PositionSample | None:
        """The newest gated position fix, or None if none arrived yet."""
        return self._position

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

    # ---- send ----------------------------------------------------------------------------
    def velocity_setpoint_message(self, vn: float, ve: float, vd: float):
        """The SET_POSITION_TARGET_LOCAL_NED message for a velocity-only setpoint."""
        boot_ms = int(self.clock() * 1000) & 0xFFFFFFFF
        return self.mav.set_position_target_local_ned_encode(
            boot_ms, self.target_system or 1, self.target_component, MAV_FRAME_LOCAL_NED, TYPEMASK_VELOCITY_ONLY,
            0.0, 0.0, 0.0, vn, ve, vd, 0.0, 0.0, 0.0, 0.0, 0.0)

    def send_velocity_ned(self, vn: float, ve: float, vd: float) -> None:
        """Send one velocity-only SET_POSITION_TARGET_LOCAL_NED [m/s]."""
        self.mav.send(self.velocity_setpoint_message(vn, ve, vd))
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
        self.mav.command_long_send(self.target_system or 1, self.target_component, cmd.command, 0,
                                   p[0], p[1], p[2], p[3], p[4], p[5], p[6])

    def send_heartbeat(self) -> None:
        """Send our HEARTBEAT as an onboard controller."""
        self.mav.heartbeat_send(MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE)

    def close(self) -> None:
        """Release the UDP socket or the pymavlink connection."""
        if self.udp is not None:
            self.udp.close()
        else:
            self.conn.close()
