"""A ground station for the real-autopilot tests: what QGroundControl or MAVProxy does, in pymavlink.

``GroundStation`` listens on the autopilots' ground-station port (udp 14550, both SITL READMEs), sends a
GCS HEARTBEAT once a second, and commands the vehicle with ordinary COMMAND_LONGs: arm
(MAV_CMD_COMPONENT_ARM_DISARM), take off (MAV_CMD_NAV_TAKEOFF) and change mode (MAV_CMD_DO_SET_MODE with
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED).  A reader thread keeps every HEARTBEAT of the vehicle (its custom mode
and armed flag, as the ground sees them), its positions and its COMMAND_ACKs, so a test can judge what the
autopilot did over a whole interval (``modes_between``), not only at the instant it looks.

The mode numbers are the autopilots' own, looked up in their sources (not the agent's constants, which
the tests judge):

- PX4 ``src/modules/commander/px4_custom_mode.h``: main modes MANUAL 1, ALTCTL 2, POSCTL 3, AUTO 4,
  ACRO 5, OFFBOARD 6; AUTO sub modes READY 1, TAKEOFF 2, LOITER 3 (Hold), MISSION 4, RTL 5, LAND 6.
  HEARTBEAT ``custom_mode`` = main << 16 | sub << 24 (``union px4_custom_mode``); DO_SET_MODE takes
  param2 = main, param3 = sub.  MAV_CMD_NAV_TAKEOFF (PX4 Commander: it sets the AUTO.TAKEOFF intention)
  takes param7 = altitude AMSL; after take-off PX4 goes to AUTO.LOITER by itself.
- ArduCopter ``ArduCopter/mode.h`` (``Mode::Number``): GUIDED 4, LOITER 5, RTL 6, LAND 9, BRAKE 17;
  ``custom_mode`` is the number; MAV_CMD_NAV_TAKEOFF in GUIDED takes param7 = height above home.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

PX4_MAIN_POSCTL, PX4_MAIN_AUTO, PX4_MAIN_OFFBOARD = 3, 4, 6
PX4_SUB_TAKEOFF, PX4_SUB_LOITER, PX4_SUB_RTL, PX4_SUB_LAND = 2, 3, 5, 6


def px4_mode(main: int, sub: int = 0) -> int:
    """PX4 HEARTBEAT ``custom_mode`` of a main / sub mode."""
    return (main << 16) | (sub << 24)


PX4_TAKEOFF = px4_mode(PX4_MAIN_AUTO, PX4_SUB_TAKEOFF)
PX4_HOLD = px4_mode(PX4_MAIN_AUTO, PX4_SUB_LOITER)
PX4_RTL = px4_mode(PX4_MAIN_AUTO, PX4_SUB_RTL)
PX4_LAND = px4_mode(PX4_MAIN_AUTO, PX4_SUB_LAND)
PX4_OFFBOARD = px4_mode(PX4_MAIN_OFFBOARD)
PX4_POSCTL = px4_mode(PX4_MAIN_POSCTL)

COPTER_GUIDED, COPTER_LOITER, COPTER_RTL, COPTER_LAND, COPTER_BRAKE = 4, 5, 6, 9, 17

PX4_NAV_AUTO_LOITER, PX4_NAV_OFFBOARD, PX4_NAV_AUTO_TAKEOFF, PX4_NAV_AUTO_LAND = 4, 14, 17, 18
"""vehicle_status.nav_state values in a ULog (PX4 ``msg/VehicleStatus.msg``)."""

MAV_CMD_NAV_TAKEOFF, MAV_CMD_DO_SET_MODE, MAV_CMD_COMPONENT_ARM_DISARM, MAV_CMD_SET_MESSAGE_INTERVAL = 22, 176, 400, 511
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MAV_MODE_FLAG_SAFETY_ARMED = 1, 128


def mode_name(custom_mode: int, autopilot: str) -> str:
    """A readable name of a ``custom_mode`` (for messages)."""
    if autopilot == "px4":
        names = {PX4_TAKEOFF: "AUTO.TAKEOFF", PX4_HOLD: "AUTO.LOITER", PX4_RTL: "AUTO.RTL", PX4_LAND: "AUTO.LAND",
                 PX4_OFFBOARD: "OFFBOARD", PX4_POSCTL: "POSCTL"}
        return names.get(custom_mode, f"main {(custom_mode >> 16) & 0xFF} sub {(custom_mode >> 24) & 0xFF}")
    names = {COPTER_GUIDED: "GUIDED", COPTER_LOITER: "LOITER", COPTER_RTL: "RTL", COPTER_LAND: "LAND",
             COPTER_BRAKE: "BRAKE", 0: "STABILIZE"}
    return names.get(custom_mode, str(custom_mode))


@dataclass(frozen=True)
class Beat:
    """One HEARTBEAT of the vehicle as the ground station received it."""

    t_s: float
    """time.monotonic() at reception [s]."""
    custom_mode: int
    """HEARTBEAT.custom_mode."""
    armed: bool
    """MAV_MODE_FLAG_SAFETY_ARMED of base_mode."""


@dataclass(frozen=True)
class Fix:
    """One position report of the vehicle."""

    t_s: float
    """time.monotonic() at reception [s]."""
    boot_s: float
    """The autopilot's own clock (time_boot_ms) [s]: a ULog's timestamps run on it."""
    ned_m: tuple[float, float, float] | None
    """LOCAL_POSITION_NED x, y, z [m] (None for a GLOBAL_POSITION_INT)."""
    lat_deg: float = math.nan
    """GLOBAL_POSITION_INT latitude [deg] (nan for a LOCAL_POSITION_NED)."""
    lon_deg: float = math.nan
    """GLOBAL_POSITION_INT longitude [deg]."""
    rel_alt_m: float = math.nan
    """GLOBAL_POSITION_INT height above home [m]."""
    amsl_m: float = math.nan
    """GLOBAL_POSITION_INT altitude AMSL [m]."""


@dataclass
class _Seen:
    beats: list[Beat] = field(default_factory=list)
    local: list[Fix] = field(default_factory=list)
    glob: list[Fix] = field(default_factory=list)
    acks: list[tuple[float, int, int]] = field(default_factory=list)
    texts: list[str] = field(default_factory=list)
    params: dict[str, float] = field(default_factory=dict)


class GroundStation:
    """``with GroundStation("px4") as gcs:`` a ground station on udp 14550 for vehicle ``target_system``.

    ``autopilot``: ``px4`` or ``ardupilot`` (how a take-off altitude is given).  Every method that
    commands waits for the vehicle to show the result (HEARTBEAT / position), retrying the command
    once a second as a ground station does, and raises ``TimeoutError`` naming what it waited for."""

    def __init__(self, autopilot: str, url: str = "udpin:127.0.0.1:14550", target_system: int = 1,
                 source_system: int = 255) -> None:
        from pymavlink import mavutil

        if autopilot not in ("px4", "ardupilot"):
            raise ValueError(f"autopilot {autopilot!r}: px4 or ardupilot")
        self.autopilot, self.target = autopilot, target_system
        self._m = mavutil.mavlink_connection(url, source_system=source_system, source_component=190)
        self._seen = _Seen()
        self.mode_requests: list[tuple[float, str]] = []
        """(wall-clock time, mode name) of every ``set_mode`` this ground station began, oldest first."""
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ground-station", daemon=True)
        self._thread.start()

    # ---- lifecycle ------------------------------------------------------------------------
    def __enter__(self) -> "GroundStation":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop the reader and close the socket."""
        self._stop.set()
        self._thread.join(timeout=3.0)
        self._m.close()

    def _run(self) -> None:
        last_beat = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now - last_beat >= 1.0 and self._m.port is not None:
                last_beat = now
                with self._send_lock:
                    try:
                        self._m.mav.heartbeat_send(6, 8, 0, 0, 4)  # MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, ACTIVE
                    except OSError:
                        pass  # udpin: no peer address before the first packet
            try:
                m = self._m.recv_match(blocking=True, timeout=0.2)
            except (OSError, ValueError):
                continue
            if m is None or m.get_srcSystem() != self.target:
                continue
            self._record(m, time.monotonic())

    def _record(self, m, t: float) -> None:
        kind = m.get_type()
        with self._lock:
            if kind == "HEARTBEAT" and m.get_srcComponent() == 1 and m.autopilot != 8:
                self._seen.beats.append(Beat(t, int(m.custom_mode), bool(m.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)))
            elif kind == "LOCAL_POSITION_NED":
                self._seen.local.append(Fix(t, m.time_boot_ms / 1e3, (float(m.x), float(m.y), float(m.z))))
            elif kind == "GLOBAL_POSITION_INT":
                self._seen.glob.append(Fix(t, m.time_boot_ms / 1e3, None, m.lat / 1e7, m.lon / 1e7,
                                           m.relative_alt / 1e3, m.alt / 1e3))
            elif kind == "COMMAND_ACK":
                self._seen.acks.append((t, int(m.command), int(m.result)))
            elif kind == "STATUSTEXT":
                self._seen.texts.append(str(m.text))
            elif kind == "PARAM_VALUE":
                self._seen.params[str(m.param_id)] = float(m.param_value)

    # ---- what the ground sees -------------------------------------------------------------
    def wait(self, pred, timeout_s: float, what: str, period_s: float = 0.05):
        """Poll ``pred()`` until truthy (returned); ``TimeoutError`` naming ``what`` otherwise."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            value = pred()
            if value:
                return value
            time.sleep(period_s)
        raise TimeoutError(f"ground station: {what} not seen within {timeout_s:.0f} s "
                           f"(last HEARTBEAT: {self.last_beat()}, texts: {self.texts()[-5:]})")

    def last_beat(self) -> Beat | None:
        """The newest HEARTBEAT of the vehicle (None before the first)."""
        with self._lock:
            return self._seen.beats[-1] if self._seen.beats else None

    def mode(self) -> int | None:
        """The vehicle's custom mode now (None before a HEARTBEAT)."""
        b = self.last_beat()
        return None if b is None else b.custom_mode

    def armed(self) -> bool:
        """The vehicle says it is armed."""
        b = self.last_beat()
        return bool(b and b.armed)

    def beats_between(self, t0_s: float, t1_s: float = math.inf) -> list[Beat]:
        """Every HEARTBEAT received in ``[t0_s, t1_s]`` (monotonic clock)."""
        with self._lock:
            return [b for b in self._seen.beats if t0_s <= b.t_s <= t1_s]

    def modes_between(self, t0_s: float, t1_s: float = math.inf) -> list[str]:
        """The vehicle's modes (names, consecutive repeats removed) in ``[t0_s, t1_s]``."""
        out: list[str] = []
        for b in self.beats_between(t0_s, t1_s):
            name = mode_name(b.custom_mode, self.autopilot)
            if not out or out[-1] != name:
                out.append(name)
        return out

    def local(self) -> Fix | None:
        """The newest LOCAL_POSITION_NED."""
        with self._lock:
            return self._seen.local[-1] if self._seen.local else None

    def global_fix(self) -> Fix | None:
        """The newest GLOBAL_POSITION_INT."""
        with self._lock:
            return self._seen.glob[-1] if self._seen.glob else None

    def texts(self) -> list[str]:
        """STATUSTEXTs received so far."""
        with self._lock:
            return list(self._seen.texts)

    # ---- commanding -----------------------------------------------------------------------
    def command(self, command: int, *params: float) -> None:
        """Send one COMMAND_LONG (param1..7, missing ones 0) to the vehicle's autopilot."""
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        with self._send_lock:
            self._m.mav.command_long_send(self.target, 1, command, 0, *p)

    def _until(self, send, pred, timeout_s: float, what: str):
        end = time.monotonic() + timeout_s
        while True:
            send()
            try:
                return self.wait(pred, min(1.0, max(0.05, end - time.monotonic())), what)
            except TimeoutError:
                if time.monotonic() >= end:
                    raise

    def connect(self, timeout_s: float = 30.0) -> None:
        """Wait for the vehicle's HEARTBEAT, then ask for its positions at 10 Hz (SET_MESSAGE_INTERVAL) and
        wait for GLOBAL_POSITION_INT (ArduCopter SITL sends no LOCAL_POSITION_NED on its ground link)."""
        self.wait(self.last_beat, timeout_s, "a HEARTBEAT")
        for msg_id in (32, 33):  # LOCAL_POSITION_NED, GLOBAL_POSITION_INT
            self.command(MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 100_000)
        self.wait(self.global_fix, 10.0, "GLOBAL_POSITION_INT")

    def set_mode(self, custom_mode: int, timeout_s: float = 10.0) -> float:
        """Change the mode (MAV_CMD_DO_SET_MODE) until a HEARTBEAT shows it; returns when that HEARTBEAT came
        (monotonic clock: from then on ``modes_between`` must show only this mode while nobody else changes it)."""
        if self.autopilot == "px4":
            args = (MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF)
        else:
            args = (MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, custom_mode)
        self.mode_requests.append((time.time(), mode_name(custom_mode, self.autopilot)))
        beat = self._until(lambda: self.command(MAV_CMD_DO_SET_MODE, *args),
                           lambda: (lambda b: b if b is not None and b.custom_mode == custom_mode else None)(
                               self.last_beat()), timeout_s, f"mode {mode_name(custom_mode, self.autopilot)}")
        return beat.t_s

    def set_param(self, name: str, value: float, timeout_s: float = 10.0) -> None:
        """PARAM_SET a REAL32 parameter until the autopilot's PARAM_VALUE echoes ``value``."""
        def send() -> None:
            with self._send_lock:
                self._m.mav.param_set_send(self.target, 1, name.encode(), float(value), 9)  # MAV_PARAM_TYPE_REAL32

        def echoed() -> bool:
            with self._lock:
                got = self._seen.params.get(name)
            return got is not None and abs(got - value) <= 1e-6 * max(1.0, abs(value))

        self._until(send, echoed, timeout_s, f"parameter {name} = {value}")

    def arm(self, timeout_s: float = 15.0) -> None:
        """Arm (MAV_CMD_COMPONENT_ARM_DISARM) until the HEARTBEAT says armed."""
        self._until(lambda: self.command(MAV_CMD_COMPONENT_ARM_DISARM, 1), self.armed, timeout_s, "armed")

    def takeoff(self, alt_m: float, timeout_s: float = 40.0) -> None:
        """Take off to ``alt_m`` above home (MAV_CMD_NAV_TAKEOFF; PX4 wants it AMSL) and wait until 90 % of it."""
        g = self.global_fix()
        if g is None:
            raise RuntimeError("ground station: no GLOBAL_POSITION_INT yet (connect() first)")
        param7 = g.amsl_m - g.rel_alt_m + alt_m if self.autopilot == "px4" else alt_m
        yaw_lat_lon = (math.nan,) * 3 if self.autopilot == "px4" else (0.0,) * 3  # PX4: NaN = keep / here
        self._until(lambda: self.command(MAV_CMD_NAV_TAKEOFF, 0, 0, 0, *yaw_lat_lon, param7),
                    lambda: (self.global_fix() or g).rel_alt_m > 0.3, 10.0, "the take-off starting")
        self.wait(lambda: (self.global_fix() or g).rel_alt_m >= 0.9 * alt_m, timeout_s, f"{alt_m:.1f} m above home")
