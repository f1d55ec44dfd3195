"""Onboard agent benchmark (prints figures; not a test).

1. Per-iteration compute, position -> setpoint message encoded (MAVLink 2 bytes):
   - hot path: NED -> map, CV lookup, command, speed/accel clamp, map -> NED velocity,
     SET_POSITION_TARGET_LOCAL_NED packed as the agent packs it (``setpoint_codec``; scalar fast path,
     ``control.ScalarField``);
   - the same with the vectorised numpy ``lookup.CommandField`` for one agent (for comparison);
   - a whole ``Runner.step()`` (mission state machine, failsafes, snapshot) on an in-memory link.
2. Setpoint period jitter of ``Runner.run()`` at 20 Hz and 50 Hz (real clock, in-memory link):
   |actual period - nominal| p50 / p99 / max.
3. CPU per agent: K real agents (one process each: ``MavlinkLink`` over UDP 127.0.0.1 + ``Runner``
   at 20 Hz, 50 Hz position stream) against K emulated autopilots (``sim.autopilot.server``,
   PX4 personality, all in one separate process), airborne at the inlet so they take over and
   fly the map (``--exit-policy loop``).  After a warm-up, each agent measures its own process
   CPU time (``time.process_time``: user + system, all threads) over the window:
   CPU seconds per agent per second = % of one core.

Targets: < 20 us per iteration; p99 jitter < 2 ms; CPU per agent a few % of one core.

    python benchmarks/bench_agent.py [--seconds 5] [--map default|synthetic]
                                     [--agents 4] [--cpu-seconds 5] [--cpu-rate 20]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import time

import numpy as np

os.environ.setdefault("MAVLINK20", "1")

from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from fisc_agent.mavlink.adapters import ModeClass  # noqa: E402
from fisc_agent.config import AgentConfig  # noqa: E402
from fisc_agent.flight.control import ScalarField, clamp_velocity  # noqa: E402
from fisc_agent.flight.health import VehicleHealth  # noqa: E402
from fisc_agent.flight.integrity import IntegrityVerdict  # noqa: E402
from fisc_agent.mavlink.link import MAV_FRAME_LOCAL_NED, TYPEMASK_VELOCITY_ONLY, PositionSample  # noqa: E402
from fisc_agent.mavlink.setpoint_codec import pack_velocity_setpoint  # noqa: E402
from fisc_agent.map.lookup import CommandField  # noqa: E402
from fisc_agent.flight.mission import State  # noqa: E402
from fisc_agent.flight.mission_types import Authority, FleetOrder, MissionCommand  # noqa: E402
from fisc_agent.runner import Runner  # noqa: E402


def load_map(which: str):
    if which == "default":
        from fisc_ground.maps.build import build_default_map

        return build_default_map()
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "fisc_agent"))
    from conftest import tunnel_map_bytes

    from fisc_agent.map.codec import decode_map

    return decode_map(tunnel_map_bytes(length_m=15.0, radius_m=1.5))


class BenchLink:
    """In-memory PX4 in OFFBOARD, armed, flying along the tunnel; encodes every setpoint."""

    def __init__(self, clock=time.monotonic, speed_m_s=2.0):
        self.clock = clock
        self.autopilot = "px4"
        self.armed = True
        self.mode = ModeClass.OFFBOARD
        self.last_heartbeat_t = clock()
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
        self.sent_t: list[float] = []
        self.nbytes = 0
        self.t0 = clock()
        self.speed = speed_m_s
        self.health = VehicleHealth()          # settable
        self.integrity = IntegrityVerdict()    # settable

    def poll(self):
        self.last_heartbeat_t = self.clock()
        return 0

    @property
    def mode_t_s(self):
        return self.last_heartbeat_t

    def latest_gnss_velocity(self):
        return None

    def latest_thrust_accel(self):
        return None

    def latest_position(self):
        """Back and forth along 14 m of the tunnel (a continuous track: a wrap-around would be a jump the
        agent's position gate refuses, and the agent would hold instead of flying)."""
        now = self.clock()
        s = (self.speed * (now - self.t0)) % 28.0
        out = s < 14.0
        x = 0.3 + (s if out else 28.0 - s)
        return PositionSample(now, (x, 0.2, -10.3), (self.speed if out else -self.speed, 0.0, 0.0))

    def send_velocity_ned(self, vn, ve, vd):
        # packed as MavlinkLink.send_velocity_ned packs it (fisc_agent.mavlink.setpoint_codec)
        self.nbytes = len(pack_velocity_setpoint(self.mav, int(self.clock() * 1000) & 0xFFFFFFFF, 1, 1,
                                                 MAV_FRAME_LOCAL_NED, TYPEMASK_VELOCITY_ONLY, vn, ve, vd))
        self.sent_t.append(self.clock())

    def send_velocity_accel_ned(self, vn, ve, vd, an, ae, ad):
        self.send_velocity_ned(vn, ve, vd)  # BenchLink reports no attitude: never called

    def use_adapter(self, adapter):
        pass

    def arm(self):
        pass

    def set_mode(self, mode):
        pass

    def takeoff(self, alt_m):
        pass

    def hold(self):
        pass

    def land(self):
        pass

    def send_heartbeat(self):
        pass

    def pop_results(self):
        return []

    def discard_backlog(self):
        return 0

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
            pack_velocity_setpoint(mav, i, 1, 1, 1, TYPEMASK_VELOCITY_ONLY, vn, ve, vd)
        results[label] = (time.perf_counter() - t) / n * 1e6
    return results


def given_the_vehicle(r: Runner, tick) -> None:
    """Hand the flying vehicle to the agent as the ground does (an addressed takeover: the agent flies
    only a vehicle it was given), ticking with ``tick`` until it flows under its command."""
    for _ in range(3):
        tick()
    r.mission.command(FleetOrder(MissionCommand.TAKEOVER, addressed=True))
    for _ in range(3):
        tick()
    if r.mission.authority != Authority.COMMAND or r.mission.state != State.FLOW:
        raise RuntimeError(f"the agent did not take the vehicle over: {r.mission.state}, {r.mission.authority}")


class ManualClock:
    """A clock the caller advances (``clock.t += dt``): the runner's time without waiting."""

    def __init__(self, t_s: float = 1000.0) -> None:
        self.t = t_s

    def __call__(self) -> float:
        return self.t


def bench_runner_step(cmap, n=20000):
    clock = ManualClock()
    cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=7, mode="slot")
    link = BenchLink(clock)
    r = Runner(cfg, link, cmap, clock=clock)

    def tick():
        clock.t += 0.05
        r.step()

    given_the_vehicle(r, tick)  # measure the steady FLOW tick
    t = time.perf_counter()
    for _ in range(n):
        clock.t += 0.05
        r.step()
    return (time.perf_counter() - t) / n * 1e6, link.nbytes, r.mission.state


def bench_jitter(cmap, rate_hz, seconds):
    cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=7, rate_hz=rate_hz)
    link = BenchLink()
    r = Runner(cfg, link, cmap)
    given_the_vehicle(r, lambda: (r.step(), time.sleep(1.0 / rate_hz)))
    link.sent_t.clear()
    r.run(until_done=False, max_duration_s=seconds)
    sent = np.asarray(link.sent_t)
    dev_ms = np.abs(np.diff(sent) - 1.0 / rate_hz) * 1e3
    late_ms = (sent - (sent[0] + np.arange(len(sent)) / rate_hz)) * 1e3  # vs the deadline schedule
    late_ms -= late_ms.min()
    return (len(sent), np.percentile(dev_ms, 50), np.percentile(dev_ms, 99), dev_ms.max(), r.overruns,
            np.percentile(late_ms, 50), np.percentile(late_ms, 99))


def _emulators_worker(conn, n: int, start_ned: list[tuple[float, float, float]]) -> None:
    """Child process: K emulated PX4 autopilots on free UDP ports until told to stop."""
    from sim.autopilot.server import AutopilotEmulator

    emus = [AutopilotEmulator("udpin:127.0.0.1:0", personality="px4", start_ned=start_ned[i], sysid=i + 1).start()
            for i in range(n)]
    try:
        conn.send([e.local_address[1] for e in emus])
        c0, w0 = time.process_time(), time.monotonic()
        conn.recv()  # stop
        conn.send((time.process_time() - c0) / (time.monotonic() - w0))
    finally:
        for e in emus:
            e.stop()


def _agent_worker(conn, port: int, agent_id: int, map_choice: str, rate_hz: float, warmup_s: float,
                  seconds: float) -> None:
    """Child process: one agent (MavlinkLink + Runner); reports its CPU over the window."""
    import logging

    from fisc_agent.mavlink.link import MavlinkLink

    logging.getLogger("fisc_agent").setLevel(logging.ERROR)  # the shutdown's "hold not confirmed" is expected
    cmap = load_map(map_choice)
    cfg = AgentConfig(mavlink_url=f"udpout:127.0.0.1:{port}", agent_id=agent_id, rate_hz=rate_hz, go=True,
                      exit_policy="loop")
    link = MavlinkLink(cfg.mavlink_url, position_rate_hz=max(50.0, rate_hz))
    r = Runner(cfg, link, cmap)
    received = [0]
    poll = link.poll

    def counting_poll() -> int:
        n = poll()
        received[0] += n
        return n

    link.poll = counting_poll
    try:
        r.run(until_done=False, max_duration_s=1.0)  # finds the autopilot and a position
        r.mission.command(FleetOrder(MissionCommand.TAKEOVER, addressed=True))  # airborne: the ground hands it over
        r.run(until_done=False, max_duration_s=warmup_s)
        ticks0, sent0, recv0 = r.ticks, link.setpoints_sent, received[0]
        c0, w0 = time.process_time(), time.monotonic()
        r.run(until_done=False, max_duration_s=seconds)
        cpu, wall = time.process_time() - c0, time.monotonic() - w0
        states = sorted({t.dst.value for t in r.mission.transitions})
        conn.send((cpu, wall, r.ticks - ticks0, link.setpoints_sent - sent0, received[0] - recv0,
                   r.mission.state.value, states, r.overruns))
    finally:
        r.shutdown(settle_s=0.0)


def bench_cpu_per_agent(map_choice: str, n_agents: int, rate_hz: float, seconds: float, warmup_s: float = 3.0):
    """CPU time per agent per second (one process per agent, emulated autopilots over UDP)."""
    ctx = mp.get_context("spawn")
    starts = [(0.5, -0.4 + 0.8 * i / max(1, n_agents - 1), -10.0) for i in range(n_agents)]  # inlet, axis height
    emu_conn, child = ctx.Pipe()
    emu_proc = ctx.Process(target=_emulators_worker, args=(child, n_agents, starts), daemon=True)
    emu_proc.start()
    ports = emu_conn.recv()
    conns, procs = [], []
    for i, port in enumerate(ports):
        a, b = ctx.Pipe()
        p = ctx.Process(target=_agent_worker, args=(b, port, i + 1, map_choice, rate_hz, warmup_s, seconds),
                        daemon=True)
        p.start()
        conns.append(a)
        procs.append(p)
    results = [c.recv() for c in conns]
    for p in procs:
        p.join(timeout=10)
    emu_conn.send("stop")
    emu_cpu = emu_conn.recv()
    emu_proc.join(timeout=10)
    return results, emu_cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="duration of each jitter run")
    ap.add_argument("--map", choices=("default", "synthetic"), default="default")
    ap.add_argument("--realtime", action="store_true", help="run the jitter loops with SCHED_FIFO (needs privileges)")
    ap.add_argument("--agents", type=int, default=4, help="agents (processes) for the CPU-per-agent run")
    ap.add_argument("--cpu-seconds", type=float, default=5.0, help="measured window of the CPU-per-agent run")
    ap.add_argument("--cpu-rate", type=float, default=20.0, help="setpoint rate of the CPU-per-agent run [Hz]")
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
    results, emu_cpu = bench_cpu_per_agent(a.map, a.agents, a.cpu_rate, a.cpu_seconds)
    per_agent = np.array([cpu / wall for cpu, wall, *_ in results])
    for i, (cpu, wall, ticks, sent, recv, state, states, over) in enumerate(results, 1):
        print(f"agent {i}: {cpu * 1e3:7.1f} ms CPU in {wall:.2f} s ({cpu / wall * 100:5.2f} % of a core), "
              f"{ticks / wall:5.1f} ticks/s, {sent / wall:5.1f} setpoints/s, {recv / wall:5.1f} MAVLink msgs/s in, "
              f"overruns {over}, now {state} "
              f"(visited {', '.join(states)})")
    print(f"CPU per agent at {a.cpu_rate:.0f} Hz ({a.agents} agent processes vs emulated PX4 over UDP, "
          f"{a.cpu_seconds:.0f} s): mean {per_agent.mean() * 1e3:.1f} ms/s ({per_agent.mean() * 100:.2f} % of one "
          f"core), max {per_agent.max() * 100:.2f} %; the {a.agents} emulators together used "
          f"{emu_cpu * 100:.1f} % of a core")
    print(f"python {sys.version.split()[0]}, {os.cpu_count()} CPUs")


if __name__ == "__main__":
    main()
