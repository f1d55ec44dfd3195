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


def gnss_velocity(msg, t_s: float) -> GnssVelocity | None:
    """GPS_RAW_INT ``msg`` received at ``t_s`` as (north, east) velocity: its ground speed ``vel`` [cm/s]
    along its course ``cog`` [cdeg]; None without a 3D fix or with either field unknown."""
    if int(msg.fix_type) < GNSS_FIX_3D or msg.vel == UINT16_UNKNOWN or msg.cog == UINT16_UNKNOWN:
        return None
    speed, course = msg.vel * 0.01, math.radians(msg.cog * 0.01)
    return GnssVelocity(t_s, (speed * math.cos(course), speed * math.sin(course)))
