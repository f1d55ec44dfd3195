"""Optional MAVSDK backend (``--backend mavsdk``): the same ``VehicleLink`` interface over MAVSDK.

For teams that already run MAVSDK on the companion computer.  PX4 only (MAVSDK's offboard,
action and telemetry plugins follow PX4 semantics).  Uses the synchronous MAVSDK (>= 3, C
library ``cmavsdk``) Python API; ``mavsdk`` is imported only when this backend is used, so
the agent stays lean without it.

Mapping onto the runner's interface (one code path with the pymavlink link):

- telemetry callbacks (position_velocity_ned or position, armed, flight_mode) update the
  position, ``armed`` and ``mode`` (MAVSDK's ``FlightMode`` as a ``ModeClass``);
- the fixes carry the autopilot's own time (``PositionSample.autopilot_t_s``): MAVSDK's
  position_velocity_ned has none, so the newest ODOMETRY's ``time_usec`` (PX4 streams it with the
  local position, at the same rate) stands in, plus the receive-time gap since it
  (``autopilot_time``);
- ``send_velocity_ned`` -> ``offboard.set_velocity_ned`` (yaw held at the current heading);
- intents are MAVSDK's own actions: ``arm`` -> ``action.arm()``, ``set_mode(OFFBOARD)`` ->
  ``offboard.start()``, ``hold`` -> ``action.hold()``, ``land`` -> ``action.land()``,
  ``takeoff`` -> ``action.set_takeoff_altitude`` + ``action.takeoff()``.  The blocking calls run
  on a worker thread; each outcome comes back as a ``CommandResult`` (``pop_results``) so the
  ``Commander`` retries and logs refusals as with pymavlink.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Callable

from fisc_agent.mavlink.adapters import Adapter, CommandKind, CommandResult, ModeClass
from fisc_agent.mavlink.endpoints import Endpoint, parse_endpoint
from fisc_agent.flight.frames import GeodeticAnchor
from fisc_agent.mavlink.link import PositionSample

log = logging.getLogger(__name__)

#: An ODOMETRY time stamp older than this (receive time) no longer dates a position fix [s].
ODOMETRY_STAMP_MAX_AGE_S = 0.5


def autopilot_time(stamp: tuple[float, float] | None, now_s: float) -> float | None:
    """The autopilot's clock at receive time ``now_s``, from ``stamp`` = (receive time, autopilot time)
    of the newest ODOMETRY message: its time plus the receive-time gap since it; None without a stamp
    or with one older than ``ODOMETRY_STAMP_MAX_AGE_S``.

    The agent learns its velocity-estimate bias from the position's rate of change between fixes
    (``fisc_agent.flight.tracking.ParcelTracker.observe``), which needs the fixes' own times: on receive times,
    a PX4 SITL running at 0.75 x real time on a loaded host read as a bias of a quarter of the speed,
    and the vehicle flew that much too fast (truth velocity nRMSE 0.129, docs/deployment.md)."""
    if stamp is None:
        return None
    gap = now_s - stamp[0]
    return stamp[1] + gap if 0.0 <= gap <= ODOMETRY_STAMP_MAX_AGE_S else None


#: MAVSDK telemetry FlightMode name -> mode class (every other flight mode is OTHER).
MODE_CLASS_OF = {"OFFBOARD": ModeClass.OFFBOARD, "HOLD": ModeClass.HOLD, "LAND": ModeClass.LAND}


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
        self.last_heartbeat_t: float | None = None
        self._mode = ModeClass.UNKNOWN
        self._position: PositionSample | None = None
        self._odometry_stamp: tuple[float, float] | None = None
        self._heading_deg = 0.0
        self._results: list[CommandResult] = []
        self._lock = threading.Lock()
        self._jobs: queue.Queue = queue.Queue()
        self._mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER))
        url = mavsdk_url(self.endpoint)
        result = self._mavsdk.add_any_connection(url)
        log.info("MAVSDK connection %s: %s", url, result)
        self._system = self._mavsdk.first_autopilot(connect_timeout_s)
        if self._system is None:
            raise ConnectionError(f"MAVSDK: no autopilot on {url} within {connect_timeout_s:.0f} s")
        from mavsdk.exceptions import MavsdkError
        from mavsdk.plugins.action import Action
        from mavsdk.plugins.offboard import Offboard, VelocityNedYaw
        from mavsdk.plugins.telemetry import Telemetry

        self._VelocityNedYaw = VelocityNedYaw
        self._error_type = MavsdkError
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
            t.subscribe_odometry(self._on_odometry)  # for its time stamp only (``autopilot_time``)
        else:
            t.subscribe_position(self._on_global)
        t.subscribe_armed(self._on_armed)
        t.subscribe_flight_mode(self._on_mode)
        t.subscribe_heading(lambda h, _ud=None: setattr(self, "_heading_deg", float(h.heading_deg)))

    def _alive(self) -> None:
        self.last_heartbeat_t = self.clock() if self._system.is_connected() else self.last_heartbeat_t

    def _on_pos_vel(self, pv, _ud=None) -> None:
        p, v = pv.position, pv.velocity
        now = self.clock()
        self._position = PositionSample(now, (p.north_m, p.east_m, p.down_m), (v.north_m_s, v.east_m_s, v.down_m_s),
                                        autopilot_time(self._odometry_stamp, now))
        self._alive()

    def _on_odometry(self, odo, _ud=None) -> None:
        if odo.time_usec > 0:
            self._odometry_stamp = (self.clock(), odo.time_usec * 1e-6)

    def _on_global(self, pos, _ud=None) -> None:
        ned = self.anchor.geodetic_to_ned(pos.latitude_deg, pos.longitude_deg, pos.absolute_altitude_m)
        prev = self._position
        vel = prev.vel_ned_m_s if prev is not None else (0.0, 0.0, 0.0)
        self._position = PositionSample(self.clock(), ned, vel)
        self._alive()

    def _on_armed(self, armed, _ud=None) -> None:
        self.armed = bool(armed)
        self._alive()

    def _on_mode(self, mode, _ud=None) -> None:
        self._mode = MODE_CLASS_OF.get(getattr(mode, "name", str(mode)), ModeClass.OTHER)
        self._alive()

    # ---- VehicleLink --------------------------------------------------------------------
    @property
    def mode(self) -> ModeClass:
        """The vehicle's mode class from MAVSDK's flight mode (``UNKNOWN`` before the first one)."""
        return self._mode if self.last_heartbeat_t is not None else ModeClass.UNKNOWN

    def use_adapter(self, adapter: Adapter) -> None:
        """MAVSDK encodes the commands itself; only PX4's semantics are supported."""
        if adapter.name != "px4":
            log.warning("MAVSDK backend: the %s adapter was chosen; MAVSDK's actions follow PX4", adapter.name)

    def poll(self) -> int:
        """Refresh link liveness from MAVSDK's connection state; MAVSDK's own threads deliver messages, so 0."""
        if self._system.is_connected() and self.last_heartbeat_t is not None:
            self.last_heartbeat_t = max(self.last_heartbeat_t, self.clock() - 0.5)
        return 0

    def latest_position(self) -> PositionSample | None:
        """The newest position from MAVSDK's telemetry plugin, or None if none arrived yet."""
        return self._position

    def send_velocity_ned(self, vn: float, ve: float, vd: float) -> None:
        """Send one velocity setpoint through MAVSDK's offboard plugin [m/s], yaw held."""
        self._offboard.set_velocity_ned(self._VelocityNedYaw(vn, ve, vd, self._heading_deg))

    def arm(self) -> None:
        """Queue MAVSDK's ``action.arm``; its answer arrives through ``pop_results``."""
        self._jobs.put((CommandKind.ARM, self._action.arm))

    def set_mode(self, mode: ModeClass) -> None:
        """Queue the MAVSDK action for ``mode`` (``offboard.start``, ``action.hold``, ``action.land``)."""
        action = {ModeClass.OFFBOARD: self._offboard.start, ModeClass.HOLD: self._action.hold,
                  ModeClass.LAND: self._action.land}.get(ModeClass(mode))
        if action is None:
            raise ValueError(f"MAVSDK backend: cannot request mode {mode!r}; choose offboard, hold or land")
        self._jobs.put((CommandKind.SET_MODE, action))

    def takeoff(self, alt_m: float) -> None:
        """Queue MAVSDK's ``action.takeoff`` to ``alt_m`` metres."""
        def _takeoff() -> None:
            self._action.set_takeoff_altitude(float(alt_m))
            self._action.takeoff()

        self._jobs.put((CommandKind.TAKEOFF, _takeoff))

    def hold(self) -> None:
        """Queue MAVSDK's ``action.hold``."""
        self.set_mode(ModeClass.HOLD)

    def land(self) -> None:
        """Queue MAVSDK's ``action.land``."""
        self.set_mode(ModeClass.LAND)

    def send_heartbeat(self) -> None:
        """MAVSDK sends its own heartbeats."""

    def pop_results(self) -> list[CommandResult]:
        """The outcomes of MAVSDK actions since the last call, oldest first."""
        with self._lock:
            results, self._results = self._results, []
        return results

    def close(self) -> None:
        """Stop the action worker and MAVSDK's server."""
        self._jobs.put(None)
        self._worker.join(timeout=2)
        self._mavsdk.destroy()

    # ---- blocking MAVSDK calls on the worker -------------------------------------------
    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            kind, call = job
            try:
                call()
                res = CommandResult(kind, True, "SUCCESS")
            except self._error_type as exc:  # ActionError / OffboardError carry MAVSDK's result
                log.warning("MAVSDK %s failed: %s", kind.value, exc)
                result = getattr(exc, "result", None)
                res = CommandResult(kind, False, getattr(result, "name", type(exc).__name__))
            except Exception as exc:  # a bug must not stop the worker (later commands would be lost): log it whole
                log.exception("MAVSDK %s raised", kind.value)
                res = CommandResult(kind, False, type(exc).__name__)
            with self._lock:
                self._results.append(res)
