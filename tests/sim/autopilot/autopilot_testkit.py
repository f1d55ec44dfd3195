"""Helpers for the autopilot emulator tests: free ports and a small pymavlink ground-station client."""

from __future__ import annotations

import math
import time
from typing import Callable

from pymavlink import mavutil

VEL_ONLY_MASK = 0b0000_1101_1100_0111  # ignore position, acceleration, yaw, yaw rate
POS_ONLY_MASK = 0b0000_1101_1111_1000  # ignore velocity, acceleration, yaw, yaw rate
POS_VEL_MASK = 0b0000_1101_1100_0000  # position + velocity




class Client:
    """A ground-station-like pymavlink client (unmodified mavutil connection)."""

    def __init__(self, url: str, target_system: int = 1) -> None:
        self.conn = mavutil.mavlink_connection(url, source_system=255, source_component=190)
        self.mav = self.conn.mav
        self.target = target_system
        self.log: list[object] = []
        self.heartbeat()

    def close(self) -> None:
        self.conn.close()

    def heartbeat(self) -> None:
        self.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def wait(self, kind: str | list[str], cond: Callable[[object], bool] = lambda m: True,
             timeout: float = 5.0, tick: Callable[[], None] | None = None, past: bool = False) -> object:
        """First message of ``kind`` from the target satisfying ``cond`` (AssertionError on timeout).

        ``past=True`` also accepts a message received earlier (every message is logged)."""
        kinds = {kind} if isinstance(kind, str) else set(kind)

        def ok(m: object) -> bool:
            return m.get_type() in kinds and m.get_srcSystem() == self.target and cond(m)

        if past:
            for m in self.log:
                if ok(m):
                    return m
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if tick is not None:
                tick()
            m = self.conn.recv_match(blocking=True, timeout=0.05)
            if m is None:
                continue
            self.log.append(m)
            if ok(m):
                return m
        raise AssertionError(f"no {kind} matching the condition within {timeout} s")

    def command(self, command: int, *params: float, timeout: float = 3.0,
                tick: Callable[[], None] | None = None) -> object:
        """Send COMMAND_LONG and return its COMMAND_ACK."""
        p = list(params) + [0.0] * (7 - len(params))
        self.mav.command_long_send(self.target, 1, command, 0, *p)
        return self.wait("COMMAND_ACK", lambda m: m.command == command, timeout, tick)

    def arm(self) -> object:
        return self.command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)

    def set_mode_px4(self, main: int, sub: int = 0, tick: Callable[[], None] | None = None) -> object:
        return self.command(mavutil.mavlink.MAV_CMD_DO_SET_MODE,
                            mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub, tick=tick)

    def set_mode_number(self, number: int, tick: Callable[[], None] | None = None) -> object:
        return self.command(mavutil.mavlink.MAV_CMD_DO_SET_MODE,
                            mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, number, tick=tick)

    def send_velocity(self, vn: float, ve: float, vd: float) -> None:
        self.mav.set_position_target_local_ned_send(
            0, self.target, 1, mavutil.mavlink.MAV_FRAME_LOCAL_NED, VEL_ONLY_MASK,
            0, 0, 0, vn, ve, vd, 0, 0, 0, 0, 0,
        )

    def streamer(self, vn: float, ve: float, vd: float, rate_hz: float = 20.0) -> Callable[[], None]:
        """A tick function sending the velocity setpoint at ``rate_hz``."""
        last = [-math.inf]

        def tick() -> None:
            now = time.monotonic()
            if now - last[0] >= 1.0 / rate_hz:
                last[0] = now
                self.send_velocity(vn, ve, vd)

        return tick

    def run_for(self, seconds: float, tick: Callable[[], None] | None = None) -> None:
        """Keep ticking (and draining input) for ``seconds``."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if tick is not None:
                tick()
            m = self.conn.recv_match(blocking=True, timeout=0.02)
            if m is not None:
                self.log.append(m)


