"""``fisc-sim emulate``: an emulated swarm, headless, with real MAVLink in the loop.

N autopilot emulators (:class:`sim.autopilot.server.AutopilotEmulator`, PX4 or ArduPilot Copter
personality, the paper's velocity plant inside) and N onboard agents (:class:`fisc_agent.runner.
Runner`, the same code ``fisc-agent`` runs) talk MAVLink 2 over loopback UDP, one socket pair per
vehicle.  The agents fly the paper's Case 2 ("reservoir"): every vehicle starts disarmed on the
ground upstream of (and 10 m below) the inlet, arms, takes off, joins the tunnel at the inlet
(its mission's JOIN state) and flows through it (FLOW); after the outlet it flies back to the
inlet and goes round again (exit policy ``loop``), so the tunnel keeps being fed for the whole
run.  Start times are staggered so that vehicles reach the inlet at the paper's source rate
(eq. source_rate, scaled to the population as ``fisc-sim run`` scales it).

Process layout (2-core friendly): the emulators live in ``emulator_workers`` processes and the
agents in ``agent_workers`` processes; each process multiplexes its share in one thread on a
monotonic-deadline schedule (emulators: ``AutopilotEmulator.poll`` at the physics rate; agents:
``Runner.step`` at the setpoint rate).  Ground truth for the swarm fields is the emulators' true
vehicle state (not the telemetry), sampled on the ``fisc-sim run`` sampling grid, transformed to
the map frame with the default deployment transform (map x -> North, y -> East, z -> Up, map
origin at local NED (0, 0, -10)) and accumulated per CV with ``FieldAccumulator`` exactly as the
vectorised simulator does.  The outputs (fields.csv, metrics.json, figures, report.md) are
written with ``sim.report``/``sim.figures``, so they have the format of ``fisc-sim run``; in
addition ``emulation.json`` (timing, real-time figures, per-agent mission outcome) and, unless
disabled, ``comparison.json`` (the metric differences against ``fisc-sim run`` on the same
map, duration, population and mode) are written, and report.md gets an "Emulation" section.
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing as mp
import os
import shutil
import time
import traceback
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from fisc_agent.config import EXIT_POLICIES
from fisc_agent.control import MapGeometry, ScalarField, entry_point, join_waypoints
from fisc_agent.frames import DEFAULT_ORIGIN_NED_M, DeploymentTransform
from fisc_agent.lookup import COMMAND_MODES, CommandField
from fisc_agent.mapfile import CommandMap, load_map
from sim.scenarios import Reservoir, scale_for_agents

log = logging.getLogger(__name__)

PERSONALITIES = ("px4", "ardupilot")
MAP_FILE_NAME = "map.fiscmap"
MAVLINK_MSG_ID_GLOBAL_POSITION_INT = 33
MAV_CMD_SET_MESSAGE_INTERVAL = 511
#: Worker start-up (spawned interpreters import numpy/pymavlink; the agents decode the map).
STARTUP_TIMEOUT_S = 120.0


# ------------------------------------------------------------------------------------ config
@dataclass(frozen=True)
class EmulateConfig:
    """Everything one ``fisc-sim emulate`` needs (recorded in emulation.json)."""

    out_dir: str = "out/emulate"
    """Output directory (also receives ``map.fiscmap``, the map the agents load)."""
    map: str | None = None
    """Command map: ``.fiscmap`` path, a reference spec to fit now, or None for the embedded default."""
    agents: int = 50
    """Number of emulated vehicles N (one autopilot emulator + one agent each)."""
    duration_s: float = 60.0
    """Real (wall-clock) time flown, from the launch of the first vehicle [s]."""
    mode: str = "mean"
    """Command mode of the agents: mean, slot or interpolated."""
    personality: str = "px4"
    """Autopilot emulated: ``px4`` or ``ardupilot``."""
    exit_policy: str = "loop"
    """Agent exit policy after the outlet: ``loop`` (back to the inlet, keeps feeding), ``hold``, ``land``."""
    rate_hz: float = 20.0
    """Agent setpoint (control loop) rate [Hz]."""
    position_rate_hz: float = 20.0
    """LOCAL_POSITION_NED rate the agents request from their autopilot [Hz]."""
    physics_rate_hz: float = 50.0
    """Emulator service rate: receive, physics step (0.02 s), telemetry [Hz]."""
    average_window_s: float = 100.0
    """Fields are time-averaged over the last this many seconds of the run (as ``fisc-sim run``) [s]."""
    sample_interval_s: float = 0.1
    """Interval between ground-truth samples of the average (``fisc-sim run``'s default) [s]."""
    min_samples: int = 10
    """CVs with fewer agent samples in the window are left out of the metrics."""
    start_spacing_m: float = 1.0
    """Spacing of the ground start grid [m]."""
    start_gap_m: float = 3.0
    """Distance of the first start row upstream of the staging plane [m]."""
    launch_overhead_s: float = 4.0
    """Predicted time from mission start to the end of the climb-out (arming, OFFBOARD, takeoff) [s];
    used to stagger the launches so that arrivals at the inlet follow the source rate."""
    emulator_workers: int = 0
    """Processes hosting the emulators (0: automatic, 1 per 150 vehicles, at most 2)."""
    agent_workers: int = 0
    """Processes hosting the agents (0: automatic, 1 per 150 vehicles, at most 2)."""
    compare: bool = True
    """Also run ``fisc-sim run`` (vectorised) on the same map/duration/agents/mode and write comparison.json."""
    figures: bool = True
    """Write the PNG figures."""
    seed: int = 0
    """Seed of the comparison run (the emulated run itself is deterministic up to OS scheduling)."""
    worker_log_level: str = "WARNING"
    """Log level inside the worker processes (agents log every mission transition at INFO)."""

    def __post_init__(self) -> None:
        def need(cond: bool, msg: str) -> None:
            if not cond:
                raise ValueError(f"emulate: {msg}")

        need(isinstance(self.agents, int) and self.agents >= 1, f"agents must be >= 1, is {self.agents!r}")
        need(math.isfinite(self.duration_s) and self.duration_s > 0, f"duration_s must be > 0, is {self.duration_s!r}")
        need(self.mode in COMMAND_MODES, f"mode {self.mode!r}: choose one of {', '.join(COMMAND_MODES)}")
        need(self.personality in PERSONALITIES, f"personality {self.personality!r}: choose px4 or ardupilot")
        need(self.exit_policy in EXIT_POLICIES, f"exit_policy {self.exit_policy!r}: choose one of {EXIT_POLICIES}")
        for name in ("rate_hz", "position_rate_hz", "physics_rate_hz", "average_window_s", "sample_interval_s",
                     "start_spacing_m"):
            v = getattr(self, name)
            need(math.isfinite(v) and v > 0, f"{name} must be > 0, is {v!r}")
        need(self.rate_hz > 2.0, "rate_hz must be > 2 Hz (PX4 offboard needs a > 2 Hz stream)")
        need(self.start_gap_m >= 0 and self.launch_overhead_s >= 0, "start_gap_m and launch_overhead_s must be >= 0")
        need(self.emulator_workers >= 0 and self.agent_workers >= 0, "worker counts must be >= 0")
        need(self.worker_log_level in ("DEBUG", "INFO", "WARNING", "ERROR"), "worker_log_level must be a level name")

    def workers(self) -> tuple[int, int]:
        """(emulator processes, agent processes) actually used."""
        auto = min(2, max(1, math.ceil(self.agents / 150)))
        return (self.emulator_workers or auto), (self.agent_workers or auto)


# ------------------------------------------------------------------------------------ launch plan
@dataclass(frozen=True)
class LaunchPlan:
    """Where each vehicle starts and when its mission is switched on (Case 2 staggering)."""

    start_ned_m: np.ndarray
    """(N, 3) start positions, local NED, on the ground (D = 0) [m]."""
    start_time_s: np.ndarray
    """(N,) launch time of each vehicle relative to the first launch [s] (sorted ascending by id)."""
    arrival_time_s: np.ndarray
    """(N,) planned arrival time at the inlet, relative to the first launch [s]."""
    inflow_rate_per_s: float
    """Planned arrival rate at the inlet: eq. source_rate summed over the inlet, population-scaled [1/s]."""
    nominal_rate_per_s: float
    """The same rate before the cap that lets every vehicle launch within the run [1/s]."""


def launch_plan(field: CommandField, n_agents: int, transform: DeploymentTransform, join_speed_m_s: float = 2.0,
                takeoff_alt_m: float = 2.5, staging_m: float = 1.5, keepout_margin_m: float = 1.0,
                entry_radius_fraction: float = 0.6, spacing_m: float = 1.0, gap_m: float = 3.0,
                overhead_s: float = 4.0, duration_s: float | None = None) -> LaunchPlan:
    """Start grid and staggered launch times so vehicles reach the inlet at eq. source_rate.

    The arrival rate is ``Reservoir(field, population_scale=scale_for_agents(field, N)).rate_per_s``,
    the rate ``fisc-sim run --agents N`` injects at.  If N vehicles at that rate would not all have
    launched within the first half of ``duration_s``, the rate is raised to N / (duration / 2).
    Vehicle i's planned arrival is i / rate; its launch is that minus its predicted travel time:
    ``overhead_s`` (arm, OFFBOARD/GUIDED, climb-out to ``takeoff_alt_m``) plus the length of its
    join path (``fisc_agent.control.join_waypoints`` to its ``entry_point``) at ``join_speed_m_s``.
    Launch times are then shifted so that the earliest is 0.  Start positions: a square grid of
    ``spacing_m`` on the ground (D = 0), centred on the tunnel axis laterally, its first row
    ``gap_m`` upstream of the staging plane, filled in id order.
    """
    geom = MapGeometry.from_field(field)
    sfield = ScalarField(field)
    nominal = Reservoir(field, population_scale=scale_for_agents(field, n_agents)).rate_per_s
    rate = nominal
    if duration_s is not None and n_agents / rate > 0.5 * duration_s:
        rate = n_agents / (0.5 * duration_s)
    ncol = max(1, math.ceil(math.sqrt(n_agents)))
    k = np.arange(n_agents)
    row, col = k // ncol, k % ncol
    x0 = geom.x_inlet_m - staging_m - gap_m
    y_c = geom.inlet_center_yz_m[0]
    start_map = np.empty((n_agents, 3))
    start_map[:, 0] = x0 - spacing_m * row
    start_map[:, 1] = y_c + spacing_m * (col - 0.5 * (ncol - 1))
    start_ned = transform.map_to_ned(start_map)
    start_ned[:, 2] = 0.0
    ground_map = transform.ned_to_map(start_ned)
    travel = np.empty(n_agents)
    for i in range(n_agents):  # once, at set-up (not a hot path)
        entry = entry_point(i, geom, sfield, entry_radius_fraction)
        p = tuple(ground_map[i] + np.array([0.0, 0.0, takeoff_alt_m]))
        pts = np.array([p] + join_waypoints(p, entry, geom, staging_m, keepout_margin_m))
        travel[i] = overhead_s + float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1))) / join_speed_m_s
    arrival = k / rate
    launch = arrival - travel
    shift = -launch.min()
    return LaunchPlan(start_ned_m=start_ned, start_time_s=launch + shift, arrival_time_s=arrival + shift,
                      inflow_rate_per_s=float(rate), nominal_rate_per_s=float(nominal))


# ------------------------------------------------------------------------------------ map
def prepare_map(spec: str | None, out_dir: Path) -> tuple[Path, CommandMap]:
    """The map the agents load by path: an existing ``.fiscmap`` is used in place; the default
    map (None) or a reference spec is built now and written to ``out_dir/map.fiscmap``."""
    if spec is not None:
        p = Path(spec)
        if p.suffix == ".fiscmap" or (p.is_file() and p.read_bytes()[:8] == b"FISCMAP\x00"):
            return p, load_map(p)
    from fisc_ground.mapbuild import DEFAULT_REFERENCE, build_map
    from fisc_ground.mapwrite import write_map
    from fisc_ground.reference.load import load_reference

    meta, arrays = build_map(load_reference(spec or DEFAULT_REFERENCE))
    path = out_dir / MAP_FILE_NAME
    write_map(path, meta, arrays)
    return path, load_map(path)


# ------------------------------------------------------------------------------------ workers
@dataclass(frozen=True)
class _EmulatorJob:
    agent_ids: tuple[int, ...]
    start_ned_m: tuple[tuple[float, float, float], ...]
    personality: str
    physics_rate_hz: float
    position_rate_hz: float
    sample_interval_s: float
    log_level: str


@dataclass(frozen=True)
class _AgentJob:
    agent_ids: tuple[int, ...]
    ports: tuple[int, ...]
    start_time_s: tuple[float, ...]
    map_path: str
    personality: str
    mode: str
    exit_policy: str
    rate_hz: float
    position_rate_hz: float
    log_level: str


def _lag_stats(lags: list[float], busy: list[float], period: float, elapsed: float, n_ticks: int) -> dict:
    a = np.asarray(lags) if lags else np.zeros(1)
    b = np.asarray(busy) if busy else np.zeros(1)
    return {
        "period_s": period, "ticks": int(n_ticks), "elapsed_s": float(elapsed),
        "tick_rate_ratio": float(n_ticks * period / elapsed) if elapsed > 0 else float("nan"),
        "lag_p50_s": float(np.percentile(a, 50)), "lag_p99_s": float(np.percentile(a, 99)),
        "lag_max_s": float(a.max()), "busy_mean_s": float(b.mean()), "busy_p99_s": float(np.percentile(b, 99)),
        "utilisation": float(b.sum() / elapsed) if elapsed > 0 else float("nan"),
        "overruns": int(np.sum(a > period)),
    }


def _cpu_s() -> float:
    t = os.times()
    return t.user + t.system


def _sleep_until(deadline: float) -> None:
    dt = deadline - time.monotonic()
    if dt > 0:
        time.sleep(dt)


def _emulator_worker(conn, job: _EmulatorJob) -> None:
    """Host ``len(job.agent_ids)`` autopilot emulators in one thread (spawned process)."""
    try:
        logging.basicConfig(level=job.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        from sim.autopilot.personalities import FlightMode
        from sim.autopilot.server import AutopilotEmulator

        emus = [AutopilotEmulator("udpin:127.0.0.1:0", job.personality, start, sysid=1 + aid % 250,
                                  rate_position_hz=job.position_rate_hz, rate_attitude_hz=0.0)
                for aid, start in zip(job.agent_ids, job.start_ned_m)]
        conn.send(("ports", [e.local_address[1] for e in emus]))
        msg = conn.recv()
        if msg[0] != "go":
            return
        t0, t_end = msg[1], msg[2]
        offboard = {FlightMode.OFFBOARD, FlightMode.GUIDED}
        period = 1.0 / job.physics_rate_hz
        n = len(emus)
        n_samples = int(math.floor((t_end - t0) / job.sample_interval_s + 1e-9)) + 1
        pos = np.full((n_samples, n, 3), np.nan)
        vel = np.full((n_samples, n, 3), np.nan)
        sample_t = np.full(n_samples, np.nan)
        sp_rate: list[float] = []
        next_rate_probe = t0 + 1.0
        lags: list[float] = []
        busy: list[float] = []
        _sleep_until(t0)
        cpu0, wall0 = _cpu_s(), time.monotonic()
        k_next = 0
        tick = 0
        while True:
            deadline = t0 + tick * period
            start = time.monotonic()
            if start >= t_end:
                break
            lags.append(start - deadline)
            for e in emus:
                e.poll()
            now = time.monotonic()
            while k_next < n_samples and now >= t0 + k_next * job.sample_interval_s:
                for j, e in enumerate(emus):
                    st = e.state
                    pos[k_next, j] = st.position_ned_m
                    vel[k_next, j] = st.velocity_ned_m_s
                sample_t[k_next] = now - t0
                k_next += 1
            if now >= next_rate_probe:
                next_rate_probe += 1.0
                for e in emus:
                    st = e.state
                    if st.armed and st.in_air and st.mode in offboard:
                        sp_rate.append(e.vehicle.setpoint_rate_hz(1.0))
            busy.append(time.monotonic() - start)
            tick += 1
            next_t = t0 + tick * period
            if next_t < time.monotonic() - period:  # overrun by more than a period: re-synchronise
                tick = int((time.monotonic() - t0) / period) + 1
                next_t = t0 + tick * period
            _sleep_until(next_t)
        wall = time.monotonic() - wall0
        cpu = _cpu_s() - cpu0
        # the final sample (end of the run), as fisc-sim run takes one at its last step
        if k_next < n_samples:
            for e in emus:
                e.poll()
            for j, e in enumerate(emus):
                pos[k_next:, j] = e.state.position_ned_m
                vel[k_next:, j] = e.state.velocity_ned_m_s
            sample_t[k_next:] = time.monotonic() - t0
        stats = {"rx": int(sum(e.stats["rx"] for e in emus)), "tx": int(sum(e.stats["tx"] for e in emus))}
        for e in emus:
            e.close()
        conn.send(("result", {
            "agent_ids": np.asarray(job.agent_ids), "pos_ned_m": pos, "vel_ned_m_s": vel, "sample_t_s": sample_t,
            "setpoint_rate_hz": np.asarray(sp_rate), "loop": _lag_stats(lags, busy, period, wall, tick),
            "cpu_s": cpu, "wall_s": wall, "messages": stats,
        }))
    except Exception:  # noqa: BLE001 - reported to the parent, which raises
        conn.send(("error", traceback.format_exc()))
    finally:
        conn.close()


def _agent_worker(conn, job: _AgentJob) -> None:
    """Host ``len(job.agent_ids)`` fisc-agent runners in one thread (spawned process)."""
    try:
        logging.basicConfig(level=job.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        from fisc_agent.adapters import CommandLong
        from fisc_agent.config import AgentConfig
        from fisc_agent.endpoints import parse_endpoint
        from fisc_agent.link import MavlinkLink
        from fisc_agent.runner import Runner

        cmap = load_map(job.map_path)
        runners = []
        for aid, port in zip(job.agent_ids, job.ports):
            cfg = AgentConfig(mavlink_url=f"udpout:127.0.0.1:{port}", agent_id=int(aid), map_path=job.map_path,
                              autopilot=job.personality, mode=job.mode, rate_hz=job.rate_hz,
                              exit_policy=job.exit_policy)
            link = MavlinkLink(parse_endpoint(cfg.mavlink_url), position_rate_hz=job.position_rate_hz)
            runners.append(Runner(cfg, link, cmap))
        # the agent needs LOCAL_POSITION_NED only: switch the autopilot's GLOBAL_POSITION_INT
        # stream off once it is found (what a bandwidth-conscious companion computer does)
        trim = CommandLong(MAV_CMD_SET_MESSAGE_INTERVAL, (float(MAVLINK_MSG_ID_GLOBAL_POSITION_INT), -1.0, 0, 0, 0, 0, 0),
                           "GLOBAL_POSITION_INT off")
        trimmed = [False] * len(runners)
        conn.send(("ready", None))
        msg = conn.recv()
        if msg[0] != "go":
            return
        t0, t_end = msg[1], msg[2]
        starts = np.asarray(job.start_time_s) + t0
        period = 1.0 / job.rate_hz
        active = np.zeros(len(runners), dtype=bool)
        first_tick = np.full(len(runners), np.nan)
        lags: list[float] = []
        busy: list[float] = []
        _sleep_until(t0)
        cpu0, wall0 = _cpu_s(), time.monotonic()
        tick = 0
        while True:
            deadline = t0 + tick * period
            start = time.monotonic()
            if start >= t_end:
                break
            lags.append(start - deadline)
            newly = (~active) & (starts <= start)
            if newly.any():
                first_tick[newly] = start - t0
                active |= newly
            for i in np.flatnonzero(active):
                r = runners[i]
                r.step()
                if not trimmed[i] and r.link.target_system is not None:
                    r.link.send_command(trim)
                    trimmed[i] = True
            busy.append(time.monotonic() - start)
            tick += 1
            next_t = t0 + tick * period
            if next_t < time.monotonic() - period:
                tick = int((time.monotonic() - t0) / period) + 1
                next_t = t0 + tick * period
            _sleep_until(next_t)
        wall = time.monotonic() - wall0
        cpu = _cpu_s() - cpu0
        agents = []
        for i, r in enumerate(runners):
            m = r.mission
            agents.append({
                "agent_id": int(job.agent_ids[i]), "launch_s": float(first_tick[i]), "state": m.state.value,
                "reason": m.reason, "laps": int(m.laps), "ticks": int(r.ticks),
                "setpoints_sent": int(getattr(r.link, "setpoints_sent", 0)),
                "transitions": [(float(tr.t_s - t0), tr.src.value, tr.dst.value, tr.reason) for tr in m.transitions],
            })
            r.link.close()
        conn.send(("result", {"agents": agents, "loop": _lag_stats(lags, busy, period, wall, tick), "cpu_s": cpu,
                              "wall_s": wall}))
    except Exception:  # noqa: BLE001 - reported to the parent, which raises
        conn.send(("error", traceback.format_exc()))
    finally:
        conn.close()


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
    """(K,) sample times since launch [s] (first worker's clock)."""
    pos_ned_m: np.ndarray
    """(K, N, 3) true positions, local NED [m]."""
    vel_ned_m_s: np.ndarray
    """(K, N, 3) true velocities, NED [m/s]."""
    agents: list[dict]
    """Per-agent mission outcome (state, laps, transitions with times since launch)."""
    emulator_loops: list[dict]
    """Loop timing of each emulator process."""
    agent_loops: list[dict]
    """Loop timing of each agent process."""
    setpoint_rate_hz: np.ndarray
    """Setpoint rates measured at the autopilots (flying in OFFBOARD/GUIDED, once a second) [Hz]."""
    cpu_s: float
    """CPU time of all worker processes during the flight [s]."""
    wall_s: float
    """Wall time of the flight [s]."""
    setup_s: float
    """Wall time of starting the workers (processes, sockets, map decoding) [s]."""
    messages: dict
    """MAVLink message counters summed over the emulators (rx, tx)."""


def fly_swarm(map_path: Path, plan: LaunchPlan, config: EmulateConfig,
              progress: Callable[[float], None] | None = None) -> SwarmRun:
    """Start the emulator and agent processes, fly ``config.duration_s`` of real time, collect."""
    n = plan.start_ned_m.shape[0]
    n_emu, n_agent = config.workers()
    ctx = mp.get_context("spawn")
    t_setup = time.monotonic()
    procs: list = []
    emu_conns, agent_conns = [], []
    try:
        emu_parts = _split(n, n_emu)
        for part in emu_parts:
            parent, child = ctx.Pipe()
            job = _EmulatorJob(tuple(int(i) for i in part), tuple(tuple(map(float, p)) for p in plan.start_ned_m[part]),
                               config.personality, config.physics_rate_hz, config.position_rate_hz,
                               config.sample_interval_s, config.worker_log_level)
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
            job = _AgentJob(tuple(int(i) for i in part), tuple(int(x) for x in ports[part]),
                            tuple(float(x) for x in plan.start_time_s[part]), str(map_path), config.personality,
                            config.mode, config.exit_policy, config.rate_hz, config.position_rate_hz,
                            config.worker_log_level)
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
        emulator_loops=[r["loop"] for r in emu_res], agent_loops=[r["loop"] for r in agent_res],
        setpoint_rate_hz=np.concatenate([r["setpoint_rate_hz"] for r in emu_res]),
        cpu_s=float(sum(r["cpu_s"] for r in emu_res + agent_res)),
        wall_s=float(max(r["wall_s"] for r in emu_res + agent_res)), setup_s=setup_s,
        messages={key: int(sum(r["messages"][key] for r in emu_res)) for key in ("rx", "tx")})
