"""The emulator's geodetic telemetry is the agent's WGS-84 model (fisc_agent.flight.frames), to < 1 cm over 100 m."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from fisc_agent.flight.frames import GeodeticAnchor
from sim.autopilot.framing import Encoder, new_parser
from sim.autopilot.personalities import PX4
from sim.autopilot.server import AutopilotEmulator
from sim.autopilot.telemetry import TelemetryBuilder

HOMES = [(47.397742, 8.545594, 488.0), (-33.8688, 151.2093, 20.0), (0.5, -78.5, 2850.0), (64.1466, -21.9426, 10.0)]


def _grid_100m() -> np.ndarray:
    """NED points out to 100 m horizontally, 0..30 m up."""
    axis = np.linspace(-100.0, 100.0, 9)
    n, e = np.meshgrid(axis, axis)
    keep = np.hypot(n, e) <= 100.0 + 1e-9
    pts = [(a, b, -d) for a, b in zip(n[keep], e[keep]) for d in (0.0, 12.5, 30.0)]
    return np.array(pts)


def _global_position_int_from_raw_bytes(home, ned) -> list:
    """GLOBAL_POSITION_INT as the emulator frames it for each NED point, decoded from the raw bytes."""
    enc, parser = Encoder(1, 1), new_parser()
    anchor = GeodeticAnchor(*home, 0.0)
    build = TelemetryBuilder(enc.mav, PX4, anchor, 1, lambda: 0.0)
    st0 = AutopilotEmulator("udpin:127.0.0.1:0", home_lla=home).state
    out = []
    for p in ned:
        st = dataclasses.replace(st0, position_ned_m=tuple(p))
        (msg,) = parser.parse_buffer(enc.frame(build.global_position_int(st)))
        out.append(msg)
    return out


@pytest.mark.parametrize("home", HOMES)
def test_emulator_global_position_int_and_the_agents_frames_agree_within_1_cm_over_100_m(home):
    ned = _grid_100m()
    agent = GeodeticAnchor(*home, 0.0)  # what an agent anchored at the emulator's home uses
    errors, sphere_errors = [], []
    for p, msg in zip(ned, _global_position_int_from_raw_bytes(home, ned)):
        lat, lon, alt = msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3
        errors.append(np.linalg.norm(np.subtract(agent.geodetic_to_ned(lat, lon, alt), p)))
        # the spherical flat-earth model the emulator used before (R = 6378137 m)
        r = 6378137.0
        n = math.radians(lat - home[0]) * r
        e = math.radians(lon - home[1]) * r * math.cos(math.radians(home[0]))
        sphere_errors.append(math.hypot(n - p[0], e - p[1]))
    assert max(errors) < 0.01  # 1e-7 deg and mm quantisation only: < 0.8 cm
    assert max(sphere_errors) > 0.1  # the check tells the two earth models apart (tens of cm at 100 m)
