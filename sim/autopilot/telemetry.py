"""Telemetry messages of the autopilot emulator, built from an immutable vehicle snapshot.

:class:`TelemetryBuilder` turns a :class:`~sim.autopilot.vehicle_types.VehicleState` into the
MAVLink messages a PX4 / ArduPilot Copter autopilot streams (HEARTBEAT, SYS_STATUS, positions,
attitude, ...).  Geodetic positions come from the agent's WGS-84 model
(:class:`fisc_agent.flight.frames.GeodeticAnchor` at the emulator's home), so what the emulator sends in
GLOBAL_POSITION_INT is what an agent anchored there converts back to local NED.
"""

from __future__ import annotations

import math
from typing import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from fisc_agent.flight.frames import GeodeticAnchor
from sim.autopilot.attitude import euler_to_quaternion, ned_to_body
from sim.autopilot.personalities import Personality
from sim.autopilot.vehicle_types import VehicleState

__all__ = ["POSITION_MESSAGES", "TelemetryBuilder", "default_intervals_s"]

POSITION_MESSAGES = frozenset({mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT})
"""Messages that carry a position (suppressed during a position dropout)."""

_SENSORS = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE | mavlink.MAV_SYS_STATUS_SENSOR_GPS
    | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mavlink.MAV_SYS_STATUS_SENSOR_YAW_POSITION | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | mavlink.MAV_SYS_STATUS_AHRS | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY | mavlink.MAV_SYS_STATUS_PREARM_CHECK
)  # fmt: skip
_POSITION_SENSORS = mavlink.MAV_SYS_STATUS_SENSOR_GPS | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL


def default_intervals_s(rate_position_hz: float, rate_attitude_hz: float) -> dict[int, float]:
    """Message id -> stream interval [s] at start (0: not streamed): 1 Hz status, 2 Hz VFR_HUD,
    0.5 Hz HOME_POSITION, positions and attitude at the given rates (0 Hz: off)."""
    position_s = 1.0 / rate_position_hz if rate_position_hz > 0 else 0.0
    return {
        mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
        mavlink.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
        mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0,
        mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
        mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 1.0,
        mavlink.MAVLINK_MSG_ID_HOME_POSITION: 2.0,
        mavlink.MAVLINK_MSG_ID_VFR_HUD: 0.5,
        mavlink.MAVLINK_MSG_ID_ATTITUDE: 1.0 / rate_attitude_hz if rate_attitude_hz > 0 else 0.0,
        mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: position_s,
        mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: position_s,
    }


def _payload_packer(cls: type) -> Callable[[tuple], bytes]:
    """Wire-order payload of a pymavlink message class without arrays, from its ``*_encode`` arguments."""
    perm = [cls.fieldnames.index(n) for n in cls.ordered_fieldnames]
    pack = cls.unpacker.pack
    return lambda args: pack(*[args[i] for i in perm])


_HEARTBEAT_PAYLOAD = _payload_packer(mavlink.MAVLink_heartbeat_message)
_LOCAL_POSITION_PAYLOAD = _payload_packer(mavlink.MAVLink_local_position_ned_message)


def _i16(x: float) -> int:
    return int(max(-32768, min(32767, round(x))))


def _e7(deg: float) -> int:
    return int(round(deg * 1e7))


def _mm(m: float) -> int:
    return int(round(m * 1000))


class TelemetryBuilder:
    """The emulator's streamed messages as functions of a vehicle snapshot.

    ``mav``: the pymavlink MAVLink object whose ``*_encode`` methods build the messages;
    ``anchor``: home as the geodetic origin of local NED; ``wall_clock``: Unix time [s]."""

    def __init__(
        self,
        mav: mavlink.MAVLink,
        personality: Personality,
        anchor: GeodeticAnchor,
        sysid: int,
        wall_clock: Callable[[], float],
    ) -> None:
        self._mav, self._personality, self._anchor = mav, personality, anchor
        self._sysid, self._wall = sysid, wall_clock
        self.builders: dict[int, Callable[[VehicleState], object]] = {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: self.heartbeat,
            mavlink.MAVLINK_MSG_ID_SYS_STATUS: self.sys_status,
            mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: self.extended_sys_state,
            mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: self.system_time,
            mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: self.gps_raw_int,
            mavlink.MAVLINK_MSG_ID_HOME_POSITION: self.home_position,
            mavlink.MAVLINK_MSG_ID_VFR_HUD: self.vfr_hud,
            mavlink.MAVLINK_MSG_ID_ATTITUDE: self.attitude,
            mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: self.local_position_ned,
            mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self.global_position_int,
            mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self.autopilot_version,
        }
        """Message id -> builder, for every message the emulator can send on request or stream."""
        if personality.name == "px4":  # ArduPilot refuses ODOMETRY (fisc_agent.mavlink.health_reader)
            self.builders[mavlink.MAVLINK_MSG_ID_ODOMETRY] = self.odometry
        self.payloads: dict[int, tuple[bytes, Callable[[VehicleState], bytes]]] = {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: (bytes((mavlink.MAVLink_heartbeat_message.crc_extra,)),
                                               self.heartbeat_payload),
            mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: (
                bytes((mavlink.MAVLink_local_position_ned_message.crc_extra,)), self.local_position_ned_payload),
        }
        """Message id -> (CRC extra, wire-order payload of the builder's message) for the streams sent
        most (framed without a message object by ``sim.autopilot.framing.Encoder.frame_payload``)."""

    @staticmethod
    def _boot_ms(st: VehicleState) -> int:
        return int(st.t_s * 1000.0) & 0xFFFFFFFF

    def heartbeat(self, st: VehicleState) -> object:
        """HEARTBEAT: quadrotor, the personality's autopilot type, mode flags and custom mode."""
        return self._mav.heartbeat_encode(*self._heartbeat_args(st))

    def heartbeat_payload(self, st: VehicleState) -> bytes:
        """The wire-order payload of ``heartbeat(st)``."""
        return _HEARTBEAT_PAYLOAD(self._heartbeat_args(st))

    def _heartbeat_args(self, st: VehicleState) -> tuple:
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
        if not st.mode.needs_pilot:
            base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED | mavlink.MAV_MODE_FLAG_AUTO_ENABLED
        if st.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        status = mavlink.MAV_STATE_ACTIVE if st.armed else mavlink.MAV_STATE_STANDBY
        return (mavlink.MAV_TYPE_QUADROTOR, self._personality.autopilot_type, base, st.custom_mode, status, 3)

    def sys_status(self, st: VehicleState) -> object:
        """SYS_STATUS: all sensors present and enabled; position sensors unhealthy without a fix."""
        health = _SENSORS if st.position_valid else _SENSORS & ~(_POSITION_SENSORS | mavlink.MAV_SYS_STATUS_PREARM_CHECK)
        return self._mav.sys_status_encode(_SENSORS, _SENSORS, health, 200, 16200, 500 if st.armed else 0, 100,
                                           0, 0, 0, 0, 0, 0)  # fmt: skip

    def extended_sys_state(self, st: VehicleState) -> object:
        """EXTENDED_SYS_STATE: multicopter, landed state."""
        return self._mav.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_MC, st.landed_state)

    def system_time(self, st: VehicleState) -> object:
        """SYSTEM_TIME: Unix time and time since boot."""
        return self._mav.system_time_encode(int(self._wall() * 1e6), self._boot_ms(st))

    def gps_raw_int(self, st: VehicleState) -> object:
        """GPS_RAW_INT: a 3D fix at the vehicle's true position and velocity (the receiver's, not the estimate's;
        no fix during a dropout)."""
        ok = st.position_valid
        lat, lon, alt = self._anchor.ned_to_geodetic(*st.position_ned_m)
        vn, ve, _ = st.velocity_ned_m_s
        cog = (math.degrees(math.atan2(ve, vn)) % 360.0) * 100 if math.hypot(vn, ve) > 0.1 else 65535
        return self._mav.gps_raw_int_encode(
            int(st.t_s * 1e6), mavlink.GPS_FIX_TYPE_3D_FIX if ok else mavlink.GPS_FIX_TYPE_NO_FIX,
            _e7(lat) if ok else 0, _e7(lon) if ok else 0, _mm(alt) if ok else 0,
            80, 120, int(round(math.hypot(vn, ve) * 100)), int(cog) % 65536, 12 if ok else 0,
        )  # fmt: skip

    def home_position(self, st: VehicleState) -> object:
        """HOME_POSITION: geodetic and local home."""
        lat, lon, alt = self._anchor.ned_to_geodetic(*st.home_ned_m)
        x, y, z = st.home_ned_m
        return self._mav.home_position_encode(
            _e7(lat), _e7(lon), _mm(alt), x, y, z, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, int(st.t_s * 1e6),
        )  # fmt: skip

    def vfr_hud(self, st: VehicleState) -> object:
        """VFR_HUD: ground speed, heading, throttle, altitude AMSL, climb rate."""
        vn, ve, vd = st.reported_velocity_ned_m_s
        gs = math.hypot(vn, ve)
        alt = self._anchor.alt_m - st.reported_position_ned_m[2]
        throttle = 50 if (st.armed and st.in_air) else 0
        return self._mav.vfr_hud_encode(gs, gs, int(math.degrees(st.yaw_rad) % 360), throttle, alt, -vd)

    def attitude(self, st: VehicleState) -> object:
        """ATTITUDE: roll/pitch from the realised thrust, heading, yaw rate."""
        return self._mav.attitude_encode(self._boot_ms(st), st.roll_rad, st.pitch_rad, st.yaw_rad, 0.0, 0.0, st.yaw_rate_rad_s)

    def odometry(self, st: VehicleState) -> object:
        """ODOMETRY as PX4 streams it: position in local NED, attitude (roll/pitch from the realised thrust),
        velocity and body rates in body FRD, no covariances, estimator resets never (counter 0)."""
        q = euler_to_quaternion(st.roll_rad, st.pitch_rad, st.yaw_rad)
        unknown = [math.nan] + [0.0] * 20
        return self._mav.odometry_encode(
            int(st.t_s * 1e6), mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_FRD, *st.reported_position_ned_m, q,
            *ned_to_body(st.reported_velocity_ned_m_s, q), 0.0, 0.0, st.yaw_rate_rad_s, unknown, unknown, 0,
            mavlink.MAV_ESTIMATOR_TYPE_AUTOPILOT, 100,
        )  # fmt: skip

    def local_position_ned(self, st: VehicleState) -> object:
        """LOCAL_POSITION_NED: the estimated position and velocity in the EKF frame."""
        return self._mav.local_position_ned_encode(self._boot_ms(st), *st.reported_position_ned_m,
                                                   *st.reported_velocity_ned_m_s)

    def local_position_ned_payload(self, st: VehicleState) -> bytes:
        """The wire-order payload of ``local_position_ned(st)``."""
        return _LOCAL_POSITION_PAYLOAD((self._boot_ms(st), *st.reported_position_ned_m, *st.reported_velocity_ned_m_s))

    def global_position_int(self, st: VehicleState) -> object:
        """GLOBAL_POSITION_INT: WGS-84 position (1e-7 deg, mm AMSL), height above home, velocity."""
        pos = st.reported_position_ned_m
        lat, lon, alt = self._anchor.ned_to_geodetic(*pos)
        rel = st.home_ned_m[2] - pos[2]
        vn, ve, vd = st.reported_velocity_ned_m_s
        hdg = int(round(math.degrees(st.yaw_rad) % 360.0 * 100)) % 36000
        return self._mav.global_position_int_encode(
            self._boot_ms(st), _e7(lat), _e7(lon), _mm(alt), _mm(rel), _i16(vn * 100), _i16(ve * 100), _i16(vd * 100), hdg,
        )  # fmt: skip

    def autopilot_version(self, st: VehicleState) -> object:
        """AUTOPILOT_VERSION: the personality's capabilities and version; uid from the system id."""
        p = self._personality
        return self._mav.autopilot_version_encode(
            p.capabilities, p.flight_sw_version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0x46495343_0000 + self._sysid
        )

    def param_value(self, index: int, values: dict[str, float]) -> object:
        """PARAM_VALUE of the personality's parameter ``index`` with the vehicle's current ``values``."""
        params = self._personality.params
        spec = params[index]
        value = self._personality.encode_param(values[spec.name], spec.param_type)
        return self._mav.param_value_encode(spec.name.encode("ascii"), value, spec.param_type, len(params), index)
