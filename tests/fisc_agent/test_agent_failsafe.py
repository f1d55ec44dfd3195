"""Failsafe decisions, each with its fault injected."""

import math

import pytest

from fisc_agent.flight.failsafe import (HANDOVER_S, GeofencePolicy, GeofenceVerdict, Handover, PositionHealth, geofence,
                                        link_ok, position_health)
from fisc_agent.mavlink.adapters import FRESH_HEARTBEAT_S, ModeClass


def test_position_health_stages():
    assert position_health(0.1, 0.5, 2.0) == PositionHealth.OK
    assert position_health(0.5, 0.5, 2.0) == PositionHealth.OK
    assert position_health(0.6, 0.5, 2.0) == PositionHealth.STALE    # -> zero-velocity hold
    assert position_health(2.5, 0.5, 2.0) == PositionHealth.STALE
    assert position_health(2.6, 0.5, 2.0) == PositionHealth.LOST     # -> autopilot hold mode
    assert position_health(math.inf, 0.5, 2.0) == PositionHealth.LOST  # never had a fix
    assert position_health(math.nan, 0.5, 2.0) == PositionHealth.LOST


def test_link_health():
    assert link_ok(1.0, 3.0)
    assert link_ok(3.0, 3.0)  # equal: still fine
    assert not link_ok(math.nextafter(3.0, 4.0), 3.0)  # one step outside
    assert not link_ok(3.5, 3.0)
    assert not link_ok(math.inf, 3.0)


def test_geofence_inside_exit_and_policies():
    assert geofence(7, 1.0, 15.0, "hold") == GeofenceVerdict.INSIDE
    assert geofence(0, 1.0, 15.0, "hold") == GeofenceVerdict.INSIDE  # CV 0 is a CV
    assert geofence(0, 20.0, 15.0, "hold") == GeofenceVerdict.INSIDE  # inside a CV wins over the outlet plane
    assert geofence(-1, 15.0, 15.0, "hold") == GeofenceVerdict.EXIT     # through the outlet plane
    assert geofence(-1, 16.0, 15.0, "return") == GeofenceVerdict.EXIT
    assert geofence(-1, 5.0, 15.0, "hold") == GeofenceVerdict.HOLD      # out through a side
    assert geofence(-1, 5.0, 15.0, "return") == GeofenceVerdict.RETURN
    assert geofence(-1, -0.5, 15.0, "return") == GeofenceVerdict.RETURN  # back out of the inlet
    assert geofence(-1, 5.0, 15.0, GeofencePolicy.RETURN) == GeofenceVerdict.RETURN
    with pytest.raises(ValueError, match="policy"):
        geofence(-1, 5.0, 15.0, "ignore")


def test_policy_options_become_enums_and_bad_ones_name_the_choices():
    from fisc_agent.config import AgentConfig, ExitPolicy

    cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=1, exit_policy="loop", geofence="return")
    assert cfg.exit_policy is ExitPolicy.LOOP and cfg.geofence is GeofencePolicy.RETURN
    with pytest.raises(ValueError, match="exit_policy must be one of hold, land, loop, is 'fly'"):
        AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=1, exit_policy="fly")


def test_a_handover_streams_zero_in_offboard_while_the_request_waits_then_stops():
    """Handing the vehicle to the autopilot's hold or land mode: zero velocity while it is still in offboard, for
    HANDOVER_S from the handover's first tick (longer than a request's wait for a fresh 1 Hz HEARTBEAT); nothing
    in any other mode; a reset (a new state) starts over."""
    assert HANDOVER_S > 1.0 + FRESH_HEARTBEAT_S
    h = Handover()
    assert h.velocity(10.0, ModeClass.OFFBOARD) == (0.0, 0.0, 0.0)                  # the first tick starts it
    assert h.velocity(10.0 + HANDOVER_S - 1e-3, ModeClass.OFFBOARD) == (0.0, 0.0, 0.0)   # just inside
    assert h.velocity(10.0 + HANDOVER_S, ModeClass.OFFBOARD) is None                # on the bound: over
    for mode in (ModeClass.HOLD, ModeClass.LAND, ModeClass.OTHER, ModeClass.UNKNOWN):
        assert Handover().velocity(0.0, mode) is None, mode                         # handed over, or not ours
    h.reset()
    assert h.velocity(20.0, ModeClass.OFFBOARD) == (0.0, 0.0, 0.0)
