"""Throughput of the vectorised VelocityPlant: agent-(sub)steps per second on one core.

Usage: python benchmarks/bench_plant.py [--agents 100000] [--repeat 50]

Each timed call is ONE semi-implicit Euler sub-step (dt = max_substep_s) of every agent, in place
(``out=`` aliasing the state), with random commands and winds that keep the actuation limits
active for part of the fleet.  With numba, ``wind False`` is the swarm simulator's case (the one
kernel's specialisation without wind, fleet-wide coefficients read as scalars) and ``wind True``
its specialisation with per-agent wind; ``--dt`` times whole swarm steps instead (dt 0.05 s = 5
sub-steps).  Target: >= 3e7 agent-steps/s at 1e5 agents for a whole
swarm step (``fisc-sim bench``), of which the plant is the largest part.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from sim.plant.model import PlantParams, numba_available, step_plant, trim_thrust_accel


def bench(n_agents: int, backend: str, wind: bool, repeat: int, dt: float | None = None) -> float:
    p = PlantParams()
    rng = np.random.default_rng(0)
    vel = rng.normal(0.0, 5.0, (n_agents, 3))
    thr = trim_thrust_accel(vel, p)
    cmd = rng.normal(0.0, 8.0, (n_agents, 3))
    w = rng.normal(0.0, 2.0, (n_agents, 3)) if wind else None
    co = p.coefficients(n_agents)
    dt = p.max_substep_s if dt is None else dt
    step_plant(vel, thr, cmd, dt, co, w, out=(vel, thr), backend=backend)  # warm-up / JIT
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(repeat):
            step_plant(vel, thr, cmd, dt, co, w, out=(vel, thr), backend=backend)
        best = min(best, (time.perf_counter() - t0) / repeat)
    return n_agents / best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--agents", type=int, nargs="+", default=[1_000, 10_000, 100_000])
    ap.add_argument("--repeat", type=int, default=50)
    ap.add_argument("--dt", type=float, default=None, help="step length [s] (default: one sub-step)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    have_numba = numba_available()
    print(f"numba available: {have_numba} (import/compile {time.perf_counter() - t0:.2f} s)")
    backends = ["numpy"] + (["numba"] if have_numba else [])
    print(f"step {args.dt if args.dt else PlantParams().max_substep_s} s")
    print(f"{'agents':>8} {'backend':>7} {'wind':>5} {'agent-steps/s':>14} {'us/step':>9}")
    for n in args.agents:
        for be in backends:
            for wind in (False, True):
                rate = bench(n, be, wind, args.repeat, args.dt)
                print(f"{n:>8} {be:>7} {str(wind):>5} {rate:>14.3g} {n / rate * 1e6:>9.1f}")


if __name__ == "__main__":
    main()
