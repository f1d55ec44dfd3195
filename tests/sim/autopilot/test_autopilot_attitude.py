"""The emulated attitude: roll/pitch from the plant's thrust, the ODOMETRY quaternion, and what the agent reads
back from it (``fisc_agent.flight.drag.thrust_accel_ne``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fisc_agent.flight.drag import G_M_S2, thrust_accel_ne
from sim.autopilot.attitude import attitude_from_thrust, euler_to_quaternion, ned_to_body


def _body_to_ned(v, q):
    w, x, y, z = q
    return ned_to_body(v, (w, -x, -y, -z))  # the inverse rotation


@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.5, math.pi])
@pytest.mark.parametrize("acc_ne", [(0.0, 0.0), (1.2, 0.0), (0.0, -0.8), (2.0, 1.5), (-3.0, 4.0)])
def test_the_agent_reads_the_plants_horizontal_thrust_back_from_the_quaternion(yaw, acc_ne):
    thrust = (acc_ne[0], acc_ne[1], -G_M_S2)  # level flight: the thrust holds the weight
    roll, pitch = attitude_from_thrust(thrust, yaw)
    q = euler_to_quaternion(roll, pitch, yaw)
    assert sum(c * c for c in q) == pytest.approx(1.0)
    assert thrust_accel_ne(q) == pytest.approx(acc_ne, abs=1e-9)
    # the body's -z axis points along the thrust
    up_body = _body_to_ned((0.0, 0.0, -1.0), q)
    assert np.asarray(up_body) == pytest.approx(np.asarray(thrust) / np.linalg.norm(thrust), abs=1e-12)


def test_euler_angles_of_simple_attitudes():
    assert euler_to_quaternion(0.0, 0.0, 0.0) == pytest.approx((1.0, 0.0, 0.0, 0.0))
    # pitched nose-down: the thrust leans forward, pitch < 0; rolled right: the thrust leans right, roll > 0
    assert attitude_from_thrust((1.0, 0.0, -G_M_S2), 0.0) == pytest.approx((0.0, -math.atan(1.0 / G_M_S2)))
    assert attitude_from_thrust((0.0, 1.0, -G_M_S2), 0.0) == pytest.approx((math.atan(1.0 / G_M_S2), 0.0))
    # heading east: a northward thrust is a roll to the left
    roll, pitch = attitude_from_thrust((1.0, 0.0, -G_M_S2), math.pi / 2)
    assert roll == pytest.approx(-math.atan(1.0 / G_M_S2)) and pitch == pytest.approx(0.0, abs=1e-12)


def test_a_thrust_that_does_not_point_up_is_taken_as_barely_up():
    roll, pitch = attitude_from_thrust((1.0, 0.0, 0.5), 0.0)
    assert pitch == pytest.approx(-math.pi / 2, abs=1e-5) and roll == pytest.approx(0.0)


def test_ned_to_body_rotates_by_the_heading_and_inverts():
    q = euler_to_quaternion(0.0, 0.0, math.pi / 2)  # facing east
    assert ned_to_body((0.0, 1.0, 0.0), q) == pytest.approx((1.0, 0.0, 0.0), abs=1e-12)  # east is forward
    assert ned_to_body((1.0, 0.0, 0.0), q) == pytest.approx((0.0, -1.0, 0.0), abs=1e-12)  # north is left
    q = euler_to_quaternion(0.3, -0.2, 1.1)
    v = (1.5, -0.4, 0.3)
    assert _body_to_ned(ned_to_body(v, q), q) == pytest.approx(v, abs=1e-12)
