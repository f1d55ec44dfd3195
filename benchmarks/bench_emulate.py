"""How many agent + autopilot-emulator pairs keep real time on this machine, and CPU per agent.

Each size N flies ``sim.emulate.fly_swarm`` (N AutopilotEmulators + N fisc-agent Runners, real
MAVLink 2 over loopback UDP, Case 2 launch plan on the default map) for ``--duration`` seconds
and judges the fully loaded part of the run (every vehicle launched and streaming, see
``sim.emulate.steady_start_s``) with ``sim.emulate.realtime_summary``: real time is kept when
the setpoint rate measured at the autopilots is within 5 % of the nominal 20 Hz, every agent
loop ran >= 95 % of its ticks, and every loop (agents and emulators) kept its p99 tick lag below
one control period (50 ms) and its p99 gap between ticks below two.

The search goes up through ``--sizes`` until a size fails, then bisects between the last pass
and the first failure (``--bisect`` steps).  Prints one line per size (with how many agents reached FLOW:
the agents must fly the map, not wait on the ground) and a summary.

    python benchmarks/bench_emulate.py                       # default settings of fisc-sim emulate
    python benchmarks/bench_emulate.py --telemetry lean --physics-rate 20 --physics-dt 0.05
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from fisc_agent.flight.frames import DeploymentTransform
from fisc_agent.map.lookup import CommandField
from sim.emulate import (EmulateConfig, entry_statistics, fly_swarm, launch_plan, prepare_map, realtime_summary,
                         steady_start_s)


PROJECTION_BUSY = 0.7
"""CPU share a real-time loop can use and still absorb scheduling jitter (for the projection)."""


def measure(n: int, args, map_path: Path, field: CommandField) -> dict:
    cfg = EmulateConfig(out_dir=args.tmp, agents=n, duration_s=args.duration, telemetry=args.telemetry,
                        physics_rate_hz=args.physics_rate, physics_dt_s=args.physics_dt,
                        emulator_workers=args.emulator_workers,
                        agent_workers=args.agent_workers, compare=False, figures=False)
    plan = launch_plan(field, n, DeploymentTransform(), duration_s=cfg.duration_s)
    swarm = fly_swarm(map_path, plan, cfg)
    t_from = steady_start_s(plan, cfg.duration_s)
    rt = realtime_summary(swarm, cfg.rate_hz, n, t_from)
    rt["workers"] = cfg.workers()
    # the agents must really fly: an agent stuck before FLOW costs less than one flying the map
    rt["reached_flow"] = entry_statistics(swarm.agents, plan)["vehicles_entered"]
    return rt


def line(n: int, rt: dict) -> str:
    a = rt["agent_loops"]
    e = rt["emulator_loops"]
    return (f"{n:5d} pairs  procs {rt['workers'][0]}+{rt['workers'][1]}  "
            f"{'REAL TIME' if rt['keeps_real_time'] else 'too slow '}  "
            f"setpoints {rt['setpoint_rate_mean_hz']:5.1f} Hz (p5 {rt['setpoint_rate_p5_hz'] or float('nan'):4.1f})  "
            f"agent ticks {min(x['tick_rate_ratio'] for x in a):.3f} lag/gap p99 "
            f"{1e3 * max(x['lag_p99_s'] for x in a):4.0f}/{1e3 * max(x['gap_p99_s'] for x in a):4.0f} ms  "
            f"emulator ticks {min(x['tick_rate_ratio'] for x in e):.3f} lag/gap p99 "
            f"{1e3 * max(x['lag_p99_s'] for x in e):4.0f}/{1e3 * max(x['gap_p99_s'] for x in e):4.0f} ms  "
            f"CPU {rt['cpu_cores_used']:.2f} cores (agents {sum(x['cpu_cores'] for x in a):.2f}, emulators "
            f"{sum(x['cpu_cores'] for x in e):.2f}) = {1e3 * rt['cpu_per_agent']:.2f} ms per vehicle-second  "
            f"(window {rt['window_s'][0]:.0f}-{rt['window_s'][1]:.0f} s, setup {rt['setup_s']:.1f} s)  "
            f"reached FLOW {rt['reached_flow']}/{n}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default="50,100,200,300,400,500,600", help="pairs to try, ascending")
    p.add_argument("--duration", type=float, default=30.0, help="real seconds per size")
    p.add_argument("--bisect", type=int, default=1, help="bisection steps after the first failure")
    p.add_argument("--telemetry", choices=("full", "lean"), default="full")
    p.add_argument("--physics-rate", type=float, default=50.0, help="emulator service rate [Hz]")
    p.add_argument("--physics-dt", type=float, default=0.02, help="vehicle physics step [s]")
    p.add_argument("--emulator-workers", type=int, default=0, help="emulator processes (0: automatic)")
    p.add_argument("--agent-workers", type=int, default=0, help="agent processes (0: automatic)")
    args = p.parse_args()
    print(f"bench_emulate: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} before start (other "
          f"processes' load lowers what is measured); telemetry {args.telemetry}, emulators served at "
          f"{args.physics_rate:.0f} Hz, physics step {args.physics_dt} s, {args.duration:.0f} s per size", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        args.tmp = tmp
        map_path, cmap = prepare_map(None, Path(tmp))
        field = CommandField.from_map(cmap)
        best, best_rt, fail = 0, None, None
        measured: dict[int, dict] = {}
        for n in [int(s) for s in args.sizes.split(",")]:
            t = time.monotonic()
            rt = measured[n] = measure(n, args, map_path, field)
            print(line(n, rt) + f"  [{time.monotonic() - t:.0f} s]", flush=True)
            if not rt["keeps_real_time"]:
                fail = n
                break
            best, best_rt = n, rt
        for _ in range(args.bisect if fail is not None and best else 0):
            n = (best + fail) // 2
            if n in (best, fail):
                break
            rt = measured[n] = measure(n, args, map_path, field)
            print(line(n, rt), flush=True)
            if rt["keeps_real_time"]:
                best, best_rt = n, rt
            else:
                fail = n
    if best_rt is None:
        print("no size kept real time")
    else:
        print(f"largest number of agent + emulator pairs keeping real time: {best}"
              + (f" (fails at {fail})" if fail is not None else " (largest size tried)"))
        print(f"CPU per agent at {best} pairs: {1e3 * best_rt['cpu_per_agent']:.2f} ms per vehicle-second "
              f"({best_rt['cpu_cores_used']:.2f} cores for agents + emulators)")
    ncpu = os.cpu_count() or 1
    n_big, rt_big = max(measured.items())
    print(f"projection for an idle machine at {PROJECTION_BUSY:.0%} CPU, from the CPU per agent at the largest size "
          f"measured ({n_big} pairs: {1e3 * rt_big['cpu_per_agent']:.2f} ms per vehicle-second): "
          f"{int(PROJECTION_BUSY * ncpu / rt_big['cpu_per_agent'])} pairs")


if __name__ == "__main__":
    main()
