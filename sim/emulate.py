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
written with ``fisc_ground.field_report``/``field_figures``, so they have the format of ``fisc-sim run``; in
addition ``emulation.json`` (timing, real-time figures, per-agent mission outcome) and, unless
disabled, ``comparison.json`` (the metric differences against ``fisc-sim run`` on the same
map, duration, population and mode) are written, and report.md gets an "Emulation" section.
"""

from __future__ import annotations

import gc
import logging
import math
import multiprocessing as mp
import os
import resource
import time
import traceback
from types import SimpleNamespace
from dataclasses import asdict, dataclass, replace
from dataclasses import field as dataclass_field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from fisc_agent.config import EXIT_POLICIES, GEOFENCE_POLICIES
from fisc_agent.control import MapGeometry, ScalarField, entry_point, join_waypoints
from fisc_agent.frames import DEFAULT_ORIGIN_NED_M, DeploymentTransform
from fisc_agent.lookup import COMMAND_MODES, CommandField
from fisc_agent.mapfile import MAGIC, CommandMap, load_map
from fisc_agent.safe_files import read_head
from sim.scenarios import Reservoir, scale_for_agents

log = logging.getLogger(__name__)

PERSONALITIES = ("px4", "ardupilot")
MAP_FILE_NAME = "map.fiscmap"
MAV_CMD_SET_MESSAGE_INTERVAL = 511
#: Worker start-up (spawned interpreters import numpy/pymavlink; the agents decode the map).
STARTUP_TIMEOUT_S = 120.0
TELEMETRY = ("full", "lean")
#: Measured launch overheads [s] (PX4 streams 1 s before OFFBOARD and climbs in OFFBOARD;
#: ArduPilot arms in GUIDED and takes off by command): arrivals then land within ~0.2 s of the plan.
LAUNCH_OVERHEAD_S = {"px4": 6.2, "ardupilot": 4.8}


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
    mode: str | None = None
    """Command mode of the agents (``fisc_agent.lookup.COMMAND_MODES``); None: the map's recommended one."""
    lookahead_s: float | None = None
    """Command look-ahead of the agents [s]; None: the map's recommended value."""
    preset: str = "default"
    """``default`` (schema-2 map, its recommended settings) or ``paper`` (schema-1 map, Algorithm 1)."""
    personality: str = "px4"
    """Autopilot emulated: ``px4`` or ``ardupilot``."""
    exit_policy: str = "loop"
    """Agent exit policy after the outlet: ``loop`` (back to the inlet, keeps feeding), ``hold``, ``land``."""
    geofence: str = "return"
    """Agents leaving the CVs sideways: ``return`` (fly back to the nearest CV, as the simulator's return
    policy; the kinetic mode's deviations reach the staircase walls) or ``hold``."""
    rate_hz: float = 20.0
    """Agent setpoint (control loop) rate [Hz]."""
    position_rate_hz: float = 20.0
    """LOCAL_POSITION_NED rate the agents request from their autopilot [Hz]."""
    physics_rate_hz: float = 50.0
    """Emulator service rate: receive, advance the physics, send due telemetry [Hz]."""
    physics_dt_s: float = 0.02
    """Physics step of the emulated vehicles [s] (the emulator's default; 0.05 = the simulator's dt)."""
    plant: str = "paper"
    """Vehicle model inside the emulators: a named ``sim.plant_fit.PLANT_PRESETS`` entry."""
    telemetry: str = "full"
    """``full``: the autopilots' default streams; ``lean``: the agents switch every stream but HEARTBEAT
    and LOCAL_POSITION_NED off (MAV_CMD_SET_MESSAGE_INTERVAL), as a companion on a busy link would."""
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
    launch_overhead_s: float | None = None
    """Predicted time from mission start to the end of the climb-out (HEARTBEAT discovery, arming,
    OFFBOARD/GUIDED, takeoff) [s], used to stagger the launches so that arrivals at the inlet follow
    the source rate; None: measured default of the personality (``LAUNCH_OVERHEAD_S``)."""
    emulator_workers: int = 0
    """Processes hosting the emulators (0: automatic, 1 per 200 vehicles, at most one per CPU)."""
    agent_workers: int = 0
    """Processes hosting the agents (0: automatic, 1 per 300 vehicles, at most one per CPU)."""
    compare: bool = True
    """Also run ``fisc-sim run`` (vectorised) on the same map/duration/agents/mode and write comparison.json."""
    figures: bool = True
    """Write the PNG figures."""
    seed: int = 0
    """Seed of the comparison run (the emulated run itself is deterministic up to OS scheduling)."""
    worker_log_level: str = "WARNING"
    """Log level inside the worker processes (agents log every mission transition at INFO)."""
    swarm: str | None = None
    """Zenoh swarm name: when set, every agent publishes its telemetry on
    ``<prefix>/<swarm>/agents/<id>/telemetry`` as a deployed fleet does, so ``fisc-ground monitor``
    and ``status`` can watch the emulated swarm; None: no Zenoh."""
    zenoh_config: str | None = None
    """Standard Zenoh JSON5 config file for the agents' session (None: the lab default, peer mode on
    loopback connecting to the hub ``tcp/127.0.0.1:7447``)."""
    zenoh_prefix: str = "fisc"
    """Zenoh key-expression prefix."""
    telemetry_rate_hz: float = 5.0
    """Zenoh telemetry rate per agent [Hz] (with ``swarm``)."""
    trusted_key: str | None = None
    """Ground Ed25519 public key (.pub) the agents trust for maps and fleet commands over Zenoh
    (required with ``swarm``, as on a real fleet)."""

    def __post_init__(self) -> None:
        def need(cond: bool, msg: str) -> None:
            if not cond:
                raise ValueError(f"emulate: {msg}")

        need(isinstance(self.agents, int) and self.agents >= 1, f"agents must be >= 1, is {self.agents!r}")
        need(math.isfinite(self.duration_s) and self.duration_s > 0, f"duration_s must be > 0, is {self.duration_s!r}")
        need(self.mode is None or self.mode in COMMAND_MODES,
             f"mode {self.mode!r}: choose one of {', '.join(COMMAND_MODES)}")
        need(self.lookahead_s is None or (math.isfinite(self.lookahead_s) and self.lookahead_s >= 0),
             f"lookahead_s must be finite and >= 0, got {self.lookahead_s!r}")
        need(self.preset in ("default", "paper"), f"preset {self.preset!r}: choose default or paper")
        need(self.personality in PERSONALITIES, f"personality {self.personality!r}: choose px4 or ardupilot")
        need(self.exit_policy in EXIT_POLICIES, f"exit_policy {self.exit_policy!r}: choose one of {EXIT_POLICIES}")
        need(self.geofence in GEOFENCE_POLICIES, f"geofence {self.geofence!r}: choose one of {GEOFENCE_POLICIES}")
        need(self.telemetry in TELEMETRY, f"telemetry {self.telemetry!r}: choose one of {', '.join(TELEMETRY)}")
        for name in ("rate_hz", "position_rate_hz", "physics_rate_hz", "physics_dt_s", "average_window_s",
                     "sample_interval_s", "start_spacing_m"):
            v = getattr(self, name)
            need(math.isfinite(v) and v > 0, f"{name} must be > 0, is {v!r}")
        need(self.rate_hz > 2.0, "rate_hz must be > 2 Hz (PX4 offboard needs a > 2 Hz stream)")
        need(self.start_gap_m >= 0, "start_gap_m must be >= 0")
        need(self.launch_overhead_s is None or self.launch_overhead_s >= 0, "launch_overhead_s must be >= 0")
        need(self.emulator_workers >= 0 and self.agent_workers >= 0, "worker counts must be >= 0")
        need(self.worker_log_level in ("DEBUG", "INFO", "WARNING", "ERROR"), "worker_log_level must be a level name")
        need(self.telemetry_rate_hz > 0, f"telemetry_rate_hz must be > 0, is {self.telemetry_rate_hz!r}")
        need(self.swarm is None or self.trusted_key is not None,
             "a Zenoh swarm needs the ground's public key (trusted_key / --trusted-key) for maps and commands")

    def agent_settings(self) -> "SimpleNamespace":
        """``mode`` and ``lookahead_s`` the agents are started with (None: the map's recommended;
        ``paper`` preset: mean, no look-ahead unless given)."""
        paper = self.preset == "paper"
        return SimpleNamespace(mode=self.mode if self.mode is not None or not paper else "mean",
                               lookahead_s=self.lookahead_s if self.lookahead_s is not None or not paper else 0.0)

    def workers(self) -> tuple[int, int]:
        """(emulator processes, agent processes) actually used.  Automatic: one emulator process
        per 200 vehicles and one agent process per 300 (an emulator costs about 1.5 x an agent),
        at most one per CPU."""
        ncpu = os.cpu_count() or 1
        emu = self.emulator_workers or min(ncpu, max(1, math.ceil(self.agents / 200)))
        agent = self.agent_workers or min(ncpu, max(1, math.ceil(self.agents / 300)))
        return emu, agent


# ------------------------------------------------------------------------------------ launch plan
@dataclass(frozen=True)
class LaunchPlan:
    """Where each vehicle starts and when its mission is switched on (Case 2 staggering)."""

    start_ned_m: np.ndarray
    """(N, 3) start positions, local NED, on the ground (D = 0) [m]."""
    start_time_s: np.ndarray
    """(N,) launch time of each vehicle (by id) relative to the first launch [s]."""
    arrival_time_s: np.ndarray
    """(N,) planned arrival time at the inlet, relative to the first launch [s]."""
    inflow_rate_per_s: float
    """Planned arrival rate at the inlet: eq. source_rate summed over the inlet, population-scaled [1/s]."""
    nominal_rate_per_s: float
    """The same rate before the cap that lets every vehicle launch within the run [1/s]."""


def launch_plan(field: CommandField, n_agents: int, transform: DeploymentTransform, join_speed_m_s: float = 2.0,
                takeoff_alt_m: float = 2.5, staging_m: float = 1.5, keepout_margin_m: float = 1.0,
                entry_radius_fraction: float = 0.6, spacing_m: float = 1.0, gap_m: float = 3.0,
                overhead_s: float = LAUNCH_OVERHEAD_S["px4"], duration_s: float | None = None) -> LaunchPlan:
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
    start_map = np.zeros((n_agents, 3))  # z is irrelevant (D is set to 0) but must be finite: NaN*0 = NaN
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
def prepare_map(spec: str | None, out_dir: Path, preset: str = "default") -> tuple[Path, CommandMap]:
    """The map the agents load by path: an existing ``.fiscmap`` is used in place; the default
    map (None) or a reference spec is built now (the paper's schema-1 map with ``preset`` ``paper``)
    and written to ``out_dir/map.fiscmap``."""
    if spec is not None:
        p = Path(spec)
        if p.suffix == ".fiscmap" or (p.is_file() and read_head(p, 8, what="map or reference file") == MAGIC):
            return p, load_map(p)
    from fisc_ground.mapbuild import DEFAULT_REFERENCE, FitConfig, build_map
    from fisc_ground.mapwrite import write_map
    from fisc_ground.reference.load import load_reference

    meta, arrays = build_map(load_reference(spec or DEFAULT_REFERENCE), FitConfig(staggered=preset != "paper"))
    path = out_dir / MAP_FILE_NAME
    write_map(path, meta, arrays)
    return path, load_map(path)


# ------------------------------------------------------------------------------------ workers
#: Streams an agent needs (HEARTBEAT is fixed-rate): with ``telemetry="lean"`` the agents switch
#: every other stream of their autopilot off (MAV_CMD_SET_MESSAGE_INTERVAL, interval -1).
LEAN_OFF_MSG_IDS = (33, 1, 245, 2, 24, 242, 74, 30)
"""GLOBAL_POSITION_INT, SYS_STATUS, EXTENDED_SYS_STATE, SYSTEM_TIME, GPS_RAW_INT, HOME_POSITION, VFR_HUD, ATTITUDE."""


@dataclass(frozen=True)
class _EmulatorJob:
    agent_ids: tuple[int, ...]
    start_ned_m: tuple[tuple[float, float, float], ...]
    start_time_s: tuple[float, ...]
    personality: str
    physics_rate_hz: float
    physics_dt_s: float
    plant: str
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
    mode: str | None
    lookahead_s: float | None
    exit_policy: str
    geofence: str
    rate_hz: float
    position_rate_hz: float
    telemetry: str
    log_level: str
    swarm: str | None = None
    zenoh_config: str | None = None
    zenoh_prefix: str = "fisc"
    telemetry_rate_hz: float = 5.0
    trusted_key: str | None = None


class _LoopLog:
    """Per-tick timing of a worker loop and its CPU time once a second (times since launch)."""

    def __init__(self, t0: float, period: float) -> None:
        self.t0, self.period = t0, period
        self.tick_t: list[float] = []
        self.lag: list[float] = []
        self.busy: list[float] = []
        self.cpu_t: list[float] = [0.0]
        self.cpu: list[float] = [_cpu_s()]

    def tick(self, start: float, deadline: float, end: float) -> None:
        self.tick_t.append(start - self.t0)
        self.lag.append(start - deadline)
        self.busy.append(end - start)
        if end - self.t0 >= self.cpu_t[-1] + 1.0:
            self.cpu_t.append(end - self.t0)
            self.cpu.append(_cpu_s())

    def export(self) -> dict:
        self.cpu_t.append(time.monotonic() - self.t0)
        self.cpu.append(_cpu_s())
        return {"period_s": self.period, "tick_t_s": np.asarray(self.tick_t), "lag_s": np.asarray(self.lag),
                "busy_s": np.asarray(self.busy), "cpu_t_s": np.asarray(self.cpu_t), "cpu_s": np.asarray(self.cpu)}


def loop_stats(log_: dict, t_from_s: float, t_to_s: float) -> dict:
    """Timing of one worker loop over [t_from_s, t_to_s] (times since launch): the share of the
    nominal ticks it ran, lag of the tick starts behind their deadlines, gaps between tick starts
    (how long its vehicles went unserved; a loop that falls more than a period behind skips the
    missed ticks, so gaps, not lags, show the stall), busy share, CPU."""
    period = float(log_["period_s"])
    t = log_["tick_t_s"]
    sel = (t >= t_from_s) & (t <= t_to_s)
    span = max(t_to_s - t_from_s, period)
    lag = log_["lag_s"][sel] if sel.any() else np.zeros(1)
    gap = np.diff(t[sel]) if sel.sum() >= 2 else np.full(1, period)
    busy = log_["busy_s"][sel] if sel.any() else np.zeros(1)
    cpu_t, cpu = log_["cpu_t_s"], log_["cpu_s"]
    c0, c1 = np.interp([t_from_s, t_to_s], cpu_t, cpu)
    return {
        "period_s": period, "window_s": [float(t_from_s), float(t_to_s)], "ticks": int(sel.sum()),
        "tick_rate_ratio": float(sel.sum() * period / span),
        "lag_p50_s": float(np.percentile(lag, 50)), "lag_p99_s": float(np.percentile(lag, 99)),
        "lag_max_s": float(lag.max()), "gap_p99_s": float(np.percentile(gap, 99)), "gap_max_s": float(gap.max()),
        "busy_mean_s": float(busy.mean()), "busy_p99_s": float(np.percentile(busy, 99)),
        "utilisation": float(busy.sum() / span), "overruns": int(np.sum(lag > period)),
        "cpu_s": float(c1 - c0), "cpu_cores": float((c1 - c0) / span),
    }


def _cpu_s() -> float:
    t = os.times()
    return t.user + t.system


def _raise_fd_limit() -> None:
    """Allow one socket per hosted vehicle beyond the usual soft limit of 1024 descriptors."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = 65536 if hard == resource.RLIM_INFINITY else hard
    if soft != resource.RLIM_INFINITY and soft < want:
        resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))


def _freeze_heap() -> None:
    """Move the set-up objects (emulators, runners, maps) out of the cyclic GC's reach: a full
    collection over hundreds of vehicles' objects stalls a real-time loop for tens of ms."""
    gc.collect()
    gc.freeze()


def _sleep_until(deadline: float) -> None:
    dt = deadline - time.monotonic()
    if dt > 0:
        time.sleep(dt)


def _next_tick(t0: float, tick: int, period: float) -> tuple[int, float]:
    """Next tick index and deadline; after an overrun of more than a period, re-synchronise."""
    tick += 1
    next_t = t0 + tick * period
    now = time.monotonic()
    if next_t < now - period:
        tick = int((now - t0) / period) + 1
        next_t = t0 + tick * period
    return tick, next_t


def _emulator_worker(conn, job: _EmulatorJob) -> None:
    """Host ``len(job.agent_ids)`` autopilot emulators in one thread (spawned process)."""
    try:
        logging.basicConfig(level=job.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        from sim.autopilot.personalities import FlightMode
        from sim.autopilot.server import AutopilotEmulator
        from sim.autopilot.vehicle import VehicleConfig
        from sim.plant import VelocityPlant

        _raise_fd_limit()
        from sim.plant_fit import plant_preset

        vcfg = VehicleConfig(physics_dt_s=job.physics_dt_s, plant_params=plant_preset(job.plant))
        emus = [AutopilotEmulator("udpin:127.0.0.1:0", job.personality, start, sysid=1 + aid % 250,
                                  rate_position_hz=job.position_rate_hz, vehicle_config=vcfg)
                for aid, start in zip(job.agent_ids, job.start_ned_m)]
        order = np.argsort(np.asarray(job.start_time_s), kind="stable")
        emus = [emus[j] for j in order]  # by launch time (the parent puts the columns back in id order)
        ids = np.asarray(job.agent_ids)[order]
        serve_from = np.asarray(job.start_time_s)[order] - 0.5
        # warm-up: the plant's numba kernel compiles (or loads its cache) on the first call; do
        # it now, not on the first vehicle's lift-off (a stall there reads as a stale position)
        VelocityPlant(vcfg.plant_params, 1).step(np.zeros((1, 3)), job.physics_dt_s)
        n = len(emus)
        sp_count = np.zeros(n, dtype=np.int64)

        def counting(j: int, fn: Callable) -> Callable:
            def set_setpoint(*a, **kw):
                sp_count[j] += 1
                return fn(*a, **kw)
            return set_setpoint

        for j, e in enumerate(emus):  # count the setpoints that reach each vehicle
            e.vehicle.set_setpoint = counting(j, e.vehicle.set_setpoint)
        _freeze_heap()
        ports = [0] * n
        for j, e in zip(order, emus):
            ports[j] = e.local_address[1]
        conn.send(("ports", ports))  # in job order
        msg = conn.recv()
        if msg[0] != "go":
            return
        t0, t_end = msg[1], msg[2]
        offboard = {FlightMode.OFFBOARD, FlightMode.GUIDED}
        period = 1.0 / job.physics_rate_hz
        n_samples = int(math.floor((t_end - t0) / job.sample_interval_s + 1e-9)) + 1
        pos = np.full((n_samples, n, 3), np.nan)
        vel = np.full((n_samples, n, 3), np.nan)
        sample_t = np.full(n_samples, np.nan)
        sp_t: list[float] = []
        sp_rate: list[float] = []
        probe_count = np.zeros(n, dtype=np.int64)
        probe_flying = np.zeros(n, dtype=bool)
        probe_t = 0.0
        n_live = 0
        _sleep_until(t0)
        loop = _LoopLog(t0, period)
        k_next = 0
        tick = 0
        next_probe = t0 + 1.0
        while True:
            deadline = t0 + tick * period
            start = time.monotonic()
            if start >= t_end:
                break
            # a vehicle is served from just before its agent is switched on: until then it sits
            # landed and disarmed with nobody listening, and its first poll catches the physics up
            if n_live < n:
                n_live = int(np.searchsorted(serve_from, start - t0, side="right"))
            for e in emus[:n_live]:
                e.poll()
            now = time.monotonic()
            while k_next < n_samples and now >= t0 + k_next * job.sample_interval_s:
                for j, e in enumerate(emus):
                    st = e.state
                    pos[k_next, j] = st.position_ned_m
                    vel[k_next, j] = st.velocity_ned_m_s
                sample_t[k_next] = now - t0
                k_next += 1
            if now >= next_probe:  # setpoint rate over the last second, vehicles flying offboard throughout
                next_probe += 1.0
                flying = np.array([e.state.armed and e.state.in_air and e.state.mode in offboard for e in emus])
                both = flying & probe_flying
                if both.any() and now > probe_t:
                    rates = (sp_count[both] - probe_count[both]) / (now - t0 - probe_t)
                    sp_rate.extend(rates.tolist())
                    sp_t.extend([now - t0] * rates.size)
                probe_count[:], probe_flying[:], probe_t = sp_count, flying, now - t0
            loop.tick(start, deadline, time.monotonic())
            tick, next_t = _next_tick(t0, tick, period)
            _sleep_until(next_t)
        timing = loop.export()
        if k_next < n_samples:  # the final sample (end of the run), as fisc-sim run takes one at its last step
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
            "agent_ids": ids, "pos_ned_m": pos, "vel_ned_m_s": vel, "sample_t_s": sample_t,
            "setpoint_rate_hz": np.asarray(sp_rate), "setpoint_rate_t_s": np.asarray(sp_t), "timing": timing,
            "messages": stats,
        }))
    except Exception:  # noqa: BLE001 - reported to the parent, which raises
        conn.send(("error", traceback.format_exc()))
    finally:
        conn.close()


def _open_fleet_links(job: _AgentJob, runners: list) -> tuple[Any, list]:
    """With ``job.swarm``: one Zenoh session for the worker and one ``AgentZenohLink`` per runner
    (telemetry out; maps and fleet commands in, which need the ground's signature as on a real
    fleet).  Returns (session, links); (None, []) without a swarm."""
    if not job.swarm:
        return None, []
    from fisc_agent.mapfile import read_public_key
    from fisc_agent.zenoh_link import AgentZenohLink, open_session

    keys = [read_public_key(job.trusted_key)]
    session = open_session(job.zenoh_config)
    links = [AgentZenohLink(None, job.swarm, int(aid), keys, False, r.offer_map, r.fleet_command,
                            prefix=job.zenoh_prefix, session=session).start()
             for aid, r in zip(job.agent_ids, runners)]
    return session, links


def _agent_worker(conn, job: _AgentJob) -> None:
    """Host ``len(job.agent_ids)`` fisc-agent runners in one thread (spawned process)."""
    try:
        logging.basicConfig(level=job.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        from fisc_agent.adapters import CommandLong
        from fisc_agent.config import AgentConfig
        from fisc_agent.endpoints import parse_endpoint
        from fisc_agent.link import MavlinkLink
        from fisc_agent.runner import Runner

        _raise_fd_limit()
        cmap = load_map(job.map_path)
        runners = []
        for aid, port in zip(job.agent_ids, job.ports):
            cfg = AgentConfig(mavlink_url=f"udpout:127.0.0.1:{port}", agent_id=int(aid), map_path=job.map_path,
                              autopilot=job.personality, mode=job.mode, lookahead_s=job.lookahead_s,
                              rate_hz=job.rate_hz,
                              exit_policy=job.exit_policy, geofence=job.geofence)
            link = MavlinkLink(parse_endpoint(cfg.mavlink_url), position_rate_hz=job.position_rate_hz)
            runners.append(Runner(cfg, link, cmap))
        # lean telemetry: once the autopilot is found, switch its streams other than HEARTBEAT and
        # LOCAL_POSITION_NED off, one command per tick (what a bandwidth-conscious companion does)
        trims = [CommandLong(MAV_CMD_SET_MESSAGE_INTERVAL, (float(mid), -1.0, 0, 0, 0, 0, 0), f"stream {mid} off")
                 for mid in (LEAN_OFF_MSG_IDS if job.telemetry == "lean" else ())]
        trimmed = np.zeros(len(runners), dtype=np.int64)
        session, zlinks = _open_fleet_links(job, runners)
        telemetry_every = max(1, round(job.rate_hz / job.telemetry_rate_hz))
        _freeze_heap()
        conn.send(("ready", None))
        msg = conn.recv()
        if msg[0] != "go":
            return
        t0, t_end = msg[1], msg[2]
        starts = np.asarray(job.start_time_s) + t0
        period = 1.0 / job.rate_hz
        active = np.zeros(len(runners), dtype=bool)
        first_tick = np.full(len(runners), np.nan)
        _sleep_until(t0)
        loop = _LoopLog(t0, period)
        tick = 0
        while True:
            deadline = t0 + tick * period
            start = time.monotonic()
            if start >= t_end:
                break
            newly = (~active) & (starts <= start)
            if newly.any():
                first_tick[newly] = start - t0
                active |= newly
            for i in np.flatnonzero(active):
                r = runners[i]
                r.step()
                if zlinks and tick % telemetry_every == 0:
                    zlinks[i].publish_telemetry(r.snapshot())
                if trimmed[i] < len(trims) and r.link.target_system is not None:
                    r.link.send_command(trims[trimmed[i]])
                    trimmed[i] += 1
            loop.tick(start, deadline, time.monotonic())
            tick, next_t = _next_tick(t0, tick, period)
            _sleep_until(next_t)
        timing = loop.export()
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
        for zl in zlinks:
            zl.close()
        if session is not None:
            session.close()
        conn.send(("result", {"agents": agents, "timing": timing}))
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
    """(K,) sample times since launch [s] (first emulator process's clock)."""
    pos_ned_m: np.ndarray
    """(K, N, 3) true positions, local NED [m]."""
    vel_ned_m_s: np.ndarray
    """(K, N, 3) true velocities, NED [m/s]."""
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
    settings = config.agent_settings()
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
                            settings.mode, settings.lookahead_s, config.exit_policy, config.geofence,
                            config.rate_hz,
                            config.position_rate_hz,
                            config.telemetry, config.worker_log_level, config.swarm, config.zenoh_config,
                            config.zenoh_prefix, config.telemetry_rate_hz, config.trusted_key)
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


# ------------------------------------------------------------------------------------ analysis
def sample_window(sample_t_s: np.ndarray, duration_s: float, average_window_s: float) -> np.ndarray:
    """Indices of the samples in the averaging window: the last ``average_window_s`` of the run
    (the whole run if it is shorter), as ``fisc-sim run`` averages."""
    start = max(0.0, duration_s - average_window_s)
    return np.flatnonzero(np.nan_to_num(sample_t_s, nan=-1.0) >= start - 1e-9)


def ground_truth_fields(swarm: SwarmRun, cmap: CommandMap, transform: DeploymentTransform, window: np.ndarray,
                        reference_velocity_m_s: np.ndarray):
    """Time-averaged swarm fields from the emulators' true states (map frame, per CV).

    Returns ``(SwarmFields, cv_ids (K, N))``: every sample in ``window`` is one ``FieldAccumulator.add``
    of all vehicles (vehicles outside every CV carry cv -1 and are ignored, as are NaN samples).
    """
    from fisc_ground.swarm_fields import FieldAccumulator

    field = CommandField.from_map(cmap)
    k, n = swarm.pos_ned_m.shape[:2]
    pos_map = transform.ned_to_map(swarm.pos_ned_m.reshape(-1, 3))
    vel_map = transform.vel_ned_to_map(swarm.vel_ned_m_s.reshape(-1, 3))
    finite = np.all(np.isfinite(pos_map), axis=1) & np.all(np.isfinite(vel_map), axis=1)
    cv = np.full(k * n, -1, dtype=np.int64)
    cv[finite] = field.cv_of(pos_map[finite])
    cv = cv.reshape(k, n)
    vel_map = np.where(finite[:, None], vel_map, 0.0).reshape(k, n, 3)
    acc = FieldAccumulator(field.n_cv, field.cell_size_m ** 3)
    mass = float(cmap.body.get("agent_mass_kg", 1.0))
    for i in window:  # one add per time sample (vectorised over vehicles inside)
        acc.add(cv[i], vel_map[i], mass, reference_velocity_m_s)
    return acc.result(), cv


def entry_statistics(agents: list[dict], plan: LaunchPlan) -> dict:
    """Arrivals at the inlet (JOIN -> FLOW transitions) against the launch plan."""
    first = np.array([next((t for t, src, dst, _ in a["transitions"] if dst == "FLOW" and src == "JOIN"), np.nan)
                      for a in agents])
    entries = np.sort(np.array([t for a in agents for t, src, dst, _ in a["transitions"]
                                if dst == "FLOW" and src == "JOIN"]))
    ok = np.isfinite(first)
    n_first = int(ok.sum())
    span = float(np.nanmax(first) - np.nanmin(first)) if n_first >= 2 else float("nan")
    err = first[ok] - plan.arrival_time_s[: first.size][ok]
    return {
        "vehicles_entered": n_first, "entries_total": int(entries.size),
        "planned_rate_per_s": plan.inflow_rate_per_s, "source_rate_per_s": plan.nominal_rate_per_s,
        "realised_first_entry_rate_per_s": (n_first - 1) / span if n_first >= 2 and span > 0 else None,
        "first_entry_s": float(np.nanmin(first)) if n_first else None,
        "last_first_entry_s": float(np.nanmax(first)) if n_first else None,
        "arrival_error_mean_s": float(err.mean()) if err.size else None,
        "arrival_error_std_s": float(err.std()) if err.size else None,
    }


def steady_start_s(plan: LaunchPlan, duration_s: float, settle_s: float = 3.0, min_window_s: float = 5.0) -> float:
    """Start of the steady (fully loaded) part of a run: every vehicle launched and streaming
    (last launch + ``settle_s``), or the second half of the run if that leaves < ``min_window_s``."""
    t = float(plan.start_time_s.max()) + settle_s
    return t if duration_s - t >= min_window_s else 0.5 * duration_s


def realtime_summary(swarm: SwarmRun, rate_hz: float, n_agents: int, t_from_s: float = 0.0,
                     tolerance: float = 0.05) -> dict:
    """Did the swarm keep real time over [t_from_s, end]?

    * the setpoint rate measured at the autopilots is within ``tolerance`` of ``rate_hz``;
    * every agent loop (the setpoint producers) ran >= (1 - tolerance) of its nominal ticks;
    * every loop, agent and emulator, kept its lag bounded relative to the control period
      T = 1 / rate_hz: p99 of the tick lag < T and p99 of the gap between ticks < 2 T (no vehicle
      went unserved for more than two control periods, 99 % of the time).

    CPU per agent = CPU seconds of all worker processes per vehicle per second of the window."""
    t_to = swarm.duration_s
    sel = swarm.setpoint_rate_t_s >= t_from_s
    sp = swarm.setpoint_rate_hz[sel]
    sp_mean = float(sp.mean()) if sp.size else float("nan")
    agent_loops = [loop_stats(tm, t_from_s, t_to) for tm in swarm.agent_timing]
    emulator_loops = [loop_stats(tm, t_from_s, t_to) for tm in swarm.emulator_timing]
    loops = agent_loops + emulator_loops
    control_period = 1.0 / rate_hz
    ticks_ok = bool(agent_loops) and all(lp["tick_rate_ratio"] >= 1.0 - tolerance for lp in agent_loops)
    lag_ok = bool(loops) and all(lp["lag_p99_s"] < control_period and lp["gap_p99_s"] < 2.0 * control_period
                                 for lp in loops)
    rate_ok = bool(sp.size) and abs(sp_mean - rate_hz) <= tolerance * rate_hz
    span = max(t_to - t_from_s, 1e-9)
    cpu = float(sum(lp["cpu_s"] for lp in loops))
    return {
        "keeps_real_time": bool(rate_ok and ticks_ok and lag_ok), "window_s": [float(t_from_s), float(t_to)],
        "setpoint_rate_nominal_hz": rate_hz, "setpoint_rate_mean_hz": sp_mean,
        "setpoint_rate_p5_hz": float(np.percentile(sp, 5)) if sp.size else None,
        "setpoint_rate_samples": int(sp.size), "setpoint_rate_ok": rate_ok, "loop_ticks_ok": ticks_ok,
        "loop_lag_ok": lag_ok, "cpu_s": cpu, "cpu_cores_used": cpu / span, "cpu_per_agent": cpu / span / n_agents,
        "setup_s": swarm.setup_s, "agent_loops": agent_loops, "emulator_loops": emulator_loops,
        "messages": swarm.messages,
    }


COMPARED_METRICS = ("nrmse_velocity", "nrmse_pressure", "nrmse_density", "pearson_velocity", "pearson_pressure",
                    "pearson_density", "centreline_max_dev_velocity", "centreline_max_dev_pressure",
                    "centreline_max_dev_density", "n_cv_compared")


def _num(v) -> float | None:
    return None if v is None or not math.isfinite(float(v)) else float(v)


def compare_fields(emu_metrics: dict, run_metrics: dict, emu_fields, run_fields, min_samples: int) -> dict:
    """Metric differences (emulate - run) and a direct comparison of the two swarm fields."""
    from fisc_ground.metrics import nrmse, normalise, pearson

    diff = {}
    for k in COMPARED_METRICS:
        e, r = _num(emu_metrics.get(k)), _num(run_metrics.get(k))
        if k == "n_cv_compared":
            e, r = (None if e is None else int(e)), (None if r is None else int(r))
        diff[k] = {"emulate": e, "run": r, "difference": None if e is None or r is None else e - r}
    direct = {}
    both = (emu_fields.samples >= min_samples) & (run_fields.samples >= min_samples)
    for name, attr, kind in (("velocity", "u_axial_m_s", "max"), ("pressure", "p_dispersion_pa", "minmax"),
                             ("density", "rho_s_kg_m3", "minmax")):
        a, b = np.asarray(getattr(emu_fields, attr), float), np.asarray(getattr(run_fields, attr), float)
        ok = both & np.isfinite(a) & np.isfinite(b)
        an, bn = (normalise(a[ok], kind), normalise(b[ok], kind)) if ok.sum() >= 2 else (None, None)
        direct[name] = {"n_cv": int(ok.sum()),
                        "nrmse_emulate_vs_run": None if an is None or bn is None else _num(nrmse(an, bn)),
                        "pearson_emulate_vs_run": _num(pearson(a[ok], b[ok])) if ok.sum() >= 2 else None}
    return {"metrics": diff, "fields_emulate_vs_run": direct,
            "cvs_with_samples": {"emulate": int(np.sum(emu_fields.samples >= min_samples)),
                                 "run": int(np.sum(run_fields.samples >= min_samples)), "both": int(both.sum())}}


# ------------------------------------------------------------------------------------ the job
@dataclass
class EmulateResult:
    """Outcome of ``run``: the emulated run in ``fisc-sim run``'s result form, plus emulation data."""

    config: EmulateConfig
    """The configuration."""
    run_result: Any
    """``sim.run.RunResult`` of the emulated swarm (fields from the emulators' true states)."""
    swarm: SwarmRun
    """Raw flight data (ground-truth samples, agent outcomes, loop timing)."""
    plan: LaunchPlan
    """Start positions and staggered launch times."""
    entries: dict
    """Arrivals at the inlet against the plan (``entry_statistics``)."""
    realtime: dict
    """Real-time and CPU figures (``realtime_summary``)."""
    comparison: dict | None = None
    """Metric differences against ``fisc-sim run`` (None when ``compare`` is off)."""
    paths: dict[str, Path] = dataclass_field(default_factory=dict)
    """Written outputs by name."""


def _run_config(config: EmulateConfig, map_path: Path):
    from sim.run import RunConfig

    return RunConfig(map=str(map_path), scenario="reservoir", agents=config.agents, duration_s=config.duration_s,
                     average_window_s=config.average_window_s, sample_interval_s=config.sample_interval_s,
                     mode=config.mode, lookahead_s=config.lookahead_s, preset=config.preset,
                     seed=config.seed, dt_s=1.0 / config.rate_hz, min_samples=config.min_samples,
                     figures=config.figures, out_dir=config.out_dir)


def _counters(agents: list[dict], cv_last: np.ndarray, n_steps: int, agent_steps: int):
    """Run-style bookkeeping: injected = inlet entries, exited = outlet passes (laps), alive =
    vehicles inside a CV at the end, escaped = the rest (left the map sideways: geofence)."""
    from sim.swarm import SwarmCounters

    injected = sum(1 for a in agents for _, src, dst, _ in a["transitions"] if src == "JOIN" and dst == "FLOW")
    exited = sum(a["laps"] for a in agents)
    alive = int(np.sum(cv_last >= 0))
    return SwarmCounters(injected=injected, exited=exited, escaped=max(0, injected - exited - alive),
                         returned=0, steps=n_steps, agent_steps=agent_steps), alive


def _snapshots(swarm: SwarmRun, cv: np.ndarray, transform: DeploymentTransform, times_s: tuple[float, ...],
               t_offset_s: float) -> list[tuple[float, np.ndarray]]:
    out = []
    for t in times_s:
        tt = t + t_offset_s
        if not np.isfinite(swarm.sample_t_s).any() or tt > np.nanmax(swarm.sample_t_s):
            continue
        i = int(np.nanargmin(np.abs(swarm.sample_t_s - tt)))
        inside = cv[i] >= 0
        out.append((float(swarm.sample_t_s[i]), transform.ned_to_map(swarm.pos_ned_m[i][inside])))
    return out


def _emulation_section(res: EmulateResult) -> str:
    cfg, rt, en = res.config, res.realtime, res.entries
    lines = [
        "", "## Emulation (MAVLink in the loop)", "",
        f"{cfg.agents} {cfg.personality} autopilot emulators and {cfg.agents} fisc-agent runners talking MAVLink 2 "
        f"over loopback UDP, {cfg.duration_s:.0f} s of real time, exit policy `{cfg.exit_policy}`, "
        f"{cfg.rate_hz:.0f} Hz setpoints, emulators served at {cfg.physics_rate_hz:.0f} Hz (physics step "
        f"{cfg.physics_dt_s} s), {cfg.telemetry} telemetry.  "
        "Fields come from the emulators' true vehicle states (map frame, default deployment transform).", "",
        f"* inlet arrivals: {en['vehicles_entered']} of {cfg.agents} vehicles entered "
        f"({en['entries_total']} entries in all); planned rate {en['planned_rate_per_s']:.2f}/s "
        f"(eq. source_rate, population-scaled: {en['source_rate_per_s']:.2f}/s), realised "
        f"{_fmtv(en['realised_first_entry_rate_per_s'])}/s; arrival error vs plan "
        f"{_fmtv(en['arrival_error_mean_s'])} +- {_fmtv(en['arrival_error_std_s'])} s",
        f"* real time: {'kept' if rt['keeps_real_time'] else 'NOT kept'}; setpoint rate at the autopilots "
        f"{_fmtv(rt['setpoint_rate_mean_hz'])} Hz mean (p5 {_fmtv(rt['setpoint_rate_p5_hz'])} Hz, nominal "
        f"{rt['setpoint_rate_nominal_hz']:.0f} Hz); {_fmtv(rt['cpu_cores_used'])} CPU cores busy, "
        f"{1e3 * rt['cpu_per_agent']:.2f} ms CPU per vehicle-second (all vehicles up: t = {rt['window_s'][0]:.1f}-"
        f"{rt['window_s'][1]:.1f} s)",
    ]
    for name, loops in (("agent", rt["agent_loops"]), ("emulator", rt["emulator_loops"])):
        for i, lp in enumerate(loops):
            lines.append(f"* {name} process {i}: {lp['ticks']} ticks ({lp['tick_rate_ratio']:.3f} of nominal), lag "
                         f"p99 {1e3 * lp['lag_p99_s']:.1f} ms, utilisation {lp['utilisation']:.2f}")
    if res.comparison is not None:
        lines += ["", "### Difference to `fisc-sim run` (same map, duration, agents, mode)", "",
                  "| metric | emulate | run | emulate - run |", "|---|---|---|---|"]
        for k, d in res.comparison["metrics"].items():
            lines.append(f"| {k} | {_fmtv(d['emulate'])} | {_fmtv(d['run'])} | {_fmtv(d['difference'])} |")
        lines += ["", "Swarm field against swarm field (CVs with enough samples in both):", ""]
        for q, d in res.comparison["fields_emulate_vs_run"].items():
            lines.append(f"* {q}: {d['n_cv']} CVs, nRMSE {_fmtv(d['nrmse_emulate_vs_run'])}, Pearson "
                         f"{_fmtv(d['pearson_emulate_vs_run'])}")
        lines += ["", "Full numbers: comparison.json; the reference run's outputs: run_reference/.  Why they differ: "
                  "docs/emulation.md.", ""]
    return "\n".join(lines)


def _fmtv(v) -> str:
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else (
        f"{v:.3f}" if isinstance(v, float) else str(v))


def run(config: EmulateConfig, progress: Callable[[float], None] | None = None) -> EmulateResult:
    """The ``fisc-sim emulate`` job: map, launch plan, fly, fields, outputs (see the module docstring)."""
    from fisc_ground.field_report import json_safe, write_json
    from fisc_ground.field_run import FieldRun, FieldSource
    from sim import report
    from sim.run import PAPER_SNAPSHOT_TIMES_S, RunConfig, RunResult
    from sim.run import run as sim_run

    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    map_path, cmap = prepare_map(config.map, out, config.preset)
    transform = DeploymentTransform(DEFAULT_ORIGIN_NED_M, 0.0)
    cf = CommandField.from_map(cmap)
    plan = launch_plan(cf, config.agents, transform, spacing_m=config.start_spacing_m, gap_m=config.start_gap_m,
                       overhead_s=config.launch_overhead_s if config.launch_overhead_s is not None
                       else LAUNCH_OVERHEAD_S[config.personality], duration_s=config.duration_s)
    swarm = fly_swarm(map_path, plan, config, progress)

    target_cmd = cmap.scale * np.asarray(cmap["target_velocity_m_s"], dtype=float)
    window = sample_window(swarm.sample_t_s, config.duration_s, config.average_window_s)
    fields, cv = ground_truth_fields(swarm, cmap, transform, window, target_cmd)
    n_steps = int(round(config.duration_s * config.rate_hz))
    counters, alive = _counters(swarm.agents, cv[-1], n_steps, sum(a["ticks"] for a in swarm.agents))
    entries = entry_statistics(swarm.agents, plan)
    first_entry = entries["first_entry_s"] if entries["first_entry_s"] is not None else float(plan.arrival_time_s[0])
    rcfg = _run_config(config, map_path)
    t_win = swarm.sample_t_s[window] if window.size else np.array([0.0, 0.0])
    settings = rcfg.flight_settings(cmap)
    fr = FieldRun(source=FieldSource.EMULATION, cmap=cmap, fields=fields, scale=cmap.scale,
                  min_samples=config.min_samples, scenario=rcfg.scenario, mode=settings.mode,
                  snapshots=tuple(_snapshots(swarm, cv, transform, PAPER_SNAPSHOT_TIMES_S, first_entry)))
    rr = RunResult(config=rcfg, field_run=fr, settings=settings, counters=counters, alive=alive,
                   wall_time_s=swarm.duration_s, window_s=(float(np.nanmin(t_win)), float(np.nanmax(t_win))),
                   inflow_rate_per_s=plan.inflow_rate_per_s, collisions=None)
    res = EmulateResult(config=config, run_result=rr, swarm=swarm, plan=plan, entries=entries,
                        realtime=realtime_summary(swarm, config.rate_hz, config.agents,
                                                  steady_start_s(plan, config.duration_s)))
    rr.metrics = report.compute_metrics(rr)
    rr.metrics["emulation"] = json_safe({"entries": entries, "real_time": {
        k: v for k, v in res.realtime.items() if k not in ("agent_loops", "emulator_loops")}})
    res.paths["map"] = map_path
    res.paths["fields"] = report.write_fields_csv(fr, out / "fields.csv")
    res.paths["metrics"] = report.write_metrics_json(rr, out / "metrics.json")
    if config.figures:
        from fisc_ground import field_figures as figures

        rr.paths.update(figures.write_run_figures(fr, out))
        res.paths.update(rr.paths)
    if config.compare:
        # the reference flies the simulator's own step (paper: 0.05 s), whatever the agents' rate
        ref = sim_run(replace(rcfg, out_dir=str(out / "run_reference"), figures=False, dt_s=RunConfig().dt_s))
        res.comparison = compare_fields(rr.metrics, ref.metrics, fields, ref.fields, config.min_samples)
        res.comparison["run_reference"] = {"out_dir": str(out / "run_reference"),
                                           "wall_time_s": ref.wall_time_s, "agents": ref.metrics.get("agents")}
        res.paths["comparison"] = write_json(out / "comparison.json", res.comparison)
    res.paths["emulation"] = write_json(out / "emulation.json", {
        "config": asdict(config), "entries": entries, "real_time": res.realtime,
        "launch_plan": {"start_ned_m": plan.start_ned_m, "start_time_s": plan.start_time_s,
                        "arrival_time_s": plan.arrival_time_s, "inflow_rate_per_s": plan.inflow_rate_per_s,
                        "nominal_rate_per_s": plan.nominal_rate_per_s},
        "agents": swarm.agents})
    rr.paths.update({k: v for k, v in res.paths.items() if k not in rr.paths})
    report_path = report.write_report_md(rr, out / "report.md")
    text = report_path.read_text().replace("# FISC swarm simulation report",
                                           "# FISC emulated swarm report (fisc-sim emulate)", 1)
    report_path.write_text(text + _emulation_section(res))
    res.paths["report"] = report_path
    log.info("emulation written to %s", out)
    return res
