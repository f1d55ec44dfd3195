"""Autopilot adapters (PX4, ArduPilot Copter) and the command reconciler (pure).

The mission says what it *wants* (mode class ``offboard``/``hold``/``land``, armed, takeoff
height); ``Commander`` compares that with what the HEARTBEAT *shows* and sends the one
COMMAND_LONG that moves the vehicle closer, resending it every ``retry_s`` until the vehicle
state changes (COMMAND_ACKs are checked and refusals logged with their MAV_RESULT).  The
adapters only encode and decode:

PX4: HEARTBEAT ``custom_mode = main_mode << 16 | sub_mode << 24``; OFFBOARD is main mode 6,
AUTO.LOITER main 4 / sub 3, AUTO.LAND main 4 / sub 6.  Mode change: MAV_CMD_DO_SET_MODE with
param1 = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, param2 = main mode, param3 = sub mode.  PX4 refuses
OFFBOARD unless a setpoint stream (> 2 Hz) is already running: the commander waits for
``stream_before_offboard_s`` of streaming first.  Takeoff: a climb in OFFBOARD (no command).

ArduPilot Copter: ``custom_mode`` is the flight mode number: GUIDED 4, LOITER 5, LAND 9,
BRAKE 17; the agent's hold is BRAKE (LOITER follows the RC throttle stick and descends without one).  Mode change: MAV_CMD_DO_SET_MODE (param2 = mode number).  Takeoff:
MAV_CMD_NAV_TAKEOFF with param7 = height above home, once armed in GUIDED.

Both: arm with MAV_CMD_COMPONENT_ARM_DISARM (param1 = 1).
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from typing import Callable

from fisc_agent.ratelimit import RateLimitedLog

log = logging.getLogger(__name__)

# MAVLink constants (common.xml); kept here so this module stays pure and import-light.
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
MAV_RESULT_NAMES = {0: "ACCEPTED", 1: "TEMPORARILY_REJECTED", 2: "DENIED", 3: "UNSUPPORTED", 4: "FAILED",
                    5: "IN_PROGRESS", 6: "CANCELLED", 7: "COMMAND_LONG_ONLY", 8: "COMMAND_INT_ONLY"}
MODE_CLASSES = ("offboard", "hold", "land")
MAX_REFUSALS_KEPT = 64
"""How many refused commands ``Commander.refusals`` keeps (the newest)."""

PX4_MAIN_AUTO = 4
PX4_MAIN_OFFBOARD = 6
PX4_SUB_AUTO_TAKEOFF = 2
PX4_SUB_AUTO_LOITER = 3
PX4_SUB_AUTO_LAND = 6
AP_COPTER_GUIDED = 4
AP_COPTER_LOITER = 5
AP_COPTER_LAND = 9
AP_COPTER_BRAKE = 17


@dataclass(frozen=True)
class CommandLong:
    """One COMMAND_LONG to send."""

    command: int
    """MAV_CMD id."""
    params: tuple[float, float, float, float, float, float, float]
    """param1..param7."""
    label: str
    """Human-readable name for logs."""


def autopilot_from_heartbeat(autopilot: int) -> str | None:
    """``px4`` / ``ardupilot`` from HEARTBEAT.autopilot (MAV_AUTOPILOT), None otherwise."""
    return {MAV_AUTOPILOT_PX4: "px4", MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot"}.get(int(autopilot))


def is_armed(base_mode: int) -> bool:
    return bool(int(base_mode) & MAV_MODE_FLAG_SAFETY_ARMED)


def arm_command() -> CommandLong:
    return CommandLong(MAV_CMD_COMPONENT_ARM_DISARM, (1.0, 0, 0, 0, 0, 0, 0), "arm")


class Px4Adapter:
    """PX4 multicopter: OFFBOARD, climb-in-offboard takeoff, AUTO.LOITER hold, AUTO.LAND."""

    name = "px4"
    takeoff_by_command = False
    stream_before_offboard_s = 1.0

    @staticmethod
    def px4_custom_mode(main_mode: int, sub_mode: int = 0) -> int:
        """HEARTBEAT ``custom_mode`` of a PX4 main/sub mode."""
        return (main_mode << 16) | (sub_mode << 24)

    def classify_mode(self, base_mode: int, custom_mode: int) -> str:
        if not int(base_mode) & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return "other"
        main, sub = (int(custom_mode) >> 16) & 0xFF, (int(custom_mode) >> 24) & 0xFF
        if main == PX4_MAIN_OFFBOARD:
            return "offboard"
        if main == PX4_MAIN_AUTO and sub == PX4_SUB_AUTO_LOITER:
            return "hold"
        if main == PX4_MAIN_AUTO and sub == PX4_SUB_AUTO_LAND:
            return "land"
        return "other"

    def set_mode(self, intent: str) -> CommandLong:
        main, sub = {"offboard": (PX4_MAIN_OFFBOARD, 0), "hold": (PX4_MAIN_AUTO, PX4_SUB_AUTO_LOITER),
                     "land": (PX4_MAIN_AUTO, PX4_SUB_AUTO_LAND)}[intent]
        label = {"offboard": "OFFBOARD", "hold": "AUTO.LOITER", "land": "AUTO.LAND"}[intent]
        return CommandLong(MAV_CMD_DO_SET_MODE, (float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(main), float(sub),
                                                 0, 0, 0, 0), f"set mode {label}")

    def takeoff(self, alt_m: float) -> CommandLong | None:
        return None


class ArduPilotAdapter:
    """ArduPilot Copter: GUIDED, NAV_TAKEOFF, BRAKE hold, LAND.

    The hold is BRAKE: it stops and holds position and altitude with no pilot.  LOITER and
    ALT_HOLD follow the RC throttle stick, so without an RC link (a swarm) they descend: real
    ArduCopter SITL hit the ground 5 s after a LOITER hold.  A LOITER the pilot selects still
    counts as a hold (the pilot is then in charge).
    """

    name = "ardupilot"
    takeoff_by_command = True
    stream_before_offboard_s = 0.0

    def __init__(self, hold_mode: int = AP_COPTER_BRAKE) -> None:
        if hold_mode not in (AP_COPTER_BRAKE, AP_COPTER_GUIDED):
            raise ValueError(f"ArduPilot hold mode {hold_mode} follows the pilot's throttle; use BRAKE (17)")
        self.hold_mode = hold_mode

    def classify_mode(self, base_mode: int, custom_mode: int) -> str:
        cm = int(custom_mode)
        if cm == AP_COPTER_GUIDED:
            return "offboard"
        if cm in (AP_COPTER_LOITER, AP_COPTER_BRAKE):
            return "hold"
        if cm == AP_COPTER_LAND:
            return "land"
        return "other"

    def set_mode(self, intent: str) -> CommandLong:
        mode = {"offboard": AP_COPTER_GUIDED, "hold": self.hold_mode, "land": AP_COPTER_LAND}[intent]
        label = {AP_COPTER_GUIDED: "GUIDED", AP_COPTER_LOITER: "LOITER", AP_COPTER_LAND: "LAND",
                 AP_COPTER_BRAKE: "BRAKE"}.get(mode, str(mode))
        return CommandLong(MAV_CMD_DO_SET_MODE, (float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(mode), 0, 0, 0, 0, 0),
                           f"set mode {label}")

    def takeoff(self, alt_m: float) -> CommandLong | None:
        return CommandLong(MAV_CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, float(alt_m)), f"takeoff to {alt_m:.1f} m")


Adapter = Px4Adapter | ArduPilotAdapter


def adapter_for(autopilot: str) -> Adapter:
    """The adapter for ``px4`` or ``ardupilot``."""
    if autopilot == "px4":
        return Px4Adapter()
    if autopilot == "ardupilot":
        return ArduPilotAdapter()
    raise ValueError(f"no adapter for autopilot {autopilot!r}; choose px4 or ardupilot")


class Commander:
    """Reconcile the mission's wants with the vehicle's observed state, one command at a time."""

    def __init__(self, adapter: Adapter, send: Callable[[CommandLong], None], retry_s: float = 1.0) -> None:
        self.adapter = adapter
        self._send = send
        self.retry_s = retry_s
        self._last_sent: dict[str, float] = {}
        self._attempts: dict[str, int] = {}
        self._takeoff_accepted = False
        self.refusals: deque[tuple[str, str]] = deque(maxlen=MAX_REFUSALS_KEPT)
        """(command label, MAV_RESULT name) of the latest refused commands, oldest first (bounded:
        forged COMMAND_ACKs must not grow it; the rate-limited log counts them all)."""
        self._refusal_log = RateLimitedLog(log)

    def _try(self, t: float, key: str, cmd: CommandLong) -> None:
        last = self._last_sent.get(key)
        if last is not None and t - last < self.retry_s:
            return
        n = self._attempts.get(key, 0) + 1
        self._attempts[key], self._last_sent[key] = n, t
        if n == 1:
            log.info("requesting %s", cmd.label)
        elif n % 5 == 0:
            log.warning("still requesting %s (attempt %d)", cmd.label, n)
        self._send(cmd)

    def _clear(self, key: str) -> None:
        self._last_sent.pop(key, None)
        self._attempts.pop(key, None)

    def reconcile(self, t: float, want_mode: str | None, want_armed: bool | None, takeoff_alt_m: float | None,
                  armed: bool, mode: str, stream_s: float) -> None:
        """Send at most one command: mode first, then arming, then (ArduPilot) takeoff.

        ``stream_s``: how long setpoints have been streamed without a gap (PX4 needs a
        running stream before it accepts OFFBOARD).
        """
        if takeoff_alt_m is None:
            self._takeoff_accepted = False
        if self._last_sent:
            if takeoff_alt_m is None:
                self._clear("takeoff")
            for intent in MODE_CLASSES:
                if intent != want_mode or mode == intent:
                    self._clear(f"mode:{intent}")
        if want_mode is not None and mode != want_mode:
            if want_mode == "offboard" and stream_s < self.adapter.stream_before_offboard_s:
                return
            self._try(t, f"mode:{want_mode}", self.adapter.set_mode(want_mode))
            return
        if want_armed and not armed:
            self._try(t, "arm", arm_command())
            return
        if self._last_sent:
            self._clear("arm")
        if takeoff_alt_m is not None and armed and not self._takeoff_accepted:
            cmd = self.adapter.takeoff(takeoff_alt_m)
            if cmd is not None:
                self._try(t, "takeoff", cmd)

    def on_ack(self, command: int, result: int) -> None:
        """Handle a COMMAND_ACK from the autopilot."""
        name = MAV_RESULT_NAMES.get(int(result), str(result))
        if command == MAV_CMD_NAV_TAKEOFF and result in (0, 5):
            self._takeoff_accepted = True
        if result in (0, 5):
            log.debug("command %d acknowledged: %s", command, name)
        else:
            label = {MAV_CMD_DO_SET_MODE: "mode change", MAV_CMD_COMPONENT_ARM_DISARM: "arming",
                     MAV_CMD_NAV_TAKEOFF: "takeoff", MAV_CMD_SET_MESSAGE_INTERVAL: "message interval"}.get(
                command, f"command {command}")
            self.refusals.append((label, name))
            self._refusal_log.event(f"refused:{label}:{name}", logging.WARNING, "autopilot refused %s: MAV_RESULT_%s",
                                    label, name)
