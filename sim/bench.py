"""``fisc-sim bench``: speed of the swarm core (agent-steps/s, peak memory, the bytes it moves
against the machine's memory bandwidth: ``sim.memory_traffic``), the wall time of the
paper's run (flown with the paper's preset and with the default), and the same agent-steps/s figure
for RotorPy's batched multirotor simulator.

Figures are printed, never asserted (speed is machine-dependent).
"""

from __future__ import annotations

import time
import tracemalloc
from collections.abc import Iterator

import numpy as np

from fisc_agent.map.lookup import CommandField
from sim.plant.model import PlantParams
from sim.memory_traffic import bandwidth_lines, copy_bandwidth_gb_s, last_level_cache_bytes
from sim.scenarios import seed_positions
from sim.swarm import Swarm, SwarmConfig


def bench_core(cf: CommandField, n_agents: int, steps: int = 20, mode: str = "mean",
               seed: int = 0) -> dict:
    """Seed ``n_agents`` uniformly over the CVs (Case 1 proportions) and time ``steps`` steps.

    Returns agent_steps_per_s (over all timed steps), best_agent_steps_per_s (the fastest
    single step: less sensitive to other processes on a shared machine), per-step time, and the
    peak traced memory of stepping (numpy allocations, tracemalloc, measured over extra steps
    after the timing, since tracing slows allocations) beside the state size.
    """
    rng = np.random.default_rng(seed)
    swarm = Swarm(cf, PlantParams(), SwarmConfig(mode=mode))
    swarm.add_agents(seed_positions(cf, rng, n_agents=n_agents))
    swarm.step()  # warm-up (numba compile, buffers)
    a0 = swarm.counters.agent_steps
    best = 0.0
    t0 = time.perf_counter()
    for _ in range(steps):
        alive, t1 = swarm.n, time.perf_counter()
        swarm.step()
        best = max(best, alive / (time.perf_counter() - t1))
    wall = time.perf_counter() - t0
    agent_steps = swarm.counters.agent_steps - a0
    tracemalloc.start()
    for _ in range(2):
        swarm.step()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    state_bytes = sum(b.nbytes for b in (swarm._pos, swarm._vel, swarm._thr, swarm._ids, swarm._out,
                                          swarm._cmd, swarm._scratch))
    return {"agents": n_agents, "steps": steps, "wall_s": wall, "agent_steps_per_s": agent_steps / wall,
            "best_agent_steps_per_s": best, "step_ms": 1e3 * wall / steps, "peak_step_mib": peak / 2**20,
            "state_mib": state_bytes / 2**20}


def bench_paper_run(cmap, preset: str = "default", agents: int = 1000, duration_s: float = 300.0) -> dict:
    """Wall time of the paper's run (Case 2 on ``cmap``, ~``agents`` agents, ``duration_s`` simulated)
    flown with ``preset``: ``paper`` (Algorithm 1, mean commands; give it the schema-1 map) or
    ``default`` (the map's recommended flight, kinetic on a schema-2 map).  The simulation loop
    only: no map fit, no figures, no paper companion."""
    from sim.run import RunConfig, simulate

    res = simulate(RunConfig(agents=agents, duration_s=duration_s, figures=False, preset=preset), cmap)
    return {"wall_s": res.wall_time_s, "mode": res.settings.mode, "lookahead_s": res.settings.lookahead_s,
            "steps": res.counters.steps, "agent_steps": res.counters.agent_steps,
            "mean_alive": res.counters.agent_steps / max(res.counters.steps, 1), "alive_end": res.alive}


def bench_rotorpy(n_agents: int, steps: int = 5, dt_s: float = 0.05) -> dict:
    """agent-steps/s of RotorPy's BatchedMultirotor (hummingbird parameters, the ``cmd_vel``
    abstraction — the same level as our velocity plant — and its fixed-step ``rk4``
    integrator, CPU) for ``n_agents`` hovering vehicles commanded 1 m/s forward, stepping at
    ``dt_s``.  Raises ImportError (no torch/roma/rotorpy) or RuntimeError when unavailable."""
    import torch  # rotorpy's batched simulator needs PyTorch
    from rotorpy.vehicles.hummingbird_params import quad_params
    from rotorpy.vehicles.multirotor import BatchedMultirotor, BatchedMultirotorParams

    torch.set_num_threads(1)  # one core, like the FISC core
    dev = torch.device("cpu")
    params = BatchedMultirotorParams([quad_params] * n_agents, n_agents, dev)
    x0 = {"x": torch.zeros(n_agents, 3, dtype=torch.double), "v": torch.zeros(n_agents, 3, dtype=torch.double),
          "q": torch.tensor([0, 0, 0, 1], dtype=torch.double).repeat(n_agents, 1),
          "w": torch.zeros(n_agents, 3, dtype=torch.double), "wind": torch.zeros(n_agents, 3, dtype=torch.double),
          "rotor_speeds": torch.full((n_agents, 4), 1788.53, dtype=torch.double)}
    vehicle = BatchedMultirotor(params, n_agents, x0, dev, control_abstraction="cmd_vel", integrator="rk4")
    state = {k: v.clone() for k, v in x0.items()}
    cmd_v = torch.zeros(n_agents, 3, dtype=torch.double)
    cmd_v[:, 0] = 1.0
    control = {"cmd_v": cmd_v}
    state = vehicle.step(state, control, dt_s)
    t0 = time.perf_counter()
    for _ in range(steps):
        state = vehicle.step(state, control, dt_s)
    wall = time.perf_counter() - t0
    return {"agents": n_agents, "agent_steps_per_s": n_agents * steps / wall}


def run_bench(sizes: list[int], steps: int = 20, rotorpy: bool = True, paper_run: bool = True,
              map_spec: str | None = None) -> Iterator[str]:
    """The bench as printable lines (generator, so results appear as they come)."""
    from sim.run import load_command_map

    cmap = load_command_map(map_spec)
    cf = CommandField.from_map(cmap)
    name = cmap.body.get("provenance", {}).get("reference", {}).get("name")
    yield f"map: {name} ({cmap.n_cv} CVs), mode mean, dt 0.05 s"
    ours, state_bytes = {}, {}
    for n in sizes:
        k = max(2, min(steps, int(2e6 // max(n, 1)) or 2))
        r = bench_core(cf, n, k)
        ours[n] = r["agent_steps_per_s"]
        state_bytes[n] = int(r["state_mib"] * 2**20)
        yield (f"swarm core {n:>8d} agents: {r['agent_steps_per_s']:.3g} agent-steps/s "
               f"({r['step_ms']:.2f} ms/step over {k} steps; best step {r['best_agent_steps_per_s']:.3g}), "
               f"peak step memory {r['peak_step_mib']:.1f} MiB, state {r['state_mib']:.1f} MiB")
    if sizes:
        yield from bandwidth_lines(ours, state_bytes, copy_bandwidth_gb_s(), last_level_cache_bytes())
    if paper_run:
        for preset, run_map in (("paper", load_command_map(map_spec, preset="paper")), ("default", cmap)):
            r = bench_paper_run(run_map, preset)
            yield (f"paper run, --preset {preset} (schema-{run_map.schema_version} map; Case 2, --agents 1000, "
                   f"300 s = {r['steps']} steps, "
                   f"mean {r['mean_alive']:.0f} agents alive; mode {r['mode']}, look-ahead {r['lookahead_s']:g} s): "
                   f"{r['wall_s']:.2f} s wall")
    if rotorpy:
        n = min(sizes, key=lambda s: abs(s - 1000)) if sizes else 1000
        try:
            r = bench_rotorpy(n)
        except Exception as exc:  # noqa: BLE001 - report why the comparison is skipped
            yield f"RotorPy BatchedMultirotor: skipped ({type(exc).__name__}: {exc})"
        else:
            ratio = ours.get(n, float("nan")) / r["agent_steps_per_s"]
            yield (f"RotorPy BatchedMultirotor {n} vehicles: {r['agent_steps_per_s']:.3g} agent-steps/s; "
                   f"FISC core / RotorPy = {ratio:.1f}x")
