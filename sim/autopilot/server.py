"""The autopilot emulator: one :class:`~sim.autopilot.vehicle.Vehicle` behind a MAVLink endpoint.

:class:`AutopilotEmulator` speaks MAVLink 2 (pymavlink's generated ``ardupilotmega`` dialect, a
superset of ``common``) over UDP or TCP so that unmodified clients (pymavlink scripts, MAVSDK,
MAVProxy) can fly it.  This module is the loop and the command handling; the layers below are
:mod:`~sim.autopilot.transport` (sockets), :mod:`~sim.autopilot.framing` (MAVLink objects),
:mod:`~sim.autopilot.telemetry` (messages from a vehicle snapshot), :mod:`~sim.autopilot.streams`
(stream rates) and :mod:`~sim.autopilot.setpoints` (SET_POSITION_TARGET_* to local NED).

Endpoints, as pymavlink/MAVSDK users write them (parsed by :mod:`fisc_agent.mavlink.endpoints`):

* ``udpin:0.0.0.0:14540`` (also ``udp:``): listen; reply to every peer that has sent something;
* ``udpout:127.0.0.1:14550``: send to that address (e.g. MAVSDK's ``udpin://0.0.0.0:14550``);
  replies are read on the same socket;
* ``tcpin:0.0.0.0:5760``: TCP server, any number of clients;
* ``tcp:127.0.0.1:5760`` (also ``tcpout:``): TCP client, reconnecting every second.

Geodesy: home (``home_lla``) is the origin of local NED on the WGS-84 ellipsoid, in the agent's own
model (:class:`fisc_agent.flight.frames.GeodeticAnchor`).

Threading: :meth:`AutopilotEmulator.start` runs the loop in a daemon thread; :meth:`poll` is one
loop iteration (usable by a caller that multiplexes many emulators in one thread);
:attr:`AutopilotEmulator.state` is an immutable snapshot safe to read from any thread.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import select
import threading
import time
from typing import Callable

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from fisc_agent.flight.frames import GeodeticAnchor
from sim.autopilot.faults import DelayLine, FaultConfig, FaultInjector
from sim.autopilot.framing import Encoder, new_parser, parse
from sim.autopilot.personalities import Personality, get_personality
from sim.autopilot.setpoints import resolve_global_setpoint, resolve_local_setpoint, takeoff_altitude_m
from sim.autopilot.streams import StreamSchedule
from sim.autopilot.telemetry import POSITION_MESSAGES, TelemetryBuilder, default_intervals_s
from sim.autopilot.transport import PEER_LIMIT, Transport, open_transport, parse_emulator_endpoint
from sim.autopilot.vehicle import Vehicle
from sim.autopilot.vehicle_types import ACCEPTED, DENIED, UNSUPPORTED, Outcome, Setpoint, VehicleConfig, VehicleState
from sim.plant.model import PlantParams, VelocityPlant

__all__ = ["AutopilotEmulator", "DEFAULT_HOME_LLA"]

_log = logging.getLogger(__name__)

DEFAULT_HOME_LLA = (47.397742, 8.545594, 488.0)
"""Geodetic origin of local NED (PX4 SITL's default, Zurich): lat [deg], lon [deg], alt AMSL [m]."""

_FORCE_DISARM_MAGIC = 21196
"""MAV_CMD_COMPONENT_ARM_DISARM param2 that forces (dis)arming (PX4 and ArduPilot)."""


def _int(x: float, default: int = 0) -> int:
    """Command parameter as int (MAVSDK and others send NaN for "unused")."""
    return int(round(x)) if math.isfinite(x) else default


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
        self.endpoint = parse_emulator_endpoint(url)
        self.personality = personality if isinstance(personality, Personality) else get_personality(personality)
        self.sysid, self.compid = int(sysid), int(compid)
        self.home_lla = tuple(float(x) for x in home_lla)
        try:
            self.anchor = GeodeticAnchor(*self.home_lla, heading_deg=0.0)
            """Home as the WGS-84 origin of local NED."""
        except (TypeError, ValueError) as exc:
            raise ValueError(f"home_lla {home_lla!r}: expected (lat, lon, alt) with |lat| <= 89 deg ({exc})") from None
        cfg = dataclasses.replace(vehicle_config or VehicleConfig(), start_ned_m=tuple(float(x) for x in start_ned))
        self._clock, self._wall = clock, wall_clock
        self._t0 = clock()
        self.vehicle = Vehicle(self.personality, cfg, sysid=self.sysid, t0_s=0.0)
        self.faults = FaultInjector(FaultConfig(loss, latency_s, tuple(position_dropouts), seed))
        self._encoder = Encoder(self.sysid, self.compid)
        self._mav = self._encoder.mav
        self._parsers: dict[object, mavlink.MAVLink] = {}
        self._delay: DelayLine[bytes] = DelayLine()
        self._transport: Transport | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.RLock()  # re-entrant: `state` may be read from a handler inside poll()
        self._schedule = StreamSchedule(default_intervals_s(rate_position_hz, rate_attitude_hz))
        self._telemetry = TelemetryBuilder(self._mav, self.personality, self.anchor, self.sysid, wall_clock)
        self._builders = self._telemetry.builders
        self._payloads = self._telemetry.payloads
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
        self._announced = (self.vehicle.armed, self.personality.custom_mode(self.vehicle.mode))

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Open the endpoint (done by :meth:`start`/:meth:`run`; idempotent)."""
        if self._transport is None:
            self._transport = open_transport(self.endpoint, self._clock)
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
                self._schedule.due_now(mavlink.MAVLINK_MSG_ID_HEARTBEAT, now)
                self._schedule.due_now(mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, now)
            next_due = self._schedule.run(now, lambda msg_id: self._send_message_id(msg_id, now))
            if self._delay:  # latency fault injection only
                for buf in self._delay.pop_due(now):
                    self._transport.send(buf)
                next_due = min(next_due, self._delay.next_due())
            return float(min(max(next_due - self.time_s, 0.0), 0.05))

    # ------------------------------------------------------------------ output
    def _send(self, msg: object) -> None:
        self._send_frame(self._encoder.frame(msg))

    def _send_frame(self, buf: bytes) -> None:
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
        if msg_id in POSITION_MESSAGES and self.faults.position_dropout(now):
            self.stats["position_suppressed"] += 1
            return True
        if self._transport is not None and not self._transport.has_peers:
            return True  # nobody listening yet (udpin before the first packet): skip the encoding
        fast = self._payloads.get(msg_id)
        if fast is not None:
            self._send_frame(self._encoder.frame_payload(msg_id, fast[0], fast[1](self._snapshot())))
        else:
            self._send(build(self._snapshot()))
        return True

    def _statustext(self, severity: int, text: str) -> None:
        self._send(self._mav.statustext_encode(severity, text.encode("ascii", "replace")[:50]))

    def _param_value(self, index: int) -> object:
        return self._telemetry.param_value(index, self.vehicle.params)

    # ------------------------------------------------------------------ input
    def _receive(self, key: object, data: bytes, now: float) -> None:
        parser = self._parsers.get(key)
        if parser is None:
            if len(self._parsers) > 4 * PEER_LIMIT:
                self._parsers.clear()
            parser = self._parsers[key] = new_parser()
            self._schedule.due_now(mavlink.MAVLINK_MSG_ID_HEARTBEAT, now)  # greet a new peer at once
        try:
            msgs = parse(parser, data)
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
            home_amsl_m = self.anchor.alt_m - float(veh.home[2])
            out = veh.takeoff(now, takeoff_altitude_m(p[6], frame, home_amsl_m, self.personality.name == "px4"))
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

    def _set_interval(self, msg_id: int, interval_us: float, now: float) -> Outcome:
        if msg_id not in self._builders or msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return Outcome(UNSUPPORTED)
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            return Outcome(DENIED, "HEARTBEAT rate is fixed")
        self._schedule.set_interval_us(msg_id, interval_us, now)
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
        m, veh = msg, self.vehicle
        veh.step(now)
        self._fly_setpoint(m, now, resolve_local_setpoint(
            m.coordinate_frame, m.type_mask, (m.x, m.y, m.z), (m.vx, m.vy, m.vz), m.yaw, m.yaw_rate,  # type: ignore[attr-defined]
            tuple(veh.pos.tolist()), veh.yaw, (m.afx, m.afy, m.afz),  # type: ignore[attr-defined]
        ))  # fmt: skip

    def _on_set_position_target_global_int(self, msg: object, now: float) -> None:
        m, veh = msg, self.vehicle
        veh.step(now)
        self._fly_setpoint(m, now, resolve_global_setpoint(
            m.coordinate_frame, m.type_mask, m.lat_int, m.lon_int, m.alt, (m.vx, m.vy, m.vz), m.yaw, m.yaw_rate,  # type: ignore[attr-defined]
            self.anchor, float(veh.home[2]), tuple(veh.pos.tolist()), veh.yaw, (m.afx, m.afy, m.afz),  # type: ignore[attr-defined]
        ))  # fmt: skip

    def _fly_setpoint(self, msg: object, now: float, sp: Setpoint | None) -> None:
        """Hand a resolved SET_POSITION_TARGET_* to the vehicle (None: its frame is not supported)."""
        if sp is None:
            _log.warning("%s frame %d not supported; ignored", msg.get_type(), msg.coordinate_frame)  # type: ignore[attr-defined]
            return
        self.stats["setpoints"] += 1
        self.vehicle.set_setpoint(sp, now)

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
