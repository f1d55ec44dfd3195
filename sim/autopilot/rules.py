"""The personality's flight rules, read from the vehicle's live parameter table (pure).

PX4 and ArduPilot Copter spell the same rules with different parameters and units (ArduPilot
speeds and altitudes in cm/s and cm): command limits, takeoff/land/cruise speeds, the RTL
altitude, failsafe actions and auto-disarm delays.  The values are read on every call, so a
PARAM_SET takes effect at once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

from sim.autopilot.personalities import FlightMode
from sim.autopilot.vehicle_types import FAILED, TEMPORARILY_REJECTED

__all__ = ["AP_NO_RC_DESCENT_M_S", "FailsafeAction", "PersonalityRules"]

# ArduPilot modes that take the climb rate from the RC throttle stick: with no RC (a swarm
# vehicle) the stick reads low and the vehicle descends (real ArduCopter SITL: LOITER with no
# RC descended and hit the ground at 2.47 m/s).  PX4's AUTO.LOITER holds altitude by itself.
_AP_THROTTLE_STICK_MODES = frozenset({FlightMode.LOITER, FlightMode.ALTCTL, FlightMode.POSCTL})
AP_NO_RC_DESCENT_M_S = 2.5
"""Descent rate of an ArduPilot throttle-stick mode with no RC [m/s] (PILOT_SPEED_DN default)."""


@dataclass(frozen=True)
class FailsafeAction:
    """What a failsafe does."""

    mode: FlightMode | None
    """Mode to enter (None: keep the mode)."""
    disarm: bool = False
    """Disarm (after entering ``mode``)."""


class PersonalityRules:
    """Rules of a PX4 (``px4=True``) or ArduPilot Copter vehicle from its parameter table."""

    def __init__(self, px4: bool, params: Mapping[str, float]) -> None:
        self._px4 = px4
        self._p = params

    @property
    def reject_code(self) -> int:
        """MAV_RESULT of "not now": PX4 TEMPORARILY_REJECTED, ArduPilot FAILED."""
        return TEMPORARILY_REJECTED if self._px4 else FAILED

    def command_limits_m_s(self) -> tuple[float, float, float]:
        """(horizontal max, climb max, descent max) [m/s] of velocity commands."""
        p = self._p
        if self._px4:
            return p["MPC_XY_VEL_MAX"], p["MPC_Z_VEL_MAX_UP"], p["MPC_Z_VEL_MAX_DN"]
        return 0.01 * p["WPNAV_SPEED"], 0.01 * p["WPNAV_SPEED_UP"], 0.01 * p["WPNAV_SPEED_DN"]

    def takeoff_speed_m_s(self) -> float:
        """Climb rate of a takeoff [m/s]."""
        return self._p["MPC_TKO_SPEED"] if self._px4 else 0.01 * self._p["WPNAV_SPEED_UP"]

    def land_speed_m_s(self) -> float:
        """Descent rate of LAND [m/s]."""
        return self._p["MPC_LAND_SPEED"] if self._px4 else 0.01 * self._p["LAND_SPEED"]

    def cruise_speed_m_s(self) -> float:
        """Horizontal speed of the RTL return leg [m/s]."""
        return self._p["MPC_XY_CRUISE"] if self._px4 else 0.01 * self._p["WPNAV_SPEED"]

    def rtl_altitude_m(self) -> float:
        """Minimum altitude above home of the RTL return leg [m]."""
        return self._p["RTL_RETURN_ALT"] if self._px4 else 0.01 * self._p["RTL_ALT"]

    def no_rc_descent_m_s(self, mode: FlightMode) -> float | None:
        """Descent rate [m/s] of a mode that flies the RC throttle stick with no RC (ArduPilot
        LOITER, ALT_HOLD, POSHOLD), None where the mode holds altitude by itself."""
        return AP_NO_RC_DESCENT_M_S if not self._px4 and mode in _AP_THROTTLE_STICK_MODES else None

    def offboard_loss_timeout_s(self) -> float:
        """PX4 COM_OF_LOSS_T: OFFBOARD without setpoints for this long triggers the failsafe [s]."""
        return self._p["COM_OF_LOSS_T"]

    def offboard_loss_action(self) -> FailsafeAction:
        """PX4 COM_OBL_RC_ACT: 3 RTL, 4 LAND, 6/7 Hold and disarm; 0 Position, 1 Altitude,
        2 Manual (no RC here) and 5 Hold: Hold (AUTO.LOITER)."""
        act = int(self._p["COM_OBL_RC_ACT"])
        if act == 3:
            return FailsafeAction(FlightMode.RTL)
        if act == 4:
            return FailsafeAction(FlightMode.LAND)
        return FailsafeAction(FlightMode.LOITER, disarm=act in (6, 7))

    def gcs_loss(self) -> tuple[int, float]:
        """(action, timeout [s]) of the GCS heartbeat-loss failsafe: PX4 NAV_DLL_ACT /
        COM_DL_LOSS_T, ArduPilot FS_GCS_ENABLE / FS_GCS_TIMEOUT (action 0: disabled)."""
        if self._px4:
            return int(self._p["NAV_DLL_ACT"]), self._p["COM_DL_LOSS_T"]
        return int(self._p["FS_GCS_ENABLE"]), self._p["FS_GCS_TIMEOUT"]

    def gcs_loss_action(self, action: int) -> FailsafeAction:
        """PX4 NAV_DLL_ACT 1 Hold, 2 RTL, 3 LAND, 5/6 disarm (else Hold); ArduPilot FS_GCS_ENABLE
        5 LAND, else RTL."""
        if not self._px4:
            return FailsafeAction(FlightMode.LAND if action == 5 else FlightMode.RTL)
        if action in (5, 6):
            return FailsafeAction(None, disarm=True)
        return FailsafeAction({1: FlightMode.LOITER, 2: FlightMode.RTL, 3: FlightMode.LAND}.get(action, FlightMode.LOITER))

    def auto_disarm_delay_s(self, ever_airborne: bool) -> float:
        """Delay before a vehicle on the ground disarms [s] (< 0: never): PX4 COM_DISARM_LAND
        after a flight, COM_DISARM_PRFLT before one; ArduPilot DISARM_DELAY (0 disables it)."""
        p = self._p
        if self._px4:
            return p["COM_DISARM_LAND"] if ever_airborne else p["COM_DISARM_PRFLT"]
        return p["DISARM_DELAY"] if p["DISARM_DELAY"] > 0 else -1.0
