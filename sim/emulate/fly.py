"""Flying the emulated swarm: start the worker processes, give the go, collect ``SwarmRun``."""

from __future__ import annotations

import logging
import multiprocessing as mp
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from fisc_agent.map.lookup import map_flight_settings
from fisc_agent.map.codec import load_map
from sim.autopilot.estimate_error import PX4_SIH_ESTIMATE_ERROR
from sim.emulate.config import STARTUP_TIMEOUT_S, EmulateConfig
from sim.emulate.plan import LaunchPlan
from sim.emulate.workers import _AgentJob, _EmulatorJob, _agent_worker, _emulator_worker

log = logging.getLogger(__name__)


def _split(n: int, parts: int) -> list[np.ndarray]:
    return [a for a in np.array_split(np.arange(n), parts) if a.size]


def _recv(conn, what: str, timeout_s: float) -> Any:
    if not conn.poll(timeout_s):
        raise RuntimeError(f"emulate: {what} worker did not answer within {timeout_s:.0f} s")
    try:
        kind, payload = conn.recv()
    except EOFError:
        raise RuntimeError(f"emulate: {what} worker exited without a result (crashed or killed)") from None
    if kind == "error":
        raise RuntimeError(f"emulate: {what} worker failed:\n{payload}")
    return payload


@dataclass
class SwarmRun:
    """Raw outcome of flying the emulated swarm (before any field estimation)."""

    agent_ids: np.ndarray
    """(N,) ids, the column order of the sample arrays."""
    sample_t_s: np.ndarray
    """(K,) sample times since launch [s] (first emulator process's clock)."""
    pos_ned_m: np.ndarray
    """(K, N, 3) positions as the autopilots report them (the truth unless ``EmulateConfig.estimate_error``),
    local NED [m]."""
    vel_ned_m_s: np.ndarray
    """(K, N, 3) velocities as the autopilots report them, NED [m/s]."""
    agents: list[dict]
    """Per-agent mission outcome (state, laps, transitions with times since launch)."""
    emulator_timing: list[dict]
    """Raw loop log of each emulator process (``_LoopLog.export``; see ``loop_stats``)."""
    agent_timing: list[dict]
    """Raw loop log of each agent process."""
    setpoint_rate_hz: np.ndarray
    """Setpoint rates measured at the autopilots, per vehicle flying in OFFBOARD/GUIDED, per second [Hz]."""
    setpoint_rate_t_s: np.ndarray
    """Time of each ``setpoint_rate_hz`` entry since launch [s]."""
    duration_s: float
    """Flight time [s]."""
    setup_s: float
    """Wall time of starting the workers (processes, sockets, map decoding) [s]."""
    messages: dict
    """MAVLink message counters summed over the emulators (rx, tx)."""


def fly_swarm(map_path: Path, plan: LaunchPlan, config: EmulateConfig,
              progress: Callable[[float], None] | None = None) -> SwarmRun:
    """Start the emulator and agent processes, fly ``config.duration_s`` of real time, collect."""
    n = plan.start_ned_m.shape[0]
    n_emu, n_agent = config.workers()
    settings = config.agent_settings(map_flight_settings(load_map(map_path)).mode)
    ctx = mp.get_context("spawn")
    t_setup = time.monotonic()
    procs: list = []
    emu_conns, agent_conns = [], []
    try:
        emu_parts = _split(n, n_emu)
        for part in emu_parts:
            parent, child = ctx.Pipe()
            job = _EmulatorJob(tuple(int(i) for i in part), tuple(tuple(map(float, p)) for p in plan.start_ned_m[part]),
                               tuple(float(t) for t in plan.start_time_s[part]), config.personality,
                               config.physics_rate_hz, config.physics_dt_s, config.plant, config.position_rate_hz,
                               config.sample_interval_s, config.worker_log_level,
                               replace(PX4_SIH_ESTIMATE_ERROR, seed=config.seed) if config.estimate_error else None)
            p = ctx.Process(target=_emulator_worker, args=(child, job), name="fisc-emulators", daemon=True)
            p.start()
            child.close()
            procs.append(p)
            emu_conns.append(parent)
        ports = np.zeros(n, dtype=np.int64)
        for part, c in zip(emu_parts, emu_conns):
            ports[part] = _recv(c, "emulator", STARTUP_TIMEOUT_S)
        for part in _split(n, n_agent):
            parent, child = ctx.Pipe()
            job = _AgentJob(agent_ids=tuple(int(i) for i in part), ports=tuple(int(x) for x in ports[part]),
                            start_time_s=tuple(float(x) for x in plan.start_time_s[part]), map_path=str(map_path),
                            personality=config.personality, mode=settings.mode, lookahead_s=settings.lookahead_s,
                            exit_policy=config.exit_policy, geofence=config.agent_geofence(), rate_hz=config.rate_hz,
                            position_rate_hz=config.position_rate_hz, telemetry=config.telemetry,
                            log_level=config.worker_log_level, tracking=config.tracking, safety_net=config.safety_net,
                            staggered_admission=config.staggered_admission, fleet_mode=config.fleet_mode,
                            entry_radius_fraction=config.entry_radius_fraction, swarm=config.swarm,
                            zenoh_config=config.zenoh_config, zenoh_prefix=config.zenoh_prefix,
                            telemetry_rate_hz=config.telemetry_rate_hz, trusted_key=config.trusted_key,
                            flight_log_dir=config.flight_logs)
            p = ctx.Process(target=_agent_worker, args=(child, job), name="fisc-agents", daemon=True)
            p.start()
            child.close()
            procs.append(p)
            agent_conns.append(parent)
        for c in agent_conns:
            _recv(c, "agent", STARTUP_TIMEOUT_S)
        setup_s = time.monotonic() - t_setup
        t0 = time.monotonic() + 0.3
        t_end = t0 + config.duration_s
        for c in emu_conns + agent_conns:
            c.send(("go", t0, t_end))
        log.info("emulate: %d vehicles launched over %.1f s, flying %.0f s of real time (%d emulator + %d agent "
                 "processes)", n, float(plan.start_time_s.max()), config.duration_s, n_emu, n_agent)
        while progress is not None and time.monotonic() < t_end:
            progress(min(1.0, max(0.0, (time.monotonic() - t0) / config.duration_s)))
            time.sleep(min(1.0, max(0.0, t_end - time.monotonic())))
        emu_res = [_recv(c, "emulator", config.duration_s + 60.0) for c in emu_conns]
        agent_res = [_recv(c, "agent", config.duration_s + 60.0) for c in agent_conns]
        if progress is not None:
            progress(1.0)
    finally:
        for c in emu_conns + agent_conns:
            c.close()
        for p in procs:
            p.join(5.0)
            if p.is_alive():
                p.terminate()
                p.join(5.0)
    ids = np.concatenate([r["agent_ids"] for r in emu_res])
    order = np.argsort(ids)
    k = min(r["pos_ned_m"].shape[0] for r in emu_res)
    pos = np.concatenate([r["pos_ned_m"][:k] for r in emu_res], axis=1)[:, order]
    vel = np.concatenate([r["vel_ned_m_s"][:k] for r in emu_res], axis=1)[:, order]
    agents = sorted((a for r in agent_res for a in r["agents"]), key=lambda a: a["agent_id"])
    return SwarmRun(
        agent_ids=ids[order], sample_t_s=emu_res[0]["sample_t_s"][:k], pos_ned_m=pos, vel_ned_m_s=vel, agents=agents,
        emulator_timing=[r["timing"] for r in emu_res], agent_timing=[r["timing"] for r in agent_res],
        setpoint_rate_hz=np.concatenate([r["setpoint_rate_hz"] for r in emu_res]),
        setpoint_rate_t_s=np.concatenate([r["setpoint_rate_t_s"] for r in emu_res]),
        duration_s=config.duration_s, setup_s=setup_s,
        messages={key: int(sum(r["messages"][key] for r in emu_res)) for key in ("rx", "tx")})
