"""A tiny fake autopilot for the agent's end-to-end tests (real UDP on 127.0.0.1, pymavlink).

Not an emulator (that is ``sim.autopilot``): just enough to fly the agent's mission -
HEARTBEAT with PX4 or ArduPilot mode encodings, LOCAL_POSITION_NED / GLOBAL_POSITION_INT at
50 Hz, COMMAND_ACKs, mode changes, arming, ArduPilot NAV_TAKEOFF, a first-order velocity
response to SET_POSITION_TARGET_LOCAL_NED, PX4's "OFFBOARD needs a running stream" rule and
its offboard-loss hold, landing and disarm on the ground.  Every setpoint and command is
recorded.  Faults: ``mute`` (send nothing: link loss), ``drop_position`` (no position).
"""

from __future__ import annotations

import math
import threading
import time

from fisc_agent.frames import GeodeticAnchor
from fisc_agent.link import _import_mavutil

PX4_MODES = {"posctl": (3, 0), "offboard": (6, 0), "hold": (4, 3), "land": (4, 6)}
HOLD_MODES = {"hold", "loiter", "brake"}
AP_MODES = {"stabilize": 0, "guided": 4, "loiter": 5, "land": 9, "brake": 17}


class FakeAutopilot:
    def __init__(self, url: str, personality: str = "px4", start_ned=(0.0, 0.0, 0.0), sysid: int = 1,
                 geo_origin=(47.3977, 8.5456, 488.0), tau_s: float = 0.15) -> None:
        self.personality = personality
        self.pos = list(start_ned)
        self.vel = [0.0, 0.0, 0.0]
        self.armed = False
        self.mode = "posctl" if personality == "px4" else "stabilize"
        if start_ned[2] < 0:  # starts in the air: armed and holding
            self.armed, self.mode = True, "hold" if personality == "px4" else "loiter"
        self.sysid = sysid
        self.tau_s = tau_s
        self.geo = GeodeticAnchor(geo_origin[0], geo_origin[1], geo_origin[2], 0.0)
        self.setpoints: list[tuple[float, float, float, float, int, int]] = []
        self.commands: list[tuple[int, tuple]] = []
        self.modes_seen: list[str] = [self.mode]
        self.mute = False
        self.drop_position = False
        self.takeoff_alt: float | None = None
        self._last_sp_t = -math.inf
        self._sp = (0.0, 0.0, 0.0)
        self._mavutil = _import_mavutil()
        self.conn = self._mavutil.mavlink_connection(url, source_system=sysid, source_component=1)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True, name="fake-autopilot")
        self._lock = threading.Lock()

    # ---- lifecycle ---------------------------------------------------------------------------
    def start(self) -> "FakeAutopilot":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.conn.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    # ---- MAVLink -------------------------------------------------------------------------------
    def _custom_mode(self) -> int:
        if self.personality == "px4":
            main, sub = PX4_MODES[self.mode]
            return (main << 16) | (sub << 24)
        return AP_MODES[self.mode]

    def _set_mode(self, mode: str) -> None:
        if mode != self.mode:
            self.mode = mode
            self.modes_seen.append(mode)

    def _handle(self, msg, now: float) -> None:
        mt = msg.get_type()
        if mt == "SET_POSITION_TARGET_LOCAL_NED":
            self.setpoints.append((now, msg.vx, msg.vy, msg.vz, msg.type_mask, msg.coordinate_frame))
            self._sp, self._last_sp_t = (msg.vx, msg.vy, msg.vz), now
        elif mt == "COMMAND_LONG":
            p = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
            self.commands.append((msg.command, p))
            self.conn.mav.command_ack_send(msg.command, self._command(msg.command, p, now))

    def _command(self, cmd: int, p: tuple, now: float) -> int:
        if cmd == 176:  # DO_SET_MODE
            if self.personality == "px4":
                want = {v: k for k, v in PX4_MODES.items()}.get((int(p[1]), int(p[2])))
                if want == "offboard" and now - self._last_sp_t > 0.5:
                    return 1  # TEMPORARILY_REJECTED: no setpoint stream
            else:
                want = {v: k for k, v in AP_MODES.items()}.get(int(p[1]))
            if want is None:
                return 2
            self._set_mode(want)
            return 0
        if cmd == 400:  # ARM
            if self.drop_position:
                return 2
            self.armed = p[0] > 0.5
            return 0
        if cmd == 22:  # NAV_TAKEOFF (ArduPilot, GUIDED, armed)
            if self.personality != "ardupilot" or self.mode != "guided" or not self.armed:
                return 2
            self.takeoff_alt = p[6]
            return 0
        if cmd == 511:  # SET_MESSAGE_INTERVAL
            return 0
        return 3

    # ---- physics -------------------------------------------------------------------------------
    def _target(self, now: float) -> tuple[float, float, float]:
        if not self.armed:
            return (0.0, 0.0, 0.0)
        if self.mode == "land":
            return (0.0, 0.0, 1.5)
        if self.takeoff_alt is not None:
            if -self.pos[2] >= self.takeoff_alt - 0.05:
                self.takeoff_alt = None
            else:
                return (0.0, 0.0, -1.5)
        age = now - self._last_sp_t
        if self.mode == "offboard":
            if age > 0.5:  # COM_OF_LOSS_T -> hold
                self._set_mode("hold")
                return (0.0, 0.0, 0.0)
            return self._sp
        if self.mode == "guided":
            return self._sp if age < 3.0 else (0.0, 0.0, 0.0)  # GUID_TIMEOUT
        return (0.0, 0.0, 0.0)

    def _physics(self, now: float, dt: float) -> None:
        tgt = self._target(now)
        k = 1.0 - math.exp(-dt / self.tau_s)
        for i in range(3):
            self.vel[i] += (tgt[i] - self.vel[i]) * k
            self.pos[i] += self.vel[i] * dt
        if self.pos[2] >= 0.0:  # ground
            self.pos[2] = 0.0
            self.vel = [0.0 if not self.armed else self.vel[0], 0.0 if not self.armed else self.vel[1],
                        min(self.vel[2], 0.0)]
            if self.armed and self.mode == "land":
                self.armed = False

    def _loop(self) -> None:
        mav = self.conn.mav
        last = time.monotonic()
        next_hb = next_pos = last
        boot = last
        while not self._stop.is_set():
            now = time.monotonic()
            while True:
                msg = self.conn.recv_msg()
                if msg is None:
                    break
                if not self.mute:
                    self._handle(msg, now)
            self._physics(now, now - last)
            last = now
            if not self.mute:
                if now >= next_hb:
                    next_hb = now + 0.5
                    base = 1 | (128 if self.armed else 0)
                    ap = 12 if self.personality == "px4" else 3
                    mav.heartbeat_send(2, ap, base, self._custom_mode(), 4)
                if now >= next_pos and not self.drop_position:
                    next_pos = now + 0.02
                    ms = int((now - boot) * 1000)
                    mav.local_position_ned_send(ms, *self.pos, *self.vel)
                    lat, lon, alt = self.geo.ned_to_geodetic(*self.pos)
                    mav.global_position_int_send(ms, int(round(lat * 1e7)), int(round(lon * 1e7)),
                                                 int(round(alt * 1000)), int(round(-self.pos[2] * 1000)),
                                                 int(round(self.vel[0] * 100)), int(round(self.vel[1] * 100)),
                                                 int(round(self.vel[2] * 100)), 65535)
            time.sleep(0.005)
