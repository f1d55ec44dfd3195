"""Autopilot personalities: how PX4 and ArduPilot Copter spell modes, types and parameters.

The vehicle state machine (:mod:`sim.autopilot.vehicle`) works with personality-independent
:class:`FlightMode` behaviours.  A :class:`Personality` translates between those and the
MAVLink encodings a real autopilot uses:

* PX4: ``custom_mode = (main_mode << 16) | (sub_mode << 24)`` (``px4_custom_mode.h``); main
  modes MANUAL=1, ALTCTL=2, POSCTL=3, AUTO=4 (sub modes READY=1, TAKEOFF=2, LOITER=3,
  MISSION=4, RTL=5, LAND=6), ACRO=5, OFFBOARD=6, STABILIZED=7.  ``MAV_CMD_DO_SET_MODE`` carries
  the main mode in param2 and the sub mode in param3.
* ArduPilot Copter: ``custom_mode`` is the plain mode number (STABILIZE=0, ACRO=1, ALT_HOLD=2,
  AUTO=3, GUIDED=4, LOITER=5, RTL=6, LAND=9, POSHOLD=16, BRAKE=17).

Parameters: each personality has a small parameter table (names, defaults and MAVLink types as
the real autopilot has them) which the emulator answers PARAM_* requests from and which the
failsafe rules read.  PX4 transmits integer parameters byte-wise inside the float field
(MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE); ArduPilot casts them to float
(MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST).  Pure data and pure functions; no I/O.
"""

from __future__ import annotations

import enum
import math
import struct
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

__all__ = [
    "FlightMode",
    "ParamSpec",
    "Personality",
    "PX4",
    "ARDUPILOT",
    "PERSONALITIES",
    "get_personality",
    "px4_custom_mode",
    "px4_main_sub",
]


class FlightMode(enum.Enum):
    """Personality-independent flight behaviours of the emulated vehicle."""

    MANUAL = "manual"  # PX4 MANUAL; needs a pilot (no RC here)
    STABILIZED = "stabilized"  # PX4 STABILIZED / ArduPilot STABILIZE
    ACRO = "acro"
    ALTCTL = "altctl"  # PX4 ALTCTL / ArduPilot ALT_HOLD
    POSCTL = "posctl"  # PX4 POSCTL / ArduPilot POSHOLD
    AUTO_READY = "auto_ready"  # PX4 AUTO.READY
    TAKEOFF = "takeoff"  # PX4 AUTO.TAKEOFF
    LOITER = "loiter"  # PX4 AUTO.LOITER ("Hold") / ArduPilot LOITER
    MISSION = "mission"  # PX4 AUTO.MISSION / ArduPilot AUTO (empty mission: hold)
    RTL = "rtl"
    LAND = "land"
    OFFBOARD = "offboard"  # PX4 only
    GUIDED = "guided"  # ArduPilot only
    BRAKE = "brake"  # ArduPilot only

    @property
    def needs_pilot(self) -> bool:
        """True for modes that fly from RC sticks (the emulator has no RC: they hold)."""
        return self in _PILOT_MODES


_PILOT_MODES = frozenset(
    {FlightMode.MANUAL, FlightMode.STABILIZED, FlightMode.ACRO, FlightMode.ALTCTL, FlightMode.POSCTL}
)

# PX4 main / sub modes (px4_custom_mode.h, as pymavlink.mavutil carries them)
PX4_MAIN_MANUAL, PX4_MAIN_ALTCTL = mavutil.PX4_CUSTOM_MAIN_MODE_MANUAL, mavutil.PX4_CUSTOM_MAIN_MODE_ALTCTL
PX4_MAIN_POSCTL, PX4_MAIN_AUTO = mavutil.PX4_CUSTOM_MAIN_MODE_POSCTL, mavutil.PX4_CUSTOM_MAIN_MODE_AUTO
PX4_MAIN_ACRO, PX4_MAIN_OFFBOARD = mavutil.PX4_CUSTOM_MAIN_MODE_ACRO, mavutil.PX4_CUSTOM_MAIN_MODE_OFFBOARD
PX4_MAIN_STABILIZED = mavutil.PX4_CUSTOM_MAIN_MODE_STABILIZED
PX4_SUB_READY, PX4_SUB_TAKEOFF = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_READY, mavutil.PX4_CUSTOM_SUB_MODE_AUTO_TAKEOFF
PX4_SUB_LOITER, PX4_SUB_MISSION = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_LOITER, mavutil.PX4_CUSTOM_SUB_MODE_AUTO_MISSION
PX4_SUB_RTL, PX4_SUB_LAND = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_RTL, mavutil.PX4_CUSTOM_SUB_MODE_AUTO_LAND


def px4_custom_mode(main_mode: int, sub_mode: int = 0) -> int:
    """PX4 ``custom_mode`` word: ``(main_mode << 16) | (sub_mode << 24)``."""
    return ((int(main_mode) & 0xFF) << 16) | ((int(sub_mode) & 0xFF) << 24)


def px4_main_sub(custom_mode: int) -> tuple[int, int]:
    """Inverse of :func:`px4_custom_mode`: ``(main_mode, sub_mode)``."""
    return (int(custom_mode) >> 16) & 0xFF, (int(custom_mode) >> 24) & 0xFF


_PX4_MODES: dict[FlightMode, tuple[int, int]] = {
    FlightMode.MANUAL: (PX4_MAIN_MANUAL, 0),
    FlightMode.ALTCTL: (PX4_MAIN_ALTCTL, 0),
    FlightMode.POSCTL: (PX4_MAIN_POSCTL, 0),
    FlightMode.AUTO_READY: (PX4_MAIN_AUTO, PX4_SUB_READY),
    FlightMode.TAKEOFF: (PX4_MAIN_AUTO, PX4_SUB_TAKEOFF),
    FlightMode.LOITER: (PX4_MAIN_AUTO, PX4_SUB_LOITER),
    FlightMode.MISSION: (PX4_MAIN_AUTO, PX4_SUB_MISSION),
    FlightMode.RTL: (PX4_MAIN_AUTO, PX4_SUB_RTL),
    FlightMode.LAND: (PX4_MAIN_AUTO, PX4_SUB_LAND),
    FlightMode.ACRO: (PX4_MAIN_ACRO, 0),
    FlightMode.OFFBOARD: (PX4_MAIN_OFFBOARD, 0),
    FlightMode.STABILIZED: (PX4_MAIN_STABILIZED, 0),
}

# ArduPilot Copter mode numbers (ArduCopter/mode.h; the ardupilotmega dialect's COPTER_MODE enum)
_ARDUPILOT_MODE_NAMES: dict[FlightMode, str] = {
    FlightMode.STABILIZED: "STABILIZE",
    FlightMode.ACRO: "ACRO",
    FlightMode.ALTCTL: "ALT_HOLD",
    FlightMode.MISSION: "AUTO",
    FlightMode.GUIDED: "GUIDED",
    FlightMode.LOITER: "LOITER",
    FlightMode.RTL: "RTL",
    FlightMode.LAND: "LAND",
    FlightMode.POSCTL: "POSHOLD",
    FlightMode.BRAKE: "BRAKE",
}
_ARDUPILOT_MODES: dict[FlightMode, int] = {m: getattr(mavlink, f"COPTER_MODE_{n}") for m, n in _ARDUPILOT_MODE_NAMES.items()}
_ARDUPILOT_NAMES = {_ARDUPILOT_MODES[m]: n for m, n in _ARDUPILOT_MODE_NAMES.items()}
_PX4_NAMES = {
    FlightMode.MANUAL: "MANUAL", FlightMode.ALTCTL: "ALTCTL", FlightMode.POSCTL: "POSCTL",
    FlightMode.AUTO_READY: "AUTO.READY", FlightMode.TAKEOFF: "AUTO.TAKEOFF",
    FlightMode.LOITER: "AUTO.LOITER", FlightMode.MISSION: "AUTO.MISSION",
    FlightMode.RTL: "AUTO.RTL", FlightMode.LAND: "AUTO.LAND", FlightMode.ACRO: "ACRO",
    FlightMode.OFFBOARD: "OFFBOARD", FlightMode.STABILIZED: "STABILIZED",
}


@dataclass(frozen=True)
class ParamSpec:
    """One autopilot parameter as the emulator exposes it."""

    name: str
    """Parameter id (<= 16 characters), exactly as the real autopilot spells it."""
    default: float
    """Default value (in the parameter's own unit, e.g. cm/s for ArduPilot speeds)."""
    param_type: int
    """MAV_PARAM_TYPE_* of the parameter."""
    doc: str
    """One line: meaning and unit, and what the emulator does with it."""


_R32 = mavlink.MAV_PARAM_TYPE_REAL32
_I32 = mavlink.MAV_PARAM_TYPE_INT32
_I16 = mavlink.MAV_PARAM_TYPE_INT16
_I8 = mavlink.MAV_PARAM_TYPE_INT8

_PX4_PARAMS = (
    ParamSpec("COM_OF_LOSS_T", 1.0, _R32, "offboard setpoint loss timeout [s] before the failsafe"),
    ParamSpec("COM_OBL_RC_ACT", 0, _I32,
              "offboard-loss action: 0 Position, 1 Altitude, 2 Manual (all Hold without RC), "
              "3 Return, 4 Land, 5 Hold, 6 Terminate, 7 Disarm (6/7 disarm)"),
    ParamSpec("COM_DISARM_LAND", 2.0, _R32, "auto-disarm delay after landing [s] (<0: off)"),
    ParamSpec("COM_DISARM_PRFLT", 10.0, _R32, "auto-disarm delay if armed but no takeoff [s] (<0: off)"),
    ParamSpec("COM_DL_LOSS_T", 10, _I32, "GCS data-link loss timeout [s]"),
    ParamSpec("NAV_DLL_ACT", 0, _I32,
              "data-link loss action: 0 off, 1 Hold, 2 Return, 3 Land, 5/6 disarm"),
    ParamSpec("MIS_TAKEOFF_ALT", 2.5, _R32, "default takeoff altitude above home [m]"),
    ParamSpec("MPC_TKO_SPEED", 1.5, _R32, "takeoff climb speed [m/s]"),
    ParamSpec("MPC_LAND_SPEED", 0.7, _R32, "landing descent speed [m/s]"),
    ParamSpec("MPC_XY_CRUISE", 5.0, _R32, "horizontal speed of auto modes (RTL) [m/s]"),
    ParamSpec("MPC_XY_VEL_MAX", 12.0, _R32, "horizontal velocity setpoint limit [m/s]"),
    ParamSpec("MPC_Z_VEL_MAX_UP", 3.0, _R32, "climb velocity setpoint limit [m/s]"),
    ParamSpec("MPC_Z_VEL_MAX_DN", 1.5, _R32, "descent velocity setpoint limit [m/s]"),
    ParamSpec("RTL_RETURN_ALT", 60.0, _R32, "RTL return altitude above home [m]"),
    ParamSpec("MAV_SYS_ID", 1, _I32, "MAVLink system id (read-only in the emulator)"),
    ParamSpec("MAV_TYPE", 2, _I32, "vehicle type (2 = quadrotor)"),
    ParamSpec("SYS_HITL", 0, _I32, "hardware-in-the-loop (always 0)"),
)

_ARDUPILOT_PARAMS = (
    ParamSpec("GUID_TIMEOUT", 3.0, _R32, "GUIDED velocity-target timeout [s]: then the vehicle stops"),
    ParamSpec("FS_GCS_ENABLE", 0, _I8,
              "GCS heartbeat-loss failsafe: 0 off, 5 Land, other non-zero RTL"),
    ParamSpec("FS_GCS_TIMEOUT", 5.0, _R32, "GCS heartbeat-loss timeout [s]"),
    ParamSpec("DISARM_DELAY", 10, _I8, "auto-disarm delay while landed [s] (0: off)"),
    ParamSpec("LAND_SPEED", 50, _I16, "final landing descent speed [cm/s]"),
    ParamSpec("WPNAV_SPEED", 500.0, _R32, "horizontal speed of auto modes (RTL) [cm/s]"),
    ParamSpec("WPNAV_SPEED_UP", 150.0, _R32,
              "climb speed of takeoff and auto modes [cm/s] (emulator default 150; ArduPilot 250)"),
    ParamSpec("WPNAV_SPEED_DN", 150.0, _R32, "descent speed of auto modes [cm/s]"),
    ParamSpec("RTL_ALT", 1500, _I16, "RTL return altitude above home [cm]"),
    ParamSpec("SYSID_THISMAV", 1, _I16, "MAVLink system id (read-only in the emulator)"),
    ParamSpec("FRAME_CLASS", 1, _I8, "frame class (1 = quad)"),
)


@dataclass(frozen=True)
class Personality:
    """How one autopilot family encodes modes, parameters and identity on MAVLink."""

    name: str
    """``"px4"`` or ``"ardupilot"``."""
    autopilot_type: int
    """MAV_AUTOPILOT_* sent in HEARTBEAT."""
    modes: Mapping[FlightMode, int]
    """Supported flight modes -> ``custom_mode`` word."""
    params: tuple[ParamSpec, ...]
    """Parameter table (order = PARAM_VALUE index)."""
    boot_mode: FlightMode
    """Mode after power-on."""
    hold_mode: FlightMode
    """Mode used for "hold position" (failsafes, airborne start)."""
    offboard_mode: FlightMode
    """Mode in which external position/velocity setpoints are flown."""
    capabilities: int
    """MAV_PROTOCOL_CAPABILITY_* bits of AUTOPILOT_VERSION."""
    flight_sw_version: int
    """AUTOPILOT_VERSION.flight_sw_version (major<<24 | minor<<16 | patch<<8 | type)."""
    _by_custom: Mapping[int, FlightMode] = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_by_custom", MappingProxyType({v: k for k, v in self.modes.items()}))

    # ---- modes -------------------------------------------------------------------------
    def custom_mode(self, mode: FlightMode) -> int:
        """``custom_mode`` word of ``mode`` (KeyError if the personality lacks it)."""
        return self.modes[mode]

    def mode_from_custom(self, custom_mode: int) -> FlightMode | None:
        """FlightMode for a ``custom_mode`` word (SET_MODE / HEARTBEAT), None if unknown."""
        custom_mode = int(custom_mode)
        if self.name == "px4":
            main, sub = px4_main_sub(custom_mode)
            if main != PX4_MAIN_AUTO:
                sub = 0  # PX4 ignores the sub mode outside AUTO
            return self._by_custom.get(px4_custom_mode(main, sub))
        return self._by_custom.get(custom_mode)

    def mode_from_command(self, param2: float, param3: float) -> FlightMode | None:
        """FlightMode for MAV_CMD_DO_SET_MODE params (custom mode, custom sub mode)."""
        if not math.isfinite(param2):
            return None
        if self.name == "px4":
            main, sub = int(param2), int(param3) if math.isfinite(param3) else 0
            if main != PX4_MAIN_AUTO:
                sub = 0
            elif sub == 0:
                sub = PX4_SUB_LOITER  # "AUTO" without sub mode: PX4 picks Hold
            return self._by_custom.get(px4_custom_mode(main, sub))
        return self._by_custom.get(int(param2))

    def mode_name(self, mode: FlightMode) -> str:
        """Human-readable mode name as the autopilot's GCS would show it."""
        if self.name == "px4":
            return _PX4_NAMES[mode]
        return _ARDUPILOT_NAMES[self.modes[mode]]

    # ---- parameters --------------------------------------------------------------------
    def default_params(self, sysid: int = 1) -> dict[str, float]:
        """Fresh parameter values (name -> value), with the system id filled in."""
        values = {p.name: float(p.default) for p in self.params}
        for key in ("MAV_SYS_ID", "SYSID_THISMAV"):
            if key in values:
                values[key] = float(sysid)
        return values

    def param_spec(self, name: str) -> ParamSpec | None:
        """Spec of parameter ``name`` or None."""
        for p in self.params:
            if p.name == name:
                return p
        return None

    def encode_param(self, value: float, param_type: int) -> float:
        """Value for the PARAM_VALUE float field (PX4 byte-wise for integers, else a cast)."""
        if self.name == "px4" and param_type != _R32:
            return struct.unpack("<f", struct.pack("<i", int(round(value))))[0]
        return float(value)

    def decode_param(self, wire_value: float, param_type: int) -> float:
        """Inverse of :meth:`encode_param` for PARAM_SET."""
        if self.name == "px4" and param_type != _R32:
            return float(struct.unpack("<i", struct.pack("<f", wire_value))[0])
        if param_type != _R32:
            return float(int(round(wire_value)))
        return float(wire_value)


_CAP_COMMON = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
)

PX4 = Personality(
    name="px4",
    autopilot_type=mavlink.MAV_AUTOPILOT_PX4,
    modes=MappingProxyType({m: px4_custom_mode(*ms) for m, ms in _PX4_MODES.items()}),
    params=_PX4_PARAMS,
    boot_mode=FlightMode.LOITER,
    hold_mode=FlightMode.LOITER,
    offboard_mode=FlightMode.OFFBOARD,
    capabilities=_CAP_COMMON | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE,
    flight_sw_version=(1 << 24) | (15 << 16) | (0 << 8) | 0xFF,
)
"""PX4 v1.15-like multicopter."""

ARDUPILOT = Personality(
    name="ardupilot",
    autopilot_type=mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
    modes=MappingProxyType(dict(_ARDUPILOT_MODES)),
    params=_ARDUPILOT_PARAMS,
    boot_mode=FlightMode.STABILIZED,
    hold_mode=FlightMode.BRAKE,
    offboard_mode=FlightMode.GUIDED,
    capabilities=_CAP_COMMON | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST,
    flight_sw_version=(4 << 24) | (5 << 16) | (0 << 8) | 0xFF,
)
"""ArduPilot Copter 4.5-like multicopter."""

PERSONALITIES: Mapping[str, Personality] = MappingProxyType({"px4": PX4, "ardupilot": ARDUPILOT})


def get_personality(name: str) -> Personality:
    """Personality by name (``px4`` or ``ardupilot``, case-insensitive; ``apm`` = ardupilot)."""
    key = name.strip().lower()
    if key in ("apm", "ardupilotmega", "arducopter"):
        key = "ardupilot"
    try:
        return PERSONALITIES[key]
    except KeyError:
        raise ValueError(f"unknown autopilot personality {name!r}; expected 'px4' or 'ardupilot'") from None
