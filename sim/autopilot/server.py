"""MAVLink front end of the autopilot emulator: sockets, telemetry streams, command handling.

:class:`AutopilotEmulator` wraps one :class:`~sim.autopilot.vehicle.Vehicle` and speaks MAVLink 2
(pymavlink's generated ``ardupilotmega`` dialect, a superset of ``common``) over UDP or TCP so that
unmodified clients (pymavlink scripts, MAVSDK, MAVProxy) can fly it.

MAVLink objects: the emulator does not use ``pymavlink.mavutil`` at all (mavutil keeps the dialect
and the MAVLink 1/2 choice in module globals driven by the ``MAVLINK20`` / ``MAVLINK_DIALECT``
environment variables).  It instantiates ``pymavlink.dialects.v20.ardupilotmega.MAVLink`` per
emulator for encoding (always MAVLink 2) and one parser per peer, and owns its sockets, so many
emulators in one process share no state.  Clients may speak MAVLink 1 or 2.

Endpoints, as pymavlink/MAVSDK users write them (``scheme:host:port`` or ``scheme://host:port``):

* ``udpin:0.0.0.0:14540`` (also ``udp:``): listen; reply to every peer that has sent something;
* ``udpout:127.0.0.1:14550``: send to that address (e.g. MAVSDK's ``udpin://0.0.0.0:14550``);
  replies are read on the same socket;
* ``tcpin:0.0.0.0:5760``: TCP server, any number of clients;
* ``tcp:127.0.0.1:5760`` (also ``tcpout:``): TCP client, reconnecting every second.

Threading: :meth:`AutopilotEmulator.start` runs the loop in a daemon thread; :meth:`poll` is one
loop iteration (usable by a caller that multiplexes many emulators in one thread);
:attr:`AutopilotEmulator.state` is an immutable snapshot safe to read from any thread.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import select
import socket
import struct
import threading
import time
from dataclasses import dataclass
from typing import Callable, Iterable

from pymavlink.dialects.v20 import ardupilotmega as mavlink

import numpy as np

from sim.autopilot.faults import DelayLine, FaultConfig, FaultInjector
from sim.autopilot.personalities import Personality, get_personality
from sim.plant import PlantParams, VelocityPlant
from sim.autopilot.vehicle import (
    ACCEPTED,
    DENIED,
    UNSUPPORTED,
    Outcome,
    Setpoint,
    Vehicle,
    VehicleConfig,
    VehicleState,
)

__all__ = [
    "AutopilotEmulator",
    "Endpoint",
    "parse_endpoint",
    "ned_to_geodetic",
    "geodetic_to_ned",
    "resolve_local_setpoint",
    "DEFAULT_HOME_LLA",
]

_log = logging.getLogger(__name__)

EARTH_RADIUS_M = 6378137.0
DEFAULT_HOME_LLA = (47.397742, 8.545594, 488.0)
"""Geodetic origin of local NED (PX4 SITL's default, Zurich): lat [deg], lon [deg], alt AMSL [m]."""

_FORCE_DISARM_MAGIC = 21196
_PEER_LIMIT = 16


# ------------------------------------------------------------------------------------ geodesy
def ned_to_geodetic(ned_m: Iterable[float], origin_lla: tuple[float, float, float]) -> tuple[float, float, float]:
    """Local NED [m] -> (lat [deg], lon [deg], alt AMSL [m]), flat-earth approximation."""
    n, e, d = (float(x) for x in ned_m)
    lat0, lon0, alt0 = origin_lla
    lat = lat0 + math.degrees(n / EARTH_RADIUS_M)
    lon = lon0 + math.degrees(e / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))
    return lat, lon, alt0 - d


def geodetic_to_ned(lat_deg: float, lon_deg: float, alt_m: float, origin_lla: tuple[float, float, float]) -> tuple[float, float, float]:
    """Inverse of :func:`ned_to_geodetic`."""
    lat0, lon0, alt0 = origin_lla
    n = math.radians(lat_deg - lat0) * EARTH_RADIUS_M
    e = math.radians(lon_deg - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0))
    return n, e, alt0 - alt_m


# ------------------------------------------------------------------------------------ setpoints
_POS_BITS = (1, 2, 4)
_VEL_BITS = (8, 16, 32)
_YAW_IGNORE = 1024
_YAW_RATE_IGNORE = 2048


def _axes(values: tuple[float, float, float], mask: int, bits: tuple[int, int, int]) -> list[float]:
    return [float(v) if not (mask & b) and math.isfinite(v) else math.nan for v, b in zip(values, bits)]


def _rotate_yaw(v: list[float], yaw: float) -> list[float]:
    c, s = math.cos(yaw), math.sin(yaw)
    return [c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]]


def resolve_local_setpoint(
    frame: int,
    type_mask: int,
    position: tuple[float, float, float],
    velocity: tuple[float, float, float],
    yaw: float,
    yaw_rate: float,
    current_ned_m: tuple[float, float, float],
    current_yaw_rad: float,
) -> Setpoint | None:
    """SET_POSITION_TARGET_LOCAL_NED fields -> :class:`Setpoint` in local NED (None: frame unsupported).

    ``type_mask`` bits set = ignore (position 1/2/4, velocity 8/16/32, yaw 1024, yaw rate 2048);
    acceleration/force fields are not flown (an axis with neither position nor velocity holds
    zero velocity).  Frames: LOCAL_NED; LOCAL_OFFSET_NED (position relative to the vehicle);
    BODY_NED (position as LOCAL_NED, velocity rotated by the heading); BODY_OFFSET_NED / BODY_FRD
    (position offset and velocity both rotated by the heading, offset relative to the vehicle).
    """
    pos = _axes(position, type_mask, _POS_BITS)
    vel = _axes(velocity, type_mask, _VEL_BITS)
    if frame == mavlink.MAV_FRAME_LOCAL_NED:
        pass
    elif frame == mavlink.MAV_FRAME_LOCAL_OFFSET_NED:
        pos = [c + p for c, p in zip(current_ned_m, pos)]
    elif frame == mavlink.MAV_FRAME_BODY_NED:
        vel = _rotate_yaw(vel, current_yaw_rad)
    elif frame in (mavlink.MAV_FRAME_BODY_OFFSET_NED, getattr(mavlink, "MAV_FRAME_BODY_FRD", 12)):
        rp = _rotate_yaw(pos, current_yaw_rad)
        pos = [c + p for c, p in zip(current_ned_m, rp)]
        vel = _rotate_yaw(vel, current_yaw_rad)
    else:
        return None
    y = float(yaw) if not (type_mask & _YAW_IGNORE) and math.isfinite(yaw) else math.nan
    yr = float(yaw_rate) if not (type_mask & _YAW_RATE_IGNORE) and math.isfinite(yaw_rate) else math.nan
    return Setpoint(tuple(pos), tuple(vel), y, yr)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------ transport
@dataclass(frozen=True)
class Endpoint:
    """A parsed MAVLink endpoint URL."""

    kind: str
    """``udpin``, ``udpout``, ``tcpin`` or ``tcp``."""
    host: str
    """Host name or address."""
    port: int
    """Port (0 with ``udpin``/``tcpin``: any free port, see ``AutopilotEmulator.local_address``)."""


_SCHEMES = {"udpin": "udpin", "udp": "udpin", "udpout": "udpout", "tcpin": "tcpin", "tcp": "tcp", "tcpout": "tcp"}


def parse_endpoint(url: str) -> Endpoint:
    """Parse ``udpin:HOST:PORT``, ``udpout:HOST:PORT``, ``tcpin:``, ``tcp:`` (``://`` also accepted)."""
    text = url.strip()
    sep = "://" if "://" in text else ":"
    scheme, _, rest = text.partition(sep)
    kind = _SCHEMES.get(scheme.lower())
    if kind is None or not rest:
        raise ValueError(
            f"MAVLink endpoint {url!r}: expected udpin:HOST:PORT, udpout:HOST:PORT, tcpin:HOST:PORT or tcp:HOST:PORT"
        )
    host, colon, port_text = rest.rpartition(":")
    if not colon:
        raise ValueError(f"MAVLink endpoint {url!r}: missing ':PORT'")
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(f"MAVLink endpoint {url!r}: port {port_text!r} is not an integer") from None
    if not 0 <= port <= 65535 or (port == 0 and kind in ("udpout", "tcp")):
        raise ValueError(f"MAVLink endpoint {url!r}: port {port} out of range")
    if not host:
        host = "0.0.0.0" if kind in ("udpin", "tcpin") else "127.0.0.1"
    return Endpoint(kind, host, port)


class _Transport:
    """Non-blocking datagram/stream I/O; peers are keyed so each gets its own parser."""

    def sockets(self) -> list[socket.socket]:
        raise NotImplementedError

    def receive(self) -> list[tuple[object, bytes]]:
        raise NotImplementedError

    def send(self, data: bytes) -> None:
        raise NotImplementedError

    @property
    def has_peers(self) -> bool:
        """True if anything would receive what is sent now."""
        raise NotImplementedError

    def close(self) -> None:
        for s in self.sockets():
            s.close()

    @property
    def local_address(self) -> tuple[str, int]:
        return self.sockets()[0].getsockname()[:2]


class _Udp(_Transport):
    def __init__(self, ep: Endpoint) -> None:
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self._peers: dict[tuple[str, int], None] = {}
        if ep.kind == "udpin":
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._sock.bind((ep.host, ep.port))
        else:
            self._sock.bind(("0.0.0.0", 0))
            self._peers[(socket.gethostbyname(ep.host), ep.port)] = None
        self._fixed = ep.kind == "udpout"

    def sockets(self) -> list[socket.socket]:
        return [self._sock]

    @property
    def has_peers(self) -> bool:
        return bool(self._peers)

    def receive(self) -> list[tuple[object, bytes]]:
        out: list[tuple[object, bytes]] = []
        while True:
            try:
                data, addr = self._sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return out
            except ConnectionRefusedError:  # ICMP from an earlier send; harmless for UDP
                continue
            if not self._fixed and addr not in self._peers:
                if len(self._peers) >= _PEER_LIMIT:
                    self._peers.pop(next(iter(self._peers)))
                self._peers[addr] = None
                _log.info("udp peer %s:%d", *addr)
            out.append((addr, data))

    def send(self, data: bytes) -> None:
        for addr in self._peers:
            try:
                self._sock.sendto(data, addr)
            except (BlockingIOError, ConnectionRefusedError, InterruptedError):
                pass  # UDP: a full buffer or an absent listener loses the datagram, as on a radio link


class _TcpServer(_Transport):
    def __init__(self, ep: Endpoint) -> None:
        self._listen = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listen.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listen.bind((ep.host, ep.port))
        self._listen.listen(8)
        self._listen.setblocking(False)
        self._clients: list[socket.socket] = []
        self._out: dict[socket.socket, bytearray] = {}

    def sockets(self) -> list[socket.socket]:
        return [self._listen, *self._clients]

    @property
    def has_peers(self) -> bool:
        return bool(self._clients)

    def receive(self) -> list[tuple[object, bytes]]:
        while True:
            try:
                conn, addr = self._listen.accept()
            except (BlockingIOError, InterruptedError):
                break
            conn.setblocking(False)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._clients.append(conn)
            self._out[conn] = bytearray()
            _log.info("tcp client %s:%d", *addr)
        out: list[tuple[object, bytes]] = []
        for c in list(self._clients):
            out.extend(_read_stream(c, self._drop))
        return out

    def _drop(self, c: socket.socket) -> None:
        if c in self._clients:
            self._clients.remove(c)
        self._out.pop(c, None)
        c.close()

    def send(self, data: bytes) -> None:
        for c in list(self._clients):
            _write_stream(c, self._out[c], data, self._drop)

    @property
    def local_address(self) -> tuple[str, int]:
        return self._listen.getsockname()[:2]


class _TcpClient(_Transport):
    def __init__(self, ep: Endpoint, clock: Callable[[], float]) -> None:
        self._ep = ep
        self._clock = clock
        self._sock: socket.socket | None = None
        self._out = bytearray()
        self._next_try = -math.inf
        self._connect()

    def _connect(self) -> None:
        if self._sock is not None or self._clock() < self._next_try:
            return
        self._next_try = self._clock() + 1.0
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.settimeout(1.0)
        try:
            s.connect((self._ep.host, self._ep.port))
        except OSError as exc:
            _log.info("tcp connect to %s:%d failed (%s); retrying", self._ep.host, self._ep.port, exc)
            s.close()
            return
        s.setblocking(False)
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = s
        self._out = bytearray()

    def _drop(self, c: socket.socket) -> None:
        c.close()
        self._sock = None

    def sockets(self) -> list[socket.socket]:
        return [] if self._sock is None else [self._sock]

    @property
    def has_peers(self) -> bool:
        return self._sock is not None

    def receive(self) -> list[tuple[object, bytes]]:
        self._connect()
        return [] if self._sock is None else _read_stream(self._sock, self._drop)

    def send(self, data: bytes) -> None:
        if self._sock is not None:
            _write_stream(self._sock, self._out, data, self._drop)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    @property
    def local_address(self) -> tuple[str, int]:
        return ("", 0) if self._sock is None else self._sock.getsockname()[:2]


def _read_stream(c: socket.socket, drop: Callable[[socket.socket], None]) -> list[tuple[object, bytes]]:
    out: list[tuple[object, bytes]] = []
    while True:
        try:
            data = c.recv(65536)
        except (BlockingIOError, InterruptedError):
            return out
        except OSError:
            drop(c)
            return out
        if not data:
            drop(c)
            return out
        out.append((id(c), data))


_STREAM_BACKLOG_BYTES = 1 << 20


def _write_stream(c: socket.socket, out: bytearray, data: bytes, drop: Callable[[socket.socket], None]) -> None:
    """Queue ``data`` behind what the socket has not taken yet and send what it takes now
    (never blocks; messages stay whole). A peer that stops reading is dropped after 1 MiB."""
    out += data
    if len(out) > _STREAM_BACKLOG_BYTES:
        _log.warning("tcp peer not reading (%d bytes queued); closing it", len(out))
        drop(c)
        return
    try:
        n = c.send(out)
    except (BlockingIOError, InterruptedError):
        return
    except OSError:
        drop(c)
        return
    del out[:n]


def _open_transport(ep: Endpoint, clock: Callable[[], float]) -> _Transport:
    if ep.kind in ("udpin", "udpout"):
        return _Udp(ep)
    if ep.kind == "tcpin":
        return _TcpServer(ep)
    return _TcpClient(ep, clock)


# ------------------------------------------------------------------------------------ emulator
_POSITION_MSGS = frozenset({mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT})
_SENSORS = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE | mavlink.MAV_SYS_STATUS_SENSOR_GPS
    | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mavlink.MAV_SYS_STATUS_SENSOR_YAW_POSITION | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | mavlink.MAV_SYS_STATUS_AHRS | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY | mavlink.MAV_SYS_STATUS_PREARM_CHECK
)  # fmt: skip
_POSITION_SENSORS = mavlink.MAV_SYS_STATUS_SENSOR_GPS | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL


def _int(x: float, default: int = 0) -> int:
    """Command parameter as int (MAVSDK and others send NaN for "unused")."""
    return int(round(x)) if math.isfinite(x) else default


def _i16(x: float) -> int:
    return int(max(-32768, min(32767, round(x))))


_HEADER_V2 = struct.Struct("<BBBBBBBHB")
_CRC_EXTRA = [bytes([n]) for n in range(256)]


def _pack(msg: mavlink.MAVLink_message, mav: mavlink.MAVLink) -> bytes:
    """``msg.pack(mav)``: the same bytes, framed with a few struct calls instead of pymavlink's
    generic ``MAVLink_message._pack`` (header object, CRC object, byte-array appends).

    The message's own ``pack`` still lays out the payload; only the framing is swapped in, and
    only for the unsigned MAVLink 2 frames the emulator sends (anything else goes through
    pymavlink unchanged)."""
    if mav.signing.sign_outgoing or float(mavlink.WIRE_PROTOCOL_VERSION) != 2.0:
        return msg.pack(mav)
    msg_id = msg.get_msgId()

    def frame(mav_: mavlink.MAVLink, crc_extra: int, payload: bytes, force_mavlink1: bool = False) -> bytes:
        if force_mavlink1:
            return mavlink.MAVLink_message._pack(msg, mav_, crc_extra, payload, force_mavlink1)
        body = payload.rstrip(b"\x00") or payload[:1]  # MAVLink 2 drops trailing zeros (keeps one byte)
        head = _HEADER_V2.pack(253, len(body), 0, 0, mav_.seq, mav_.srcSystem, mav_.srcComponent,
                               msg_id & 0xFFFF, msg_id >> 16)  # fmt: skip
        crc = mavlink.x25crc(head[1:] + body + _CRC_EXTRA[crc_extra]).crc
        return head + body + _CRC_U16.pack(crc)

    msg._pack = frame  # type: ignore[method-assign]  # instance attribute: this message only
    try:
        return msg.pack(mav)  # type: ignore[attr-defined]
    finally:
        del msg._pack  # type: ignore[attr-defined]


_CRC_U16 = struct.Struct("<H")


def _warm_up_plant() -> None:
    """Compile (or load from cache) the plant kernel now, not on the first airborne step.

    The first numba call costs about 0.5 s; inside the loop it would stall position output
    and trip the agent's stale-position failsafe.
    """
    VelocityPlant(PlantParams(), 1).step(np.zeros((1, 3)), 0.01)


class AutopilotEmulator:
    """A PX4- or ArduPilot-Copter-like autopilot on a MAVLink endpoint, flying a simulated vehicle.

    Parameters
    ----------
    url: endpoint (see module docstring), e.g. ``"udpin:127.0.0.1:0"`` or ``"udpout:127.0.0.1:14540"``.
    personality: ``"px4"`` or ``"ardupilot"`` (or a :class:`Personality`).
    start_ned: initial position [m] local NED (D < 0: airborne, armed, holding).
    sysid, compid: MAVLink ids of the autopilot.
    home_lla: geodetic origin of local NED (lat, lon [deg], alt AMSL [m]).
    rate_position_hz: LOCAL_POSITION_NED and GLOBAL_POSITION_INT rate (MAV_CMD_SET_MESSAGE_INTERVAL changes it).
    rate_attitude_hz: ATTITUDE rate.
    loss, latency_s, position_dropouts, seed: fault injection (:class:`~sim.autopilot.faults.FaultConfig`).
    vehicle_config: physics/rule settings (start_ned overrides its ``start_ned_m``).
    clock: monotonic clock [s] (injectable for tests); wall_clock: Unix time [s] for SYSTEM_TIME.
    """

    def __init__(
        self,
        url: str,
        personality: str | Personality = "px4",
        start_ned: tuple[float, float, float] = (0.0, 0.0, 0.0),
        *,
        sysid: int = 1,
        compid: int = mavlink.MAV_COMP_ID_AUTOPILOT1,
        home_lla: tuple[float, float, float] = DEFAULT_HOME_LLA,
        rate_position_hz: float = 20.0,
        rate_attitude_hz: float = 10.0,
        loss: float = 0.0,
        latency_s: float = 0.0,
        position_dropouts: tuple[tuple[float, float], ...] = (),
        seed: int | None = 0,
        vehicle_config: VehicleConfig | None = None,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        if not 1 <= sysid <= 255:
            raise ValueError(f"sysid must be in 1..255, got {sysid}")
        for name, rate in (("rate_position_hz", rate_position_hz), ("rate_attitude_hz", rate_attitude_hz)):
            if not (rate >= 0 and math.isfinite(rate)):
                raise ValueError(f"{name} must be a finite number >= 0, got {rate}")
        self.url = url
        self.endpoint = parse_endpoint(url)
        self.personality = personality if isinstance(personality, Personality) else get_personality(personality)
        self.sysid, self.compid = int(sysid), int(compid)
        self.home_lla = tuple(float(x) for x in home_lla)
        cfg = dataclasses.replace(vehicle_config or VehicleConfig(), start_ned_m=tuple(float(x) for x in start_ned))
        self._clock, self._wall = clock, wall_clock
        self._t0 = clock()
        self.vehicle = Vehicle(self.personality, cfg, sysid=self.sysid, t0_s=0.0)
        self.faults = FaultInjector(FaultConfig(loss, latency_s, tuple(position_dropouts), seed))
        self._mav = mavlink.MAVLink(None, srcSystem=self.sysid, srcComponent=self.compid)
        self._parsers: dict[object, mavlink.MAVLink] = {}
        self._delay: DelayLine[bytes] = DelayLine()
        self._transport: _Transport | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.RLock()  # re-entrant: `state` may be read from a handler inside poll()
        self._intervals: dict[int, float] = {}
        self._next_due: dict[int, float] = {}
        self._default_intervals = {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
            mavlink.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
            mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0,
            mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
            mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 1.0,
            mavlink.MAVLINK_MSG_ID_HOME_POSITION: 2.0,
            mavlink.MAVLINK_MSG_ID_VFR_HUD: 0.5,
            mavlink.MAVLINK_MSG_ID_ATTITUDE: 1.0 / rate_attitude_hz if rate_attitude_hz > 0 else 0.0,
            mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 1.0 / rate_position_hz if rate_position_hz > 0 else 0.0,
            mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 1.0 / rate_position_hz if rate_position_hz > 0 else 0.0,
        }
        self._intervals = dict(self._default_intervals)
        self._builders: dict[int, Callable[[VehicleState], object]] = {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: self._heartbeat,
            mavlink.MAVLINK_MSG_ID_SYS_STATUS: self._sys_status,
            mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: self._extended_sys_state,
            mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: self._system_time,
            mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: self._gps_raw_int,
            mavlink.MAVLINK_MSG_ID_HOME_POSITION: self._home_position,
            mavlink.MAVLINK_MSG_ID_VFR_HUD: self._vfr_hud,
            mavlink.MAVLINK_MSG_ID_ATTITUDE: self._attitude,
            mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: self._local_position_ned,
            mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self._global_position_int,
            mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self._autopilot_version,
        }
        self._handlers: dict[str, Callable[[object, float], None]] = {
            "HEARTBEAT": self._on_heartbeat,
            "COMMAND_LONG": self._on_command_long,
            "COMMAND_INT": self._on_command_int,
            "SET_MODE": self._on_set_mode,
            "SET_POSITION_TARGET_LOCAL_NED": self._on_set_position_target_local_ned,
            "SET_POSITION_TARGET_GLOBAL_INT": self._on_set_position_target_global_int,
            "PARAM_REQUEST_LIST": self._on_param_request_list,
            "PARAM_REQUEST_READ": self._on_param_request_read,
            "PARAM_SET": self._on_param_set,
            "MISSION_REQUEST_LIST": self._on_mission_request_list,
            "MISSION_COUNT": self._on_mission_count,
            "MISSION_CLEAR_ALL": self._on_mission_clear_all,
            "TIMESYNC": self._on_timesync,
        }
        self.stats = {"rx": 0, "tx": 0, "rx_dropped": 0, "tx_dropped": 0, "position_suppressed": 0, "errors": 0,
                      "setpoints": 0}
        """Message counters (read-only for callers)."""
        self._state: VehicleState | None = None  # built lazily by _snapshot() after each change
        self._streams_due = -math.inf  # earliest next-due time of the streams (-inf: recompute)
        self._announced = (self.vehicle.armed, self.personality.custom_mode(self.vehicle.mode))

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Open the endpoint (done by :meth:`start`/:meth:`run`; idempotent)."""
        if self._transport is None:
            self._transport = _open_transport(self.endpoint, self._clock)
            _log.info("autopilot emulator %s sysid %d on %s", self.personality.name, self.sysid, self.url)

    @property
    def local_address(self) -> tuple[str, int]:
        """(host, port) the socket is bound to (useful with port 0)."""
        self.open()
        assert self._transport is not None
        return self._transport.local_address

    @property
    def state(self) -> VehicleState:
        """Latest immutable vehicle snapshot (thread-safe)."""
        with self._lock:
            return self._snapshot()

    def _snapshot(self) -> VehicleState:
        """The vehicle snapshot as of the last change point (poll, command), built on first use.

        Every place that used to take a snapshot now only drops the cached one; the vehicle does
        not change between such a place and the next read, so what is read is the same."""
        st = self._state
        if st is None:
            st = self._state = self.vehicle.snapshot()
        return st

    @property
    def time_s(self) -> float:
        """Emulator time since construction [s]."""
        return self._clock() - self._t0

    def start(self) -> "AutopilotEmulator":
        """Run the emulator in a background daemon thread."""
        if self._thread is not None:
            raise RuntimeError("emulator already started")
        self.open()
        self._stop.clear()
        self._thread = threading.Thread(target=self.run, name=f"autopilot-{self.sysid}", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the loop (thread or :meth:`run`) and close the socket."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
            self._thread = None
        self.close()

    def close(self) -> None:
        """Close the socket."""
        with self._lock:
            if self._transport is not None:
                self._transport.close()
                self._transport = None

    def __enter__(self) -> "AutopilotEmulator":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def run(self, stop: threading.Event | None = None) -> None:
        """Serve in real time until :meth:`stop` is called or ``stop`` is set."""
        self.open()
        _warm_up_plant()
        ev = self._stop if stop is None else stop
        while not (ev.is_set() or self._stop.is_set()):
            wait = self.poll()
            with self._lock:
                socks = [] if self._transport is None else self._transport.sockets()
            if not socks:
                time.sleep(min(wait, 0.05))
                continue
            try:
                select.select(socks, [], [], wait)
            except (OSError, ValueError):  # socket closed by stop() in another thread
                if ev.is_set() or self._stop.is_set():
                    break
                raise

    def poll(self) -> float:
        """One iteration: receive and handle, advance the vehicle, send due messages.

        Returns the time [s] until something is next due (the caller may sleep that long)."""
        with self._lock:
            if self._transport is None:
                return 0.05
            now = self.time_s
            for key, data in self._transport.receive():
                self._receive(key, data, now)
            veh = self.vehicle
            veh.step(now)
            dropout = self.faults.position_dropout(now)
            if veh.position_valid == dropout:
                veh.set_position_valid(not dropout, now)
            for ev in veh.drain_events():
                self._statustext(ev.severity, ev.text)
            self._state = None
            announced = (veh.armed, self.personality.custom_mode(veh.mode))
            if announced != self._announced:
                # arming / mode changes are announced at once (then the 1 Hz rhythm resumes)
                self._announced = announced
                self._next_due[mavlink.MAVLINK_MSG_ID_HEARTBEAT] = now
                self._next_due[mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE] = now
                self._streams_due = -math.inf
            next_due = self._send_streams(now) if now >= self._streams_due else self._streams_due
            if self._delay:  # latency fault injection only
                for buf in self._delay.pop_due(now):
                    self._transport.send(buf)
                next_due = min(next_due, self._delay.next_due())
            return float(min(max(next_due - self.time_s, 0.0), 0.05))

    # ------------------------------------------------------------------ output
    def _send(self, msg: object) -> None:
        buf = _pack(msg, self._mav)
        self._mav.seq = (self._mav.seq + 1) % 256
        if self.faults.drop_outgoing():
            self.stats["tx_dropped"] += 1
            return
        self.stats["tx"] += 1
        if self.faults.latency_s > 0.0:
            self._delay.push(self.time_s + self.faults.latency_s, buf)
        elif self._transport is not None:
            self._transport.send(buf)

    def _send_message_id(self, msg_id: int, now: float) -> bool:
        build = self._builders.get(msg_id)
        if build is None:
            return False
        if msg_id in _POSITION_MSGS and self.faults.position_dropout(now):
            self.stats["position_suppressed"] += 1
            return True
        if self._transport is not None and not self._transport.has_peers:
            return True  # nobody listening yet (udpin before the first packet): skip the encoding
        self._send(build(self._snapshot()))
        return True

    def _send_streams(self, now: float) -> float:
        next_due = math.inf
        for msg_id, interval in self._intervals.items():
            if interval <= 0.0:
                continue
            due = self._next_due.get(msg_id, now)
            if now >= due:
                self._send_message_id(msg_id, now)
                due = due + interval if now - due < interval else now + interval
                self._next_due[msg_id] = due
            next_due = min(next_due, due)
        self._streams_due = next_due
        return next_due

    def _statustext(self, severity: int, text: str) -> None:
        self._send(self._mav.statustext_encode(severity, text.encode("ascii", "replace")[:50]))

    def _boot_ms(self, st: VehicleState) -> int:
        return int(st.t_s * 1000.0) & 0xFFFFFFFF

    def _heartbeat(self, st: VehicleState) -> object:
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
        if not st.mode.needs_pilot:
            base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED | mavlink.MAV_MODE_FLAG_AUTO_ENABLED
        if st.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        status = mavlink.MAV_STATE_ACTIVE if st.armed else mavlink.MAV_STATE_STANDBY
        return self._mav.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR, self.personality.autopilot_type, base, st.custom_mode, status, 3
        )

    def _sys_status(self, st: VehicleState) -> object:
        health = _SENSORS if st.position_valid else _SENSORS & ~(_POSITION_SENSORS | mavlink.MAV_SYS_STATUS_PREARM_CHECK)
        return self._mav.sys_status_encode(_SENSORS, _SENSORS, health, 200, 16200, 500 if st.armed else 0, 100,
                                           0, 0, 0, 0, 0, 0)  # fmt: skip

    def _extended_sys_state(self, st: VehicleState) -> object:
        return self._mav.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_MC, st.landed_state)

    def _system_time(self, st: VehicleState) -> object:
        return self._mav.system_time_encode(int(self._wall() * 1e6), self._boot_ms(st))

    def _gps_raw_int(self, st: VehicleState) -> object:
        ok = st.position_valid
        lat, lon, alt = ned_to_geodetic(st.position_ned_m, self.home_lla)
        vn, ve, _ = st.velocity_ned_m_s
        cog = (math.degrees(math.atan2(ve, vn)) % 360.0) * 100 if math.hypot(vn, ve) > 0.1 else 65535
        return self._mav.gps_raw_int_encode(
            int(st.t_s * 1e6), mavlink.GPS_FIX_TYPE_3D_FIX if ok else mavlink.GPS_FIX_TYPE_NO_FIX,
            int(round(lat * 1e7)) if ok else 0, int(round(lon * 1e7)) if ok else 0, int(round(alt * 1000)) if ok else 0,
            80, 120, int(round(math.hypot(vn, ve) * 100)), int(cog) % 65536, 12 if ok else 0,
        )  # fmt: skip

    def _home_position(self, st: VehicleState) -> object:
        lat, lon, alt = ned_to_geodetic(st.home_ned_m, self.home_lla)
        x, y, z = st.home_ned_m
        return self._mav.home_position_encode(
            int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)), x, y, z, [1.0, 0.0, 0.0, 0.0],
            0.0, 0.0, 0.0, int(st.t_s * 1e6),
        )  # fmt: skip

    def _vfr_hud(self, st: VehicleState) -> object:
        vn, ve, vd = st.velocity_ned_m_s
        gs = math.hypot(vn, ve)
        alt = self.home_lla[2] - st.position_ned_m[2]
        throttle = 50 if (st.armed and st.in_air) else 0
        return self._mav.vfr_hud_encode(gs, gs, int(math.degrees(st.yaw_rad) % 360), throttle, alt, -vd)

    def _attitude(self, st: VehicleState) -> object:
        return self._mav.attitude_encode(self._boot_ms(st), st.roll_rad, st.pitch_rad, st.yaw_rad, 0.0, 0.0, st.yaw_rate_rad_s)

    def _local_position_ned(self, st: VehicleState) -> object:
        return self._mav.local_position_ned_encode(self._boot_ms(st), *st.position_ned_m, *st.velocity_ned_m_s)

    def _global_position_int(self, st: VehicleState) -> object:
        lat, lon, alt = ned_to_geodetic(st.position_ned_m, self.home_lla)
        rel = st.home_ned_m[2] - st.position_ned_m[2]
        vn, ve, vd = st.velocity_ned_m_s
        hdg = int(round(math.degrees(st.yaw_rad) % 360.0 * 100)) % 36000
        return self._mav.global_position_int_encode(
            self._boot_ms(st), int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
            int(round(rel * 1000)), _i16(vn * 100), _i16(ve * 100), _i16(vd * 100), hdg,
        )  # fmt: skip

    def _autopilot_version(self, st: VehicleState) -> object:
        p = self.personality
        return self._mav.autopilot_version_encode(
            p.capabilities, p.flight_sw_version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0x46495343_0000 + self.sysid
        )

    def _param_value(self, index: int) -> object:
        spec = self.personality.params[index]
        value = self.personality.encode_param(self.vehicle.params[spec.name], spec.param_type)
        return self._mav.param_value_encode(
            spec.name.encode("ascii"), value, spec.param_type, len(self.personality.params), index
        )

    # ------------------------------------------------------------------ input
    def _receive(self, key: object, data: bytes, now: float) -> None:
        parser = self._parsers.get(key)
        if parser is None:
            if len(self._parsers) > 4 * _PEER_LIMIT:
                self._parsers.clear()
            parser = mavlink.MAVLink(None)
            parser.robust_parsing = True
            self._parsers[key] = parser
            self._next_due[mavlink.MAVLINK_MSG_ID_HEARTBEAT] = now  # greet a new peer at once
            self._streams_due = -math.inf
        try:
            msgs = parser.parse_buffer(data) or []
        except mavlink.MAVError as exc:  # robust parsing should prevent this; count it
            _log.debug("unparsable MAVLink input: %s", exc)
            return
        for msg in msgs:
            kind = msg.get_type()
            if kind == "BAD_DATA" or msg.get_srcSystem() == self.sysid and kind == "HEARTBEAT":
                continue
            if self.faults.drop_incoming():
                self.stats["rx_dropped"] += 1
                continue
            self.stats["rx"] += 1
            target = getattr(msg, "target_system", 0)
            if target not in (0, self.sysid):
                continue
            if getattr(msg, "target_component", 0) not in (0, self.compid):
                continue
            handler = self._handlers.get(kind)
            if handler is not None:
                try:
                    handler(msg, now)
                except Exception:  # a malformed request must not take the vehicle down; logged, counted
                    self.stats["errors"] += 1
                    _log.exception("autopilot sysid %d: error handling %s", self.sysid, msg)

    def _on_heartbeat(self, msg: object, now: float) -> None:
        if msg.type == mavlink.MAV_TYPE_GCS or msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID:  # type: ignore[attr-defined]
            self.vehicle.gcs_heartbeat(now)

    def _ack(self, msg: object, command: int, outcome: Outcome) -> None:
        self._send(self._mav.command_ack_encode(command, outcome.result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))  # type: ignore[attr-defined]
        if outcome.text and not outcome.ok:
            self._statustext(mavlink.MAV_SEVERITY_WARNING, outcome.text)

    def _on_command_long(self, msg: object, now: float) -> None:
        m = msg
        params = [m.param1, m.param2, m.param3, m.param4, m.param5, m.param6, m.param7]  # type: ignore[attr-defined]
        self._command(m, m.command, params, None, now)  # type: ignore[attr-defined]

    def _on_command_int(self, msg: object, now: float) -> None:
        m = msg
        params = [m.param1, m.param2, m.param3, m.param4, float(m.x), float(m.y), m.z]  # type: ignore[attr-defined]
        self._command(m, m.command, params, m.frame, now)  # type: ignore[attr-defined]

    def _command(self, msg: object, command: int, p: list[float], frame: int | None, now: float) -> None:
        veh = self.vehicle
        follow_up: list[int] = []
        if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            force = _int(p[1]) == _FORCE_DISARM_MAGIC
            out = veh.arm(now, force) if _int(p[0]) == 1 else veh.disarm(now, force)
        elif command == mavlink.MAV_CMD_DO_SET_MODE:
            if not _int(p[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                out = Outcome(UNSUPPORTED, "Only custom modes are supported")
            else:
                mode = self.personality.mode_from_command(p[1], p[2])
                out = Outcome(UNSUPPORTED, "Unknown mode") if mode is None else veh.set_mode(mode, now)
        elif command == mavlink.MAV_CMD_NAV_TAKEOFF:
            out = veh.takeoff(now, self._takeoff_altitude(p[6], frame))
        elif command == mavlink.MAV_CMD_NAV_LAND:
            out = veh.land(now)
        elif command == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            out = veh.return_to_launch(now)
        elif command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            out = self._set_interval(_int(p[0], -1), p[1], now)
        elif command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            msg_id = _int(p[0], -1)
            out = Outcome(ACCEPTED) if msg_id in self._builders else Outcome(UNSUPPORTED)
            follow_up.append(msg_id)
        elif command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            out = Outcome(ACCEPTED)
            follow_up.append(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        elif command == mavlink.MAV_CMD_GET_HOME_POSITION:
            out = Outcome(ACCEPTED)
            follow_up.append(mavlink.MAVLINK_MSG_ID_HOME_POSITION)
        else:
            out = Outcome(UNSUPPORTED)
        self._state = None
        self._ack(msg, command, out)
        for msg_id in follow_up:
            if out.ok:
                self._send_message_id(msg_id, now)

    def _takeoff_altitude(self, param7: float, frame: int | None) -> float | None:
        """Takeoff altitude above home [m]: PX4 param7 is AMSL; ArduPilot's is relative."""
        if not math.isfinite(param7):
            return None
        home_amsl = self.home_lla[2] - self.vehicle.home[2]
        relative_frames = (mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
        amsl_frames = (mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT)
        if frame in relative_frames:
            return param7
        if frame in amsl_frames or self.personality.name == "px4":
            return param7 - home_amsl
        return param7

    def _set_interval(self, msg_id: int, interval_us: float, now: float) -> Outcome:
        if msg_id not in self._builders or msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return Outcome(UNSUPPORTED)
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            return Outcome(DENIED, "HEARTBEAT rate is fixed")
        if not math.isfinite(interval_us) or interval_us == 0:
            interval = self._default_intervals.get(msg_id, 0.0)
        elif interval_us < 0:
            interval = 0.0
        else:
            interval = max(interval_us * 1e-6, 0.005)
        self._intervals[msg_id] = interval
        self._next_due[msg_id] = now
        self._streams_due = -math.inf
        return Outcome(ACCEPTED)

    def _on_set_mode(self, msg: object, now: float) -> None:
        if not msg.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:  # type: ignore[attr-defined]
            out = Outcome(UNSUPPORTED, "Only custom modes are supported")
        else:
            mode = self.personality.mode_from_custom(msg.custom_mode)  # type: ignore[attr-defined]
            out = Outcome(UNSUPPORTED, "Unknown mode") if mode is None else self.vehicle.set_mode(mode, now)
        self._state = None
        self._ack(msg, mavlink.MAVLINK_MSG_ID_SET_MODE, out)

    def _on_set_position_target_local_ned(self, msg: object, now: float) -> None:
        m = msg
        veh = self.vehicle
        veh.step(now)
        sp = resolve_local_setpoint(
            m.coordinate_frame, m.type_mask, (m.x, m.y, m.z), (m.vx, m.vy, m.vz), m.yaw, m.yaw_rate,  # type: ignore[attr-defined]
            tuple(veh.pos.tolist()), veh.yaw,
        )  # fmt: skip
        if sp is None:
            _log.warning("SET_POSITION_TARGET_LOCAL_NED frame %d not supported; ignored", m.coordinate_frame)  # type: ignore[attr-defined]
            return
        self.stats["setpoints"] += 1
        veh.set_setpoint(sp, now)

    def _on_set_position_target_global_int(self, msg: object, now: float) -> None:
        m = msg
        veh = self.vehicle
        veh.step(now)
        frame = m.coordinate_frame  # type: ignore[attr-defined]
        if frame not in (mavlink.MAV_FRAME_GLOBAL_INT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                         mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT):
            _log.warning("SET_POSITION_TARGET_GLOBAL_INT frame %d not supported; ignored", frame)
            return
        alt = m.alt  # type: ignore[attr-defined]
        if frame in (mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT):
            alt = alt + self.home_lla[2] - veh.home[2]
        n, e, d = geodetic_to_ned(m.lat_int * 1e-7, m.lon_int * 1e-7, alt, self.home_lla)  # type: ignore[attr-defined]
        sp = resolve_local_setpoint(
            mavlink.MAV_FRAME_LOCAL_NED, m.type_mask, (n, e, d), (m.vx, m.vy, m.vz), m.yaw, m.yaw_rate,  # type: ignore[attr-defined]
            tuple(veh.pos.tolist()), veh.yaw,
        )  # fmt: skip
        if sp is not None:
            self.stats["setpoints"] += 1
            veh.set_setpoint(sp, now)

    def _on_param_request_list(self, msg: object, now: float) -> None:
        for i in range(len(self.personality.params)):
            self._send(self._param_value(i))

    def _on_param_request_read(self, msg: object, now: float) -> None:
        idx = msg.param_index  # type: ignore[attr-defined]
        names = [p.name for p in self.personality.params]
        if idx < 0:
            name = msg.param_id  # type: ignore[attr-defined]
            if name not in names:
                _log.debug("PARAM_REQUEST_READ of unknown %r", name)
                return
            idx = names.index(name)
        if 0 <= idx < len(names):
            self._send(self._param_value(idx))

    def _on_param_set(self, msg: object, now: float) -> None:
        name = msg.param_id  # type: ignore[attr-defined]
        spec = self.personality.param_spec(name)
        if spec is None:
            _log.debug("PARAM_SET of unknown %r ignored", name)
            return
        value = self.personality.decode_param(msg.param_value, msg.param_type)  # type: ignore[attr-defined]
        if math.isfinite(value):
            self.vehicle.set_param(name, value)
        self._send(self._param_value([p.name for p in self.personality.params].index(name)))

    def _on_mission_request_list(self, msg: object, now: float) -> None:
        self._send(self._mav.mission_count_encode(msg.get_srcSystem(), msg.get_srcComponent(), 0,  # type: ignore[attr-defined]
                                                  getattr(msg, "mission_type", 0)))  # fmt: skip

    def _on_mission_count(self, msg: object, now: float) -> None:
        result = mavlink.MAV_MISSION_ACCEPTED if msg.count == 0 else mavlink.MAV_MISSION_UNSUPPORTED  # type: ignore[attr-defined]
        self._send(self._mav.mission_ack_encode(msg.get_srcSystem(), msg.get_srcComponent(), result,  # type: ignore[attr-defined]
                                                getattr(msg, "mission_type", 0)))  # fmt: skip

    def _on_mission_clear_all(self, msg: object, now: float) -> None:
        self._send(self._mav.mission_ack_encode(msg.get_srcSystem(), msg.get_srcComponent(),  # type: ignore[attr-defined]
                                                mavlink.MAV_MISSION_ACCEPTED, getattr(msg, "mission_type", 0)))  # fmt: skip

    def _on_timesync(self, msg: object, now: float) -> None:
        if msg.tc1 == 0:  # type: ignore[attr-defined]
            self._send(self._mav.timesync_encode(int(now * 1e9), msg.ts1))  # type: ignore[attr-defined]
