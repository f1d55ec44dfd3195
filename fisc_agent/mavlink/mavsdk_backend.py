"""Optional MAVSDK backend (``--backend mavsdk``): the same ``VehicleLink`` interface over MAVSDK.

For teams that already run MAVSDK on the companion computer.  PX4 only (MAVSDK's offboard,
action and telemetry plugins follow PX4 semantics).  Uses the synchronous MAVSDK (>= 3, C
library ``cmavsdk``) Python API; ``mavsdk`` is imported only when this backend is used, so
the agent stays lean without it.

Mapping onto the runner's interface (one code path with the pymavlink link):

- telemetry callbacks (position_velocity_ned or position, armed, flight_mode) update the
  position, ``armed`` and ``mode`` (MAVSDK's ``FlightMode`` as a ``ModeClass``); MAVSDK reports the
  flight mode on every HEARTBEAT, which dates the mode (``mode_t_s``) as on the pymavlink link;
- the fixes carry the autopilot's own time (``PositionSample.autopilot_t_s``): MAVSDK's
  position_velocity_ned has none, so the newest ODOMETRY's ``time_usec`` (PX4 streams it with the
  local position, at the same rate) stands in, plus the receive-time gap since it
  (``autopilot_time``);
- ``send_velocity_ned`` -> ``offboard.set_velocity_ned`` (yaw held at the current heading);
- with a geodetic anchor the fixes come from ``position`` and carry the newest ``velocity_ned``
  (MAVSDK's position has no velocity);
- the GNSS receiver's velocity (``latest_gnss_velocity``) from ``raw_gps`` (asked for at ``GNSS_RATE_HZ``)
  with the fix type of ``gps_info``, as the pymavlink link reads GPS_RAW_INT;
- ``health``: battery % (``battery``), landed state (``landed_state``) and the estimator's local
  (and, with an anchor, global) position flags (``health``); the rest stays unknown.  ``integrity``:
  ``fisc_agent.flight.integrity`` over the fixes and the estimator flags (MAVSDK gives no reset counter);
- **watchdog**: MAVSDK re-sends the last offboard setpoint on its own; when the vehicle flies OFFBOARD
  and the control thread has sent no setpoint for ``SETPOINT_STALL_S``, the watchdog thread calls
  ``offboard.stop()`` (MAVSDK stops streaming and requests Hold) and counts it in ``watchdog_trips``;
  the next ``send_velocity_ned`` re-arms it.  Outside OFFBOARD it does nothing (the stop's Hold would
  override a pilot or a failsafe), so MAVSDK's stale setpoint stream then goes on until the next
  setpoint or ``close`` (PX4 ignores it outside OFFBOARD);
- intents are MAVSDK's own actions: ``arm`` -> ``action.arm()``, ``set_mode(OFFBOARD)`` ->
  ``offboard.start()``, ``hold`` -> ``action.hold()``, ``land`` -> ``action.land()``,
  ``takeoff`` -> ``action.set_takeoff_altitude`` + ``action.takeoff()``.  The blocking calls run
  on a worker thread from a queue bounded at ``MAX_QUEUED_JOBS`` (when full the oldest job is dropped
  and counted in ``jobs_dropped``); each outcome comes back as a ``CommandResult`` (``pop_results``) so
  the ``Commander`` retries and logs refusals as with pymavlink.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Callable

from dataclasses import replace

from fisc_agent.flight.frames import GeodeticAnchor
from fisc_agent.flight.health import LandedState, VehicleHealth
from fisc_agent.flight.integrity import IntegrityMonitor, IntegrityVerdict
from fisc_agent.mavlink.adapters import Adapter, CommandKind, CommandResult, ModeClass
from fisc_agent.mavlink.endpoints import Endpoint, parse_endpoint
from fisc_agent.mavlink.gnss import mavsdk_ground_velocity
from fisc_agent.mavlink.health_reader import GNSS_RATE_HZ
from fisc_agent.mavlink.interfaces import GnssVelocity, PositionSample

log = logging.getLogger(__name__)

MAX_QUEUED_JOBS = 16
"""Commands waiting for the MAVSDK worker; beyond this the oldest is dropped (``jobs_dropped``)."""
SETPOINT_STALL_S = 0.5
"""No setpoint from the control thread for longer than this stops MAVSDK's setpoint stream [s]."""
WATCHDOG_PERIOD_S = 0.1
"""How often the watchdog looks [s]."""

#: MAVSDK telemetry LandedState name -> ``LandedState``.
LANDED_OF = {"ON_GROUND": LandedState.ON_GROUND, "IN_AIR": LandedState.IN_AIR, "TAKING_OFF": LandedState.TAKEOFF,
             "LANDING": LandedState.LANDING}


def setpoint_stalled(last_setpoint_s: float | None, now_s: float, in_offboard: bool,
                     stall_s: float = SETPOINT_STALL_S) -> bool:
    """True when the watchdog must stop MAVSDK's setpoint stream: the vehicle flies OFFBOARD, setpoints
    were streaming (``last_setpoint_s`` not None) and the newest is older than ``stall_s``.  Outside
    OFFBOARD it never trips: ``offboard.stop()`` also requests Hold, which would override a pilot's or a
    failsafe's mode."""
    return in_offboard and last_setpoint_s is not None and now_s - last_setpoint_s > stall_s


class DropOldestQueue:
    """A thread-safe FIFO of at most ``maxsize`` items; a put on a full queue drops the oldest (counted)."""

    def __init__(self, maxsize: int) -> None:
        if maxsize < 1:
            raise ValueError(f"maxsize must be >= 1, got {maxsize}")
        self._q: queue.Queue = queue.Queue(maxsize)
        self._put_lock = threading.Lock()
        self.dropped = 0
        """Items dropped because the queue was full."""

    def put(self, item) -> None:
        """Append ``item``; drops the oldest item first when full (never blocks)."""
        with self._put_lock:
            while True:
                try:
                    self._q.put_nowait(item)
                    return
                except queue.Full:
                    try:
                        self._q.get_nowait()
                        self.dropped += 1
                    except queue.Empty:
                        pass

    def get(self, timeout_s: float | None = None):
        """The oldest item (blocks up to ``timeout_s``; raises ``queue.Empty`` after it)."""
        return self._q.get(timeout=timeout_s)

    def qsize(self) -> int:
        """Items waiting."""
        return self._q.qsize()

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
        self._mode_t_s: float | None = None
        self._position: PositionSample | None = None
        self._odometry_stamp: tuple[float, float] | None = None
        self._heading_deg = 0.0
        self._results: list[CommandResult] = []
        self._lock = threading.Lock()
        self._jobs = DropOldestQueue(MAX_QUEUED_JOBS)
        self._health = VehicleHealth()
        self._integrity = IntegrityMonitor()
        self._vel_ned: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._gnss: GnssVelocity | None = None
        self._gnss_fix_type = 0
        self._last_setpoint_s: float | None = None
        self._stop = threading.Event()
        self.watchdog_trips = 0
        """Times the watchdog stopped MAVSDK's setpoint stream (the control thread had stalled)."""
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
        self._watchdog = threading.Thread(target=self._watch, daemon=True, name="mavsdk-watchdog")
        self._watchdog.start()

    # ---- telemetry callbacks (MAVSDK threads) -----------------------------------------
    def _subscribe(self) -> None:
        t = self._telemetry
        if self.anchor is None:
            t.subscribe_position_velocity_ned(self._on_pos_vel)
            t.subscribe_odometry(self._on_odometry)  # for its time stamp only (``autopilot_time``)
        else:
            t.subscribe_position(self._on_global)
            t.subscribe_velocity_ned(self._on_velocity)
        t.subscribe_battery(self._on_battery)
        t.subscribe_landed_state(self._on_landed)
        t.subscribe_health(self._on_health)
        t.subscribe_armed(self._on_armed)
        t.subscribe_flight_mode(self._on_mode)
        t.subscribe_heading(lambda h, _ud=None: setattr(self, "_heading_deg", float(h.heading_deg)))
        t.subscribe_gps_info(self._on_gps_info)
        t.subscribe_raw_gps(self._on_raw_gps)
        t.set_rate_raw_gps_async(GNSS_RATE_HZ, lambda result, _ud=None: log.debug("raw GPS rate: %s", result))

    def _alive(self) -> None:
        self.last_heartbeat_t = self.clock() if self._system.is_connected() else self.last_heartbeat_t

    def _on_pos_vel(self, pv, _ud=None) -> None:
        p, v = pv.position, pv.velocity
        now = self.clock()
        self._set_position(PositionSample(now, (p.north_m, p.east_m, p.down_m), (v.north_m_s, v.east_m_s, v.down_m_s),
                                          autopilot_time(self._odometry_stamp, now)))
        self._alive()

    def _set_position(self, sample: PositionSample) -> None:
        with self._lock:
            self._integrity.on_fix(sample.t_s, sample.pos_ned_m, sample.vel_ned_m_s, sample.autopilot_t_s)
            self._log_integrity()
        self._position = sample

    def _log_integrity(self) -> None:
        for event in self._integrity.pop_events():
            v = event.verdict
            log.warning("position integrity %s", "OK again (re-anchored)" if v.ok else
                        f"DISRUPTED ({v.reason.value}): {v.detail}")

    def _on_odometry(self, odo, _ud=None) -> None:
        if odo.time_usec > 0:
            self._odometry_stamp = (self.clock(), odo.time_usec * 1e-6)

    def _on_global(self, pos, _ud=None) -> None:
        ned = self.anchor.geodetic_to_ned(pos.latitude_deg, pos.longitude_deg, pos.absolute_altitude_m)
        self._set_position(PositionSample(self.clock(), ned, self._vel_ned))
        self._alive()

    def _on_gps_info(self, info, _ud=None) -> None:
        self._gnss_fix_type = int(info.fix_type)

    def _on_raw_gps(self, raw, _ud=None) -> None:
        self._gnss = mavsdk_ground_velocity(self.clock(), self._gnss_fix_type, float(raw.velocity_m_s),
                                            float(raw.cog_deg)) or self._gnss

    def _on_velocity(self, v, _ud=None) -> None:
        self._vel_ned = (float(v.north_m_s), float(v.east_m_s), float(v.down_m_s))

    def _on_battery(self, b, _ud=None) -> None:
        pct = float(b.remaining_percent)
        if int(getattr(b, "id", 0)) == 0 and 0.0 <= pct <= 100.0:  # NaN: not reported
            self._health = replace(self._health, battery_pct=pct)

    def _on_landed(self, state, _ud=None) -> None:
        self._health = replace(self._health, landed=LANDED_OF.get(getattr(state, "name", ""), LandedState.UNKNOWN))

    def _on_health(self, h, _ud=None) -> None:
        ok = bool(h.is_local_position_ok) and (self.anchor is None or bool(h.is_global_position_ok))
        detail = "" if ok else "no local position" if not h.is_local_position_ok else "no global position"
        self._health = replace(self._health, estimator_ok=ok, estimator_detail=detail)
        with self._lock:
            self._integrity.on_estimator(self.clock(), ok, detail)
            self._log_integrity()

    def _on_armed(self, armed, _ud=None) -> None:
        self.armed = bool(armed)
        self._alive()

    def _on_mode(self, mode, _ud=None) -> None:
        # MAVSDK calls this on every HEARTBEAT of the autopilot, changed or not (TelemetryImpl::process_heartbeat)
        self._mode = MODE_CLASS_OF.get(getattr(mode, "name", str(mode)), ModeClass.OTHER)
        self._mode_t_s = self.clock()
        self._alive()

    # ---- VehicleLink --------------------------------------------------------------------
    @property
    def mode(self) -> ModeClass:
        """The vehicle's mode class from MAVSDK's flight mode (``UNKNOWN`` before the first one)."""
        return self._mode if self.last_heartbeat_t is not None else ModeClass.UNKNOWN

    @property
    def mode_t_s(self) -> float | None:
        """When MAVSDK last reported the flight mode, on the autopilot's HEARTBEAT [s, ``clock``]; None: never.
        Unlike ``last_heartbeat_t`` (any telemetry while MAVSDK is connected), 1 Hz as on the pymavlink link."""
        return self._mode_t_s

    @property
    def health(self) -> VehicleHealth:
        """Battery %, landed state and estimator position flags from MAVSDK's telemetry; the rest unknown."""
        return self._health

    @property
    def integrity(self) -> IntegrityVerdict:
        """Position integrity over MAVSDK's fixes and estimator flags (``fisc_agent.flight.integrity``)."""
        return self._integrity.verdict

    @property
    def jobs_dropped(self) -> int:
        """Commands dropped because the worker's queue was full."""
        return self._jobs.dropped

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

    def latest_gnss_velocity(self) -> GnssVelocity | None:
        """The GNSS receiver's newest velocity with a 3D fix (MAVSDK's ``raw_gps`` with the fix of its
        ``gps_info``, asked for at ``GNSS_RATE_HZ``), or None."""
        return self._gnss

    def latest_thrust_accel(self) -> None:
        """None: this backend does not read the attitude, so the agent identifies no drag through it (its
        velocity setpoints carry no acceleration feed-forward; ``fisc_agent.flight.drag``)."""
        return None

    def send_velocity_accel_ned(self, vn: float, ve: float, vd: float, an: float, ae: float, ad: float) -> None:
        """The velocity only (MAVSDK's velocity setpoint has no acceleration): ``send_velocity_ned``."""
        self.send_velocity_ned(vn, ve, vd)

    def send_velocity_ned(self, vn: float, ve: float, vd: float) -> None:
        """Send one velocity setpoint through MAVSDK's offboard plugin [m/s], yaw held (never raises)."""
        self._last_setpoint_s = self.clock()
        try:
            self._offboard.set_velocity_ned(self._VelocityNedYaw(vn, ve, vd, self._heading_deg))
        except Exception as exc:  # a flying agent never crashes on a setpoint
            log.warning("MAVSDK set_velocity_ned failed: %r", exc)

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

    def discard_backlog(self) -> int:
        """Nothing to drop: MAVSDK's callbacks keep the newest state, not a queue of old messages."""
        return 0

    def close(self) -> None:
        """Stop the action worker, the watchdog and MAVSDK's server."""
        self._stop.set()
        self._jobs.put(None)
        self._worker.join(timeout=2)
        self._watchdog.join(timeout=2)
        self._mavsdk.destroy()

    # ---- blocking MAVSDK calls on the worker -------------------------------------------
    def _watch(self) -> None:
        while not self._stop.wait(WATCHDOG_PERIOD_S):
            if not setpoint_stalled(self._last_setpoint_s, self.clock(), self.mode == ModeClass.OFFBOARD):
                continue
            self._last_setpoint_s = None  # once per stall; the next setpoint re-arms the watchdog
            self.watchdog_trips += 1
            log.error("no setpoint from the control loop for %.1f s: stopping MAVSDK's offboard setpoint stream",
                      SETPOINT_STALL_S)
            try:
                self._offboard.stop()
            except Exception as exc:  # offboard may not be active: then there was no stream to stop
                log.warning("MAVSDK offboard.stop failed: %r", exc)

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
