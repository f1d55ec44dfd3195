"""Onboard agent benchmark (prints figures; not a test).

1. Per-iteration compute, position -> setpoint message encoded (MAVLink 2 bytes):
   - hot path: NED -> map, CV lookup, command, speed/accel clamp, map -> NED velocity,
     SET_POSITION_TARGET_LOCAL_NED encode + pack (scalar fast path, ``control.ScalarField``);
   - the same with the vectorised numpy ``lookup.CommandField`` for one agent (for comparison);
   - a whole ``Runner.step()`` (mission state machine, failsafes, snapshot) on an in-memory link.
2. Setpoint period jitter of ``Runner.run()`` at 20 Hz and 50 Hz (real clock, in-memory link):
   |actual period - nominal| p50 / p99 / max.

Targets: < 20 us per iteration; p99 jitter < 2 ms.

    python benchmarks/bench_agent.py [--seconds 5] [--map default|synthetic]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

os.environ.setdefault("MAVLINK20", "1")

from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from fisc_agent.adapters import Px4Adapter  # noqa: E402
from fisc_agent.config import AgentConfig  # noqa: E402
from fisc_agent.control import ScalarField, clamp_velocity  # noqa: E402
from fisc_agent.link import MAV_FRAME_LOCAL_NED, TYPEMASK_VELOCITY_ONLY, PositionSample  # noqa: E402
from fisc_agent.lookup import CommandField  # noqa: E402
from fisc_agent.mission import State  # noqa: E402
from fisc_agent.runner import Runner  # noqa: E402


def load_map(which: str):
    if which == "default":
        from fisc_ground.mapbuild import build_default_map

        return build_default_map()
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "fisc_agent"))
    from conftest import tunnel_map_bytes

    from fisc_agent.mapfile import decode_map

    return decode_map(tunnel_map_bytes(length_m=15.0, radius_m=1.5))


class BenchLink:
    """In-memory PX4 in OFFBOARD, armed, flying along the tunnel; encodes every setpoint."""

    def __init__(self, clock=time.monotonic, speed_m_s=2.0):
        self.clock = clock
        self.autopilot = "px4"
        self.armed = True
        self.base_mode, self.custom_mode = 1 | 128, Px4Adapter.px4_custom_mode(6)
        self.last_heartbeat_t = clock()
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
        self.sent_t: list[float] = []
        self.nbytes = 0
        self.t0 = clock()
        self.speed = speed_m_s

    def poll(self):
        self.last_heartbeat_t = self.clock()
        return 0

    def latest_position(self):
        now = self.clock()
        x = 0.3 + (self.speed * (now - self.t0)) % 14.0
        return PositionSample(now, (x, 0.2, -10.3), (self.speed, 0.0, 0.0))

    def send_velocity_ned(self, vn, ve, vd):
        msg = self.mav.set_position_target_local_ned_encode(
            int(self.clock() * 1000) & 0xFFFFFFFF, 1, 1, MAV_FRAME_LOCAL_NED, TYPEMASK_VELOCITY_ONLY,
            0.0, 0.0, 0.0, vn, ve, vd, 0.0, 0.0, 0.0, 0.0, 0.0)
        self.nbytes = len(msg.pack(self.mav))
        self.sent_t.append(self.clock())

    def send_command(self, cmd):
        pass

    def send_heartbeat(self):
        pass

    def pop_acks(self):
        return []

    def close(self):
        pass


def bench_hot_path(cmap, n=50000):
    cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=7, mode="slot")
    tf = cfg.transform
    sf = ScalarField(CommandField.from_map(cmap))
    cf = sf.field
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    rng = np.random.default_rng(0)
    centres = np.asarray(cf.centers_m)
    inside = centres[rng.integers(0, len(centres), 1000)] + rng.uniform(-0.2, 0.2, size=(1000, 3))
    pts = [tuple(tf.map_to_ned_xyz(*p)) for p in inside]
    results = {}
    for label, numpy_path in (("scalar fast path", False), ("numpy CommandField (1 agent)", True)):
        prev = (0.0, 0.0, 0.0)
        t = time.perf_counter()
        for i in range(n):
            n_, e_, d_ = pts[i % 1000]
            x, y, z = tf.ned_to_map_xyz(n_, e_, d_)
            if numpy_path:
                v = tuple(cf.command(np.array([[x, y, z]]), np.array([7]), "slot")[0].tolist())
            else:
                v = sf.command(x, y, z, 7, "slot")
            v = clamp_velocity(v, prev, 0.05, cfg.max_speed_m_s, cfg.max_accel_m_s2)
            prev = v
            vn, ve, vd = tf.vel_map_to_ned_xyz(*v)
            mav.set_position_target_local_ned_encode(i, 1, 1, 1, TYPEMASK_VELOCITY_ONLY, 0.0, 0.0, 0.0, vn, ve, vd,
                                                     0.0, 0.0, 0.0, 0.0, 0.0).pack(mav)
        results[label] = (time.perf_counter() - t) / n * 1e6
    return results


def bench_runner_step(cmap, n=20000):
    class Clock:
        t = 1000.0

        def __call__(self):
            return self.t

    clock = Clock()
    cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=7, mode="slot")
    link = BenchLink(clock)
    r = Runner(cfg, link, cmap, clock=clock)
    r.mission.state = State.FLOW  # measure the steady FLOW tick
    t = time.perf_counter()
    for _ in range(n):
        clock.t += 0.05
        r.step()
    return (time.perf_counter() - t) / n * 1e6, link.nbytes, r.mission.state


def bench_jitter(cmap, rate_hz, seconds):
    cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=7, rate_hz=rate_hz)
    link = BenchLink()
    r = Runner(cfg, link, cmap)
    r.mission.state = State.FLOW
    r.run(until_done=False, max_duration_s=seconds)
    sent = np.asarray(link.sent_t)
    dev_ms = np.abs(np.diff(sent) - 1.0 / rate_hz) * 1e3
    late_ms = (sent - (sent[0] + np.arange(len(sent)) / rate_hz)) * 1e3  # vs the deadline schedule
    late_ms -= late_ms.min()
    return (len(sent), np.percentile(dev_ms, 50), np.percentile(dev_ms, 99), dev_ms.max(), r.overruns,
            np.percentile(late_ms, 50), np.percentile(late_ms, 99))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="duration of each jitter run")
    ap.add_argument("--map", choices=("default", "synthetic"), default="default")
    ap.add_argument("--realtime", action="store_true", help="run the jitter loops with SCHED_FIFO (needs privileges)")
    a = ap.parse_args()
    cmap = load_map(a.map)
    print(f"map: {a.map}, {cmap.n_cv} CVs")
    for label, us in bench_hot_path(cmap).items():
        print(f"per-iteration (position -> encoded setpoint), {label:30s}: {us:6.2f} us")
    us, nbytes, state = bench_runner_step(cmap)
    print(f"per-iteration, whole Runner.step() in {state.value} (mission, failsafes, snapshot): {us:6.2f} us "
          f"({nbytes}-byte MAVLink 2 message)")
    if a.realtime:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
            print("running the jitter loops with SCHED_FIFO priority 10")
        except (AttributeError, PermissionError, OSError) as exc:
            print(f"SCHED_FIFO not available ({exc}); normal scheduling")
    with open("/proc/loadavg") if os.path.exists("/proc/loadavg") else open(os.devnull) as fh:
        print(f"load average: {fh.read().strip() or 'n/a'}")
    for rate in (20.0, 50.0):
        n, p50, p99, mx, over, l50, l99 = bench_jitter(cmap, rate, a.seconds)
        print(f"setpoint period jitter at {rate:4.0f} Hz over {n} setpoints: p50 {p50:.3f} ms, p99 {p99:.3f} ms, "
              f"max {mx:.3f} ms, overruns {over}; lateness vs deadline p50 {l50:.3f} ms, p99 {l99:.3f} ms")
    print(f"python {sys.version.split()[0]}, {os.cpu_count()} CPUs")


if __name__ == "__main__":
    main()
