"""MAVSDK (native 4.x binding, ``mavsdk.asyncio``) flies the PX4 personality: connect, health,
arm, takeoff, offboard velocity north."""

from __future__ import annotations

import asyncio
import time

import pytest

from ...ports import free_udp_port
from sim.autopilot.personalities import FlightMode
from sim.autopilot.server import AutopilotEmulator
from ...optional import require_module

mavsdk_asyncio = require_module("mavsdk.asyncio", extra="mavsdk")


async def _fly(port: int, em: AutopilotEmulator) -> dict:
    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.action import ActionAsync
    from mavsdk.asyncio.plugins.offboard import OffboardAsync, VelocityNedYaw
    from mavsdk.asyncio.plugins.telemetry import FlightMode as MavsdkFlightMode
    from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

    result: dict = {}
    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as mavsdk:
        await mavsdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        drone = await mavsdk.first_autopilot(timeout_s=10.0)
        assert drone is not None, "MAVSDK saw no autopilot"
        assert await drone.is_connected()
        tel, action, offboard = TelemetryAsync(drone), ActionAsync(drone), OffboardAsync(drone)
        for _ in range(100):
            health = await tel.health()
            if health.is_global_position_ok and health.is_home_position_ok and health.is_local_position_ok:
                break
            await asyncio.sleep(0.1)
        result["health"] = health
        await action.set_takeoff_altitude(1.5)
        await action.arm()
        await action.takeoff()
        for _ in range(100):
            if (await tel.position()).relative_altitude_m > 1.2:
                break
            await asyncio.sleep(0.1)
        result["takeoff_alt"] = (await tel.position()).relative_altitude_m
        start_lat = (await tel.position()).latitude_deg
        await offboard.set_velocity_ned(VelocityNedYaw(1.0, 0.0, 0.0, 0.0))
        await offboard.start()
        await asyncio.sleep(2.0)
        result["mode"] = await tel.flight_mode()
        result["offboard_mode_expected"] = MavsdkFlightMode.OFFBOARD
        result["dlat"] = (await tel.position()).latitude_deg - start_lat
        result["emulator_mode"] = em.state.mode
        result["north_m"] = em.state.position_ned_m[0]
        await offboard.stop()
    return result


@pytest.mark.slow
def test_mavsdk_takes_off_and_flies_offboard_north():
    port = free_udp_port()
    em = AutopilotEmulator(f"udpout:127.0.0.1:{port}", personality="px4").start()
    try:
        t0 = time.monotonic()
        r = asyncio.run(asyncio.wait_for(_fly(port, em), timeout=40.0))
    finally:
        em.stop()
    h = r["health"]
    assert h.is_global_position_ok and h.is_home_position_ok and h.is_local_position_ok and h.is_armable
    assert r["takeoff_alt"] > 1.2
    assert r["mode"] == r["offboard_mode_expected"] and r["emulator_mode"] == FlightMode.OFFBOARD
    assert r["north_m"] > 1.0 and r["dlat"] > 0.0
    assert time.monotonic() - t0 < 40.0


async def _fly_ardupilot(port: int, em: AutopilotEmulator) -> None:
    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.action import ActionAsync
    from mavsdk.asyncio.plugins.offboard import OffboardAsync, VelocityNedYaw
    from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as mavsdk:
        await mavsdk.add_any_connection(f"udpout://127.0.0.1:{port}")  # emulator listens (udpin)
        drone = await mavsdk.first_autopilot(timeout_s=10.0)
        assert drone is not None, "MAVSDK saw no autopilot"
        tel, action, offboard = TelemetryAsync(drone), ActionAsync(drone), OffboardAsync(drone)
        for _ in range(100):
            if (await tel.health()).is_home_position_ok:
                break
            await asyncio.sleep(0.1)
        await action.set_takeoff_altitude(1.0)
        await action.arm()
        await action.takeoff()  # MAVSDK switches to GUIDED, then NAV_TAKEOFF
        for _ in range(100):
            if em.state.position_ned_m[2] < -0.9:
                break
            await asyncio.sleep(0.1)
        assert em.state.mode == FlightMode.GUIDED and em.state.armed
        await offboard.set_velocity_ned(VelocityNedYaw(0.0, -1.0, 0.0, 0.0))
        await offboard.start()
        await asyncio.sleep(1.5)
        assert em.state.position_ned_m[1] < -0.5  # flew west
        await action.land()
        for _ in range(100):
            if not em.state.armed:
                break
            await asyncio.sleep(0.1)
        assert not em.state.armed and em.state.position_ned_m[2] == 0.0


@pytest.mark.slow
def test_mavsdk_flies_the_ardupilot_personality():
    em = AutopilotEmulator("udpin:127.0.0.1:0", personality="ardupilot").start()
    try:
        asyncio.run(asyncio.wait_for(_fly_ardupilot(em.local_address[1], em), timeout=40.0))
    finally:
        em.stop()
