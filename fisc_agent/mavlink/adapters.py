"""Autopilot adapters (PX4, ArduPilot Copter), the vehicle-command interface and the command
reconciler (pure).

The mission says what it *wants* (mode class ``offboard``/``hold``/``land``, armed, takeoff
height); ``Commander`` compares that with what the vehicle *shows* and asks the link for the one
intent that moves the vehicle closer (``VehicleCommands``: ``set_mode``, ``arm``, ``takeoff``),
asking again every ``retry_s`` until the vehicle state changes.  The link reports how each
request went as a typed ``CommandResult`` (a COMMAND_ACK on pymavlink, the action's result on
MAVSDK); refusals are logged.  The adapters encode intents as MAVLink COMMAND_LONGs for the
pymavlink link (``link.MavlinkLink``) and decode HEARTBEAT modes:

PX4: HEARTBEAT ``custom_mode = main_mode << 16 | sub_mode << 24``; OFFBOARD is main mode 6,
AUTO.LOITER main 4 / sub 3, AUTO.LAND main 4 / sub 6.  Mode change: MAV_CMD_DO_SET_MODE with
param1 = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, param2 = main mode, param3 = sub mode.  PX4 refuses
OFFBOARD unless a setpoint stream (> 2 Hz) is already running: the commander waits for
``stream_before_offboard_s`` of streaming first.  Takeoff: a climb in OFFBOARD (no command).

ArduPilot Copter: ``custom_mode`` is the flight mode number: GUIDED 4, LOITER 5, LAND 9,
BRAKE 17; the agent's hold is BRAKE (LOITER follows the RC throttle stick and descends without
one).  Mode change: MAV_CMD_DO_SET_MODE (param2 = mode number).  Takeoff: MAV_CMD_NAV_TAKEOFF
with param7 = height above home, once armed in GUIDED.

Both: arm with MAV_CMD_COMPONENT_ARM_DISARM (param1 = 1).  MAVLink numbers come from
pymavlink's ``ardupilotmega`` dialect (common.xml included); PX4's main/sub modes are not in any
dialect (PX4 ``px4_custom_mode.h``) and are spelled out here.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from enum import StrEnum
from typing import Callable, Protocol

from pymavlink.dialects.v20.ardupilotmega import (COPTER_MODE_BRAKE, COPTER_MODE_GUIDED, COPTER_MODE_LAND,
                                                  COPTER_MODE_LOITER, MAV_AUTOPILOT_ARDUPILOTMEGA, MAV_AUTOPILOT_PX4,
                                                  MAV_CMD_COMPONENT_ARM_DISARM, MAV_CMD_DO_SET_MODE,
                                                  MAV_CMD_NAV_TAKEOFF, MAV_CMD_SET_MESSAGE_INTERVAL,
                                                  MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MAV_MODE_FLAG_SAFETY_ARMED,
                                                  MAV_RESULT_ACCEPTED, MAV_RESULT_IN_PROGRESS)
from pymavlink.dialects.v20.ardupilotmega import enums as _MAVLINK_ENUMS

from fisc_agent.common.ratelimit import RateLimitedLog

log = logging.getLogger(__name__)

MAX_REFUSALS_KEPT = 64
"""How many refused commands ``Commander.refusals`` keeps (the newest)."""
FRESH_HEARTBEAT_S = 0.25
"""Every mode, arming or take-off request waits for a HEARTBEAT at most this old [s], on the ground and in the air.
PX4 and ArduPilot send HEARTBEAT, the only message that carries the mode, at 1 Hz: a mode change by a pilot, a
ground station or an autopilot failsafe in the second before the agent's request is invisible to it, and the
request would take the vehicle back unseen (PX4 SITL, 2026-12-06: the ground's AUTO.TAKEOFF 0.9 s before the
agent's OFFBOARD in ARM).  The wait costs at most a second (the agent's own setpoints, a zero velocity in its
holds, fly meanwhile) and leaves a change in the last quarter second unseen, not the last second.  A retry also
waits for a HEARTBEAT that came after the request it repeats: the view from before the request would take back a
switch made since.  The HEARTBEAT's time is the link's ``mode_t_s`` (on the MAVSDK backend too: MAVSDK reports the
flight mode on every HEARTBEAT)."""

# PX4 main / sub modes (PX4 src/modules/commander/px4_custom_mode.h; in no MAVLink dialect)
PX4_MAIN_AUTO = 4
PX4_MAIN_OFFBOARD = 6
PX4_SUB_AUTO_TAKEOFF = 2
PX4_SUB_AUTO_LOITER = 3
PX4_SUB_AUTO_LAND = 6


class ModeClass(StrEnum):
    """What the agent needs to know of an autopilot mode (the value is the status/telemetry text)."""

    OFFBOARD = "offboard"
    """PX4 OFFBOARD / ArduPilot GUIDED: the agent's setpoints fly the vehicle."""
    HOLD = "hold"
    """The autopilot holds position (PX4 AUTO.LOITER, ArduPilot BRAKE or LOITER)."""
    LAND = "land"
    """The autopilot lands."""
    OTHER = "other"
    """Any other mode (the pilot's or an autopilot failsafe's)."""
    UNKNOWN = "unknown"
    """No HEARTBEAT (or no adapter) yet."""


MODE_CLASSES = (ModeClass.OFFBOARD, ModeClass.HOLD, ModeClass.LAND)
"""The modes the agent requests."""


class CommandKind(StrEnum):
    """What a vehicle command asked for (the value names it in logs and ``Commander.refusals``)."""

    ARM = "arming"
    SET_MODE = "mode change"
    TAKEOFF = "takeoff"
    MESSAGE_INTERVAL = "message interval"
    OTHER = "other command"


@dataclass(frozen=True)
class CommandResult:
    """How the autopilot answered one command."""

    kind: CommandKind
    """What was asked."""
    accepted: bool
    """Accepted (or in progress)."""
    result: str
    """The answer's name: a MAV_RESULT without its prefix (``ACCEPTED``, ``DENIED``...) or MAVSDK's result."""


class VehicleCommands(Protocol):
    """Commands at the level of intent; each link encodes them its own way (COMMAND_LONGs on
    pymavlink, MAVSDK actions) and reports the outcome as a ``CommandResult``."""

    def arm(self) -> None:
        """Request arming."""

    def set_mode(self, mode: ModeClass) -> None:
        """Request the autopilot mode of a ``ModeClass`` (offboard, hold, land)."""

    def takeoff(self, alt_m: float) -> None:
        """Request a takeoff to ``alt_m`` above home (autopilots that take off by command)."""

    def hold(self) -> None:
        """Request the autopilot's hold mode (``set_mode(HOLD)``)."""

    def land(self) -> None:
        """Request landing (``set_mode(LAND)``)."""


@dataclass(frozen=True)
class CommandLong:
    """One COMMAND_LONG to send."""

    command: int
    """MAV_CMD id."""
    params: tuple[float, float, float, float, float, float, float]
    """param1..param7."""
    label: str
    """Human-readable name for logs."""


_KIND_OF_COMMAND = {MAV_CMD_COMPONENT_ARM_DISARM: CommandKind.ARM, MAV_CMD_DO_SET_MODE: CommandKind.SET_MODE,
                    MAV_CMD_NAV_TAKEOFF: CommandKind.TAKEOFF,
                    MAV_CMD_SET_MESSAGE_INTERVAL: CommandKind.MESSAGE_INTERVAL}


def mav_result_name(result: int) -> str:
    """``DENIED`` for MAV_RESULT_DENIED, ... (the number itself if the dialect does not know it)."""
    entry = _MAVLINK_ENUMS["MAV_RESULT"].get(int(result))
    return entry.name.removeprefix("MAV_RESULT_") if entry is not None else str(int(result))


def command_result(command: int, result: int) -> CommandResult:
    """A COMMAND_ACK (command id, MAV_RESULT) as a ``CommandResult``."""
    return CommandResult(_KIND_OF_COMMAND.get(int(command), CommandKind.OTHER),
                         int(result) in (MAV_RESULT_ACCEPTED, MAV_RESULT_IN_PROGRESS), mav_result_name(result))


def autopilot_from_heartbeat(autopilot: int) -> str | None:
    """``px4`` / ``ardupilot`` from HEARTBEAT.autopilot (MAV_AUTOPILOT), None otherwise."""
    return {MAV_AUTOPILOT_PX4: "px4", MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot"}.get(int(autopilot))


def is_armed(base_mode: int) -> bool:
    """The armed flag of a HEARTBEAT's ``base_mode``."""
    return bool(int(base_mode) & MAV_MODE_FLAG_SAFETY_ARMED)


def arm_command() -> CommandLong:
    """MAV_CMD_COMPONENT_ARM_DISARM, arm."""
    return CommandLong(MAV_CMD_COMPONENT_ARM_DISARM, (1.0, 0, 0, 0, 0, 0, 0), "arm")


class Px4Adapter:
    """PX4 multicopter: OFFBOARD, climb-in-offboard takeoff, AUTO.LOITER hold, AUTO.LAND."""

    name = "px4"
    takeoff_by_command = False
    stream_before_offboard_s = 1.0
    _MODES = {ModeClass.OFFBOARD: (PX4_MAIN_OFFBOARD, 0, "OFFBOARD"),
              ModeClass.HOLD: (PX4_MAIN_AUTO, PX4_SUB_AUTO_LOITER, "AUTO.LOITER"),
              ModeClass.LAND: (PX4_MAIN_AUTO, PX4_SUB_AUTO_LAND, "AUTO.LAND")}

    @staticmethod
    def px4_custom_mode(main_mode: int, sub_mode: int = 0) -> int:
        """HEARTBEAT ``custom_mode`` of a PX4 main/sub mode."""
        return (main_mode << 16) | (sub_mode << 24)

    def classify_mode(self, base_mode: int, custom_mode: int) -> ModeClass:
        """The ``ModeClass`` of a HEARTBEAT's ``base_mode`` / ``custom_mode``."""
        if not int(base_mode) & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return ModeClass.OTHER
        main, sub = (int(custom_mode) >> 16) & 0xFF, (int(custom_mode) >> 24) & 0xFF
        if main == PX4_MAIN_OFFBOARD:
            return ModeClass.OFFBOARD
        if main == PX4_MAIN_AUTO and sub == PX4_SUB_AUTO_LOITER:
            return ModeClass.HOLD
        if main == PX4_MAIN_AUTO and sub == PX4_SUB_AUTO_LAND:
            return ModeClass.LAND
        return ModeClass.OTHER

    def mode_name(self, mode: ModeClass) -> str:
        """PX4's name of the mode the agent requests for ``mode``."""
        return self._MODES[ModeClass(mode)][2]

    def set_mode(self, mode: ModeClass) -> CommandLong:
        """The COMMAND_LONG requesting ``mode``."""
        main, sub, label = self._MODES[ModeClass(mode)]
        return CommandLong(MAV_CMD_DO_SET_MODE, (float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(main), float(sub),
                                                 0, 0, 0, 0), f"set mode {label}")

    def takeoff(self, alt_m: float) -> CommandLong | None:
        """None: PX4 takes off by climbing in OFFBOARD (the mission streams the climb)."""
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
    _NAMES = {COPTER_MODE_GUIDED: "GUIDED", COPTER_MODE_LOITER: "LOITER", COPTER_MODE_LAND: "LAND",
              COPTER_MODE_BRAKE: "BRAKE"}

    def __init__(self, hold_mode: int = COPTER_MODE_BRAKE) -> None:
        if hold_mode not in (COPTER_MODE_BRAKE, COPTER_MODE_GUIDED):
            raise ValueError(f"ArduPilot hold mode {hold_mode} follows the pilot's throttle; use BRAKE "
                             f"({COPTER_MODE_BRAKE})")
        self.hold_mode = hold_mode

    def classify_mode(self, base_mode: int, custom_mode: int) -> ModeClass:
        """The ``ModeClass`` of a HEARTBEAT's ``custom_mode`` (the Copter mode number)."""
        cm = int(custom_mode)
        if cm == COPTER_MODE_GUIDED:
            return ModeClass.OFFBOARD
        if cm in (COPTER_MODE_LOITER, COPTER_MODE_BRAKE):
            return ModeClass.HOLD
        if cm == COPTER_MODE_LAND:
            return ModeClass.LAND
        return ModeClass.OTHER

    def _mode_number(self, mode: ModeClass) -> int:
        return {ModeClass.OFFBOARD: COPTER_MODE_GUIDED, ModeClass.HOLD: self.hold_mode,
                ModeClass.LAND: COPTER_MODE_LAND}[ModeClass(mode)]

    def mode_name(self, mode: ModeClass) -> str:
        """ArduPilot's name of the mode the agent requests for ``mode``."""
        number = self._mode_number(mode)
        return self._NAMES.get(number, str(number))

    def set_mode(self, mode: ModeClass) -> CommandLong:
        """The COMMAND_LONG requesting ``mode``."""
        return CommandLong(MAV_CMD_DO_SET_MODE, (float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED),
                                                 float(self._mode_number(mode)), 0, 0, 0, 0, 0),
                           f"set mode {self.mode_name(mode)}")

    def takeoff(self, alt_m: float) -> CommandLong | None:
        """MAV_CMD_NAV_TAKEOFF to ``alt_m`` above home."""
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
    """Reconcile the mission's wants with the vehicle's observed state, one request at a time."""

    def __init__(self, adapter: Adapter, vehicle: VehicleCommands, retry_s: float = 1.0) -> None:
        self.adapter = adapter
        self.vehicle = vehicle
        self.retry_s = retry_s
        self._last_sent: dict[str, float] = {}
        self._attempts: dict[str, int] = {}
        self._takeoff_accepted = False
        self.refusals: deque[tuple[str, str]] = deque(maxlen=MAX_REFUSALS_KEPT)
        """(command kind, result name) of the latest refused commands, oldest first (bounded:
        forged COMMAND_ACKs must not grow it; the rate-limited log counts them all)."""
        self._refusal_log = RateLimitedLog(log)

    def _try(self, t: float, key: str, label: str, request: Callable[[], None], mode_age_s: float) -> None:
        last = self._last_sent.get(key)
        if last is not None and (t - last < self.retry_s or t - mode_age_s <= last):
            return  # a retry only on a HEARTBEAT newer than the request: never on a view older than it
        n = self._attempts.get(key, 0) + 1
        self._attempts[key], self._last_sent[key] = n, t
        if n == 1:
            log.info("requesting %s", label)
        elif n % 5 == 0:
            log.warning("still requesting %s (attempt %d)", label, n)
        request()

    def _clear(self, key: str) -> None:
        self._last_sent.pop(key, None)
        self._attempts.pop(key, None)

    def reconcile(self, t: float, want_mode: ModeClass | None, want_armed: bool | None, takeoff_alt_m: float | None,
                  armed: bool, mode: ModeClass, stream_s: float, mode_age_s: float) -> None:
        """Request at most one thing: the mode first, then arming, then (ArduPilot) the takeoff.

        ``stream_s``: how long setpoints have been streamed without a gap (PX4 needs a running stream before it
        accepts OFFBOARD).  ``mode_age_s``: the age of the newest report of the mode (the HEARTBEAT,
        ``VehicleLink.mode_t_s``); every request, on the ground or in the air, goes out only on a fresh one
        (``FRESH_HEARTBEAT_S``), and a retry only on a report received after the request it repeats.
        """
        if takeoff_alt_m is None:
            self._takeoff_accepted = False
        if self._last_sent:
            if takeoff_alt_m is None:
                self._clear("takeoff")
            for intent in MODE_CLASSES:
                if intent != want_mode or mode == intent:
                    self._clear(f"mode:{intent.value}")
        if mode_age_s > FRESH_HEARTBEAT_S:
            return  # first see whether someone else just changed the mode
        if want_mode is not None and mode != want_mode:
            if want_mode == ModeClass.OFFBOARD and stream_s < self.adapter.stream_before_offboard_s:
                return
            wanted = ModeClass(want_mode)
            self._try(t, f"mode:{wanted.value}", f"set mode {self.adapter.mode_name(wanted)}",
                      lambda: self.vehicle.set_mode(wanted), mode_age_s)
            return
        if want_armed and not armed:
            self._try(t, "arm", "arm", self.vehicle.arm, mode_age_s)
            return
        if self._last_sent:
            self._clear("arm")
        if takeoff_alt_m is not None and armed and not self._takeoff_accepted and self.adapter.takeoff_by_command:
            self._try(t, "takeoff", f"takeoff to {takeoff_alt_m:.1f} m", lambda: self.vehicle.takeoff(takeoff_alt_m),
                      mode_age_s)

    def on_result(self, res: CommandResult) -> None:
        """Handle the autopilot's answer to a command."""
        if res.kind == CommandKind.TAKEOFF and res.accepted:
            self._takeoff_accepted = True
        if res.accepted:
            log.debug("%s acknowledged: %s", res.kind.value, res.result)
            return
        self.refusals.append((res.kind.value, res.result))
        self._refusal_log.event(f"refused:{res.kind.value}:{res.result}", logging.WARNING,
                                "autopilot refused %s: %s", res.kind.value, res.result)
