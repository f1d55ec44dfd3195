"""The GNSS receiver's own velocity from GPS_RAW_INT (pure decoding).

An autopilot's velocity estimate can stray far from the truth while its receiver's stays close: on
stock PX4 SIH the EKF2 velocity was 0.33 m/s RMS off SIH's ground truth (up to 0.9 m/s), the
receiver's 0.10 m/s RMS, without a measurable delay (``tests/faults`` seed 7, 2026-12-05).  The agent
learns its estimator's velocity bias from it (``fisc_agent.flight.tracking.ParcelTracker.observe``).
"""

from __future__ import annotations

import math

from fisc_agent.mavlink.interfaces import GnssVelocity

GNSS_FIX_3D = 3
"""GPS_RAW_INT ``fix_type`` from which its velocity is used (GPS_FIX_TYPE_3D_FIX)."""
UINT16_UNKNOWN = 65535
"""GPS_RAW_INT's value of an unknown ``vel`` or ``cog``."""


def ground_velocity(t_s: float, fix_type: int, speed_m_s: float, course_deg: float) -> GnssVelocity | None:
    """A receiver's ground speed ``speed_m_s`` along its course over ground ``course_deg`` (clockwise from
    north) at ``t_s`` as (north, east) velocity; None without a 3D fix or with a value not finite."""
    if int(fix_type) < GNSS_FIX_3D or not (math.isfinite(speed_m_s) and math.isfinite(course_deg)):
        return None
    course = math.radians(course_deg)
    return GnssVelocity(t_s, (speed_m_s * math.cos(course), speed_m_s * math.sin(course)))


def gnss_velocity(msg, t_s: float) -> GnssVelocity | None:
    """GPS_RAW_INT ``msg`` received at ``t_s`` as (north, east) velocity: its ground speed ``vel`` [cm/s]
    along its course ``cog`` [cdeg]; None without a 3D fix or with either field unknown."""
    if msg.vel == UINT16_UNKNOWN or msg.cog == UINT16_UNKNOWN:
        return None
    return ground_velocity(t_s, msg.fix_type, msg.vel * 0.01, msg.cog * 0.01)


def mavsdk_ground_velocity(t_s: float, fix_type: int, speed_m_s: float, course_deg: float) -> GnssVelocity | None:
    """MAVSDK's ``RawGps`` (its ``velocity_m_s`` and ``cog_deg``, GPS_RAW_INT's ``vel`` and ``cog`` scaled by
    0.01 as they came, an unknown one as 655.35) with the fix type of its ``GpsInfo``, as ``ground_velocity``."""
    if speed_m_s >= UINT16_UNKNOWN * 0.01 - 1e-3 or course_deg >= UINT16_UNKNOWN * 0.01 - 1e-3:
        return None
    return ground_velocity(t_s, fix_type, speed_m_s, course_deg)
