"""Optional MAVSDK backend (``--backend mavsdk``): the same ``VehicleLink`` interface over MAVSDK.

For teams that already run MAVSDK on the companion computer.  PX4 only (MAVSDK's offboard,
action and telemetry plugins follow PX4 semantics).  Uses the synchronous MAVSDK (>= 3, C
library ``cmavsdk``) Python API; ``mavsdk`` is imported only when this backend is used, so
the agent stays lean without it.

Mapping onto the runner's interface (one code path with the pymavlink link):

- telemetry callbacks (position_velocity_ned or position, armed, flight_mode) update the same
  state fields ``MavlinkLink`` has; the flight mode is re-encoded as a PX4 HEARTBEAT
  ``custom_mode`` so ``adapters.Px4Adapter.classify_mode`` reads it unchanged;
- ``send_velocity_ned`` -> ``offboard.set_velocity_ned`` (yaw held at the current heading);
- ``send_command`` translates the adapter's COMMAND_LONGs: DO_SET_MODE OFFBOARD ->
  ``offboard.start()``, AUTO.LOITER -> ``action.hold()``, AUTO.LAND -> ``action.land()``,
  ARM -> ``action.arm()``, SET_MESSAGE_INTERVAL -> ``telemetry.set_rate_position_velocity_ned``.
  The blocking MAVSDK calls run on a worker thread; their results come back as COMMAND_ACKs
  (``pop_acks``) so the ``Commander`` logs refusals exactly as with pymavlink.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Callable

from fisc_agent.adapters import (MAV_CMD_COMPONENT_ARM_DISARM, MAV_CMD_DO_SET_MODE, MAV_CMD_SET_MESSAGE_INTERVAL,
                                 MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MAV_MODE_FLAG_SAFETY_ARMED, PX4_MAIN_AUTO,
                                 PX4_MAIN_OFFBOARD, PX4_SUB_AUTO_LAND, PX4_SUB_AUTO_LOITER, CommandLong, Px4Adapter)
from fisc_agent.endpoints import Endpoint, parse_endpoint
from fisc_agent.frames import GeodeticAnchor
from fisc_agent.link import PositionSample

log = logging.getLogger(__name__)

MAV_RESULT_ACCEPTED, MAV_RESULT_DENIED, MAV_RESULT_UNSUPPORTED = 0, 2, 3

#: MAVSDK telemetry FlightMode name -> PX4 (main, sub) mode.
_PX4_MODE_OF = {"OFFBOARD": (6, 0), "HOLD": (4, 3), "LAND": (4, 6), "TAKEOFF": (4, 2), "READY": (4, 1),
                "MISSION": (4, 4), "RETURN_TO_LAUNCH": (4, 5), "MANUAL": (1, 0), "ALTCTL": (2, 0),
                "POSCTL": (3, 0), "ACRO": (5, 0), "STABILIZED": (7, 0)}


def mavsdk_url(ep: Endpoint) -> str:
    """The MAVSDK connection URL of an endpoint (MAVSDK >= 2 syntax)."""
    if ep.kind == "serial":
        return f"serial://{ep.host}:{ep.baud}"
    scheme = {"udpin": "udpin", "udpout": "udpout", "udpbcast": "udpout", "tcp": "tcpout", "tcpin": "tcpin"}[ep.kind]
    return f"{scheme}://{ep.host}:{ep.port}"


class MavsdkLink:
    """``VehicleLink`` over MAVSDK (PX4)."""

    def __init__(self, endpoint: Endpoint | str, anchor: GeodeticAnchor | None = None,
                 connect_timeout_s: float = 10.0, clock: Callable[[], float] = time.monotonic) -> None:
        try:
            from mavsdk import ComponentType, Configuration, Mavsdk
        except ImportError as exc:  # optional dependency
            raise RuntimeError("--backend mavsdk needs the optional 'mavsdk' package (pip install fisc[mavsdk])") from exc
        self.endpoint = parse_endpoint(endpoint) if isinstance(endpoint, str) else endpoint
        self.anchor, self.clock = anchor, clock
        self.autopilot: str | None = None
        self.armed = False
        self.base_mode = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        self.custom_mode = 0
        self.last_heartbeat_t: float | None = None
        self._position: PositionSample | None = None
        self._heading_deg = 0.0
        self._acks: list[tuple[int, int]] = []
        self._lock = threading.Lock()
        self._jobs: queue.Queue = queue.Queue()
        self._mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER))
        url = mavsdk_url(self.endpoint)
        result = self._mavsdk.add_any_connection(url)
        log.info("MAVSDK connection %s: %s", url, result)
        self._system = self._mavsdk.first_autopilot(connect_timeout_s)
        if self._system is None:
            raise ConnectionError(f"MAVSDK: no autopilot on {url} within {connect_timeout_s:.0f} s")
        from mavsdk.plugins.action import Action
        from mavsdk.plugins.offboard import Offboard, VelocityNedYaw
        from mavsdk.plugins.telemetry import Telemetry

        self._VelocityNedYaw = VelocityNedYaw
        self._telemetry, self._action, self._offboard = Telemetry(self._system), Action(self._system), Offboard(self._system)
        self.autopilot = "px4" if self._system.autopilot_type().name == "PX4" else None
        if self.autopilot is None:
            log.warning("MAVSDK backend: autopilot is %s; only PX4 is supported", self._system.autopilot_type().name)
        self._subscribe()
        self._worker = threading.Thread(target=self._work, daemon=True, name="mavsdk-commands")
        self._worker.start()

    # ---- telemetry callbacks (MAVSDK threads) -----------------------------------------
    def _subscribe(self) -> None:
        t = self._telemetry
        if self.anchor is None:
            t.subscribe_position_velocity_ned(self._on_pos_vel)
        else:
            t.subscribe_position(self._on_global)
        t.subscribe_armed(self._on_armed)
        t.subscribe_flight_mode(self._on_mode)
        t.subscribe_heading(lambda h, _ud=None: setattr(self, "_heading_deg", float(h.heading_deg)))

    def _alive(self) -> None:
        self.last_heartbeat_t = self.clock() if self._system.is_connected() else self.last_heartbeat_t

    def _on_pos_vel(self, pv, _ud=None) -> None:
        p, v = pv.position, pv.velocity
        self._position = PositionSample(self.clock(), (p.north_m, p.east_m, p.down_m),
                                        (v.north_m_s, v.east_m_s, v.down_m_s))
        self._alive()

    def _on_global(self, pos, _ud=None) -> None:
        ned = self.anchor.geodetic_to_ned(pos.latitude_deg, pos.longitude_deg, pos.absolute_altitude_m)
        prev = self._position
        vel = prev.vel_ned_m_s if prev is not None else (0.0, 0.0, 0.0)
        self._position = PositionSample(self.clock(), ned, vel)
        self._alive()

    def _on_armed(self, armed, _ud=None) -> None:
        self.armed = bool(armed)
        flags = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
        self.base_mode = flags
        self._alive()

    def _on_mode(self, mode, _ud=None) -> None:
        main, sub = _PX4_MODE_OF.get(getattr(mode, "name", str(mode)), (0, 0))
        self.custom_mode = Px4Adapter.px4_custom_mode(main, sub)
        self._alive()

    # ---- VehicleLink --------------------------------------------------------------------
    def poll(self) -> int:
        if self._system.is_connected() and self.last_heartbeat_t is not None:
            self.last_heartbeat_t = max(self.last_heartbeat_t, self.clock() - 0.5)
        return 0

    def latest_position(self) -> PositionSample | None:
        return self._position

    def send_velocity_ned(self, vn: float, ve: float, vd: float) -> None:
        self._offboard.set_velocity_ned(self._VelocityNedYaw(vn, ve, vd, self._heading_deg))

    def send_command(self, cmd: CommandLong) -> None:
        self._jobs.put(cmd)

    def send_heartbeat(self) -> None:
        """MAVSDK sends its own heartbeats."""

    def pop_acks(self) -> list[tuple[int, int]]:
        with self._lock:
            acks, self._acks = self._acks, []
        return acks

    def close(self) -> None:
        self._jobs.put(None)
        self._worker.join(timeout=2)
        self._mavsdk.destroy()

    # ---- blocking MAVSDK calls on the worker -------------------------------------------
    def _call(self, cmd: CommandLong):
        p = cmd.params
        if cmd.command == MAV_CMD_COMPONENT_ARM_DISARM:
            return self._action.arm() if p[0] > 0.5 else self._action.disarm()
        if cmd.command == MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._telemetry.set_rate_position_velocity_ned(1e6 / max(p[1], 1.0))
        if cmd.command == MAV_CMD_DO_SET_MODE:
            main, sub = int(p[1]), int(p[2])
            if main == PX4_MAIN_OFFBOARD:
                return self._offboard.start()
            if (main, sub) == (PX4_MAIN_AUTO, PX4_SUB_AUTO_LOITER):
                return self._action.hold()
            if (main, sub) == (PX4_MAIN_AUTO, PX4_SUB_AUTO_LAND):
                return self._action.land()
        raise NotImplementedError(cmd.label)

    def _work(self) -> None:
        while True:
            cmd = self._jobs.get()
            if cmd is None:
                return
            try:
                self._call(cmd)
                result = MAV_RESULT_ACCEPTED
            except NotImplementedError:
                result = MAV_RESULT_UNSUPPORTED
            except Exception as exc:  # MAVSDK raises ActionError/OffboardError/TelemetryError
                log.warning("MAVSDK %s failed: %s", cmd.label, exc)
                result = MAV_RESULT_DENIED
            with self._lock:
                self._acks.append((cmd.command, result))
