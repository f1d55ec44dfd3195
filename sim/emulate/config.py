"""Configuration of ``fisc-sim emulate`` (``EmulateConfig``) and its constants."""

from __future__ import annotations

import math
import os
from types import SimpleNamespace
from dataclasses import dataclass


from fisc_agent.config import EXIT_POLICIES, GEOFENCE_POLICIES
from fisc_agent.map.lookup import COMMAND_MODES
from sim.plant.fit import PLANT_PRESETS
from sim.plant.px4_loop import PX4_LOOP_PLANT

PERSONALITIES = ("px4", "ardupilot")
PLANTS = (*PLANT_PRESETS, PX4_LOOP_PLANT)
"""The emulators' vehicle models (``--plant``): the velocity plant's presets and stock PX4's loop."""
MAP_FILE_NAME = "map.fiscmap"
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
    duration_s: float = 120.0
    """Real (wall-clock) time flown, from the launch of the first vehicle [s].  The first vehicle
    reaches the inlet after ~11 s and the looping swarm takes another ~30 s to settle, so the default
    leaves a steady minute to average (``average_window_s``)."""
    mode: str | None = None
    """Command mode of the agents (``fisc_agent.map.lookup.COMMAND_MODES``); None: the map's recommended one."""
    lookahead_s: float | None = None
    """Command look-ahead of the agents [s]; None: the map's recommended value."""
    preset: str = "default"
    """``default`` (schema-2 map, its recommended settings) or ``paper`` (schema-1 map, Algorithm 1)."""
    personality: str = "px4"
    """Autopilot emulated: ``px4`` or ``ardupilot``."""
    exit_policy: str = "loop"
    """Agent exit policy after the outlet: ``loop`` (back to the inlet, keeps feeding), ``hold``, ``land``."""
    tracking: bool = True
    """Agents track their streamline (``fisc_agent.flight.tracking``), as ``fisc-agent`` does by default on a
    real vehicle; False: gain 0, the agents fly ``fisc_agent.map.lookup.flight_command`` at their position,
    the very command function of ``fisc-sim run`` (a like-for-like check of the command chain)."""
    safety_net: bool = False
    """The agents fly the separation safety net (``fisc_agent.flight.safety_net``), hearing each other over
    Zenoh (needs ``swarm``), as ``fisc-agent --swarm`` does by default on a real vehicle.  False: the paper's
    law alone, as ``fisc-sim run`` flies by default, so the two compare like for like."""
    fleet_mode: bool = False
    """The agents resolve the map's recommended mode themselves, as ``fisc-agent`` does on a real fleet: under
    streamline tracking a recommended ``kinetic`` is flown on the ``staggered`` field, without its deviations
    (``fisc_agent.flight.point_command.tracked_mode``), and a ``--mode kinetic`` given turns its deviations
    within fisc-agent's margin of the map's real wall (``AgentConfig.wall_margin_m``).  False: the
    recommendation is given to them explicitly, so that they fly its deviations, reflected at the CV staircase
    as ``fisc-sim run``'s agents do.  A prediction of a real
    fleet's flight needs True (an eight-PX4 loop flew the staggered field near the axis, parcels 0.22 m from
    it; its emulation with the deviations put them 0.78 m out and 200 times across the CVs' side)."""
    staggered_admission: bool = False
    """The agents admit themselves into the tunnel from the map's admission budget (each in its entry window,
    ``AgentConfig.entry_stagger_s`` None: the map's admission period), as ``fisc-agent`` does by default on a
    real vehicle, first passes and laps alike.  False: ``entry_stagger_s`` 0, the launches staggered at the
    paper's source rate (``sim.emulate.plan``), as ``fisc-sim run``'s reservoir injects, so the two compare;
    at eight vehicles that rate (one per 2.8 s) is above the default map's budget (one per 4.2 s)."""
    entry_radius_fraction: float = 1.0
    """Fraction of the inlet radius the agents' entry points spread over (``AgentConfig.entry_radius_fraction``;
    a real deployment keeps 0.6 clear of the duct's wall).  1: evenly over every inlet CV, as ``fisc-sim
    run``'s reservoir injects; at 0.6 the outer inlet CVs are seldom entered (docs/emulation.md)."""
    geofence: str | None = None
    """Agents leaving the CVs (sideways, or upstream through the inlet): ``return`` (fly back to the nearest CV,
    as the simulator's return policy; the kinetic mode's deviations reach the staircase walls) or ``hold``.
    None: fisc-agent's own default (``hold``, ``AgentConfig.geofence``) with ``fleet_mode``, else ``return``
    (``agent_geofence``)."""
    rate_hz: float = 20.0
    """Agent setpoint (control loop) rate [Hz]."""
    position_rate_hz: float = 20.0
    """LOCAL_POSITION_NED rate the agents request from their autopilot [Hz]."""
    physics_rate_hz: float = 50.0
    """Emulator service rate: receive, advance the physics, send due telemetry [Hz]."""
    physics_dt_s: float = 0.02
    """Physics step of the emulated vehicles [s] (the emulator's default; 0.05 = the simulator's dt)."""
    plant: str = "paper"
    """Vehicle model inside the emulators: a named ``sim.plant.fit.PLANT_PRESETS`` entry, or ``px4-sih-loop``
    (stock PX4's velocity loop on SIH's quadrotor, ``sim.plant.px4_loop``; PX4 personality only)."""
    estimate_error: bool = False
    """Each emulated autopilot's state estimate strays from the truth as stock PX4's on SIH does
    (``sim.autopilot.estimate_error.PX4_SIH_ESTIMATE_ERROR``, seeded by ``seed`` and the vehicle's id): it flies
    and reports the estimate, its GNSS receiver the truth.  The fields, profile and closest approach are then
    taken from what the autopilots report, as a ground station sees a real fleet (the monitor scores the
    agents' published estimates).  False: the estimate is the truth."""
    telemetry: str = "full"
    """``full``: the autopilots' default streams; ``lean``: the agents switch every stream but HEARTBEAT
    and LOCAL_POSITION_NED off (MAV_CMD_SET_MESSAGE_INTERVAL), as a companion on a busy link would."""
    average_window_s: float = 60.0
    """Fields are time-averaged over the last this many seconds of the run (as ``fisc-sim run``) [s]."""
    sample_interval_s: float = 0.1
    """Interval between ground-truth samples of the average (``fisc-sim run``'s default) [s]."""
    min_samples: int = 10
    """CVs with fewer agent samples in the window are left out of the metrics."""
    start_spacing_m: float = 1.0
    """Spacing of the ground start grid [m] (with ``staggered_admission`` the joins also wait for their
    windows above their launch points, this far apart: a real fleet's spacing, e.g. the 3 m of the
    real-swarm tests' SITL, keeps them clear of d_min)."""
    start_gap_m: float = 3.0
    """Distance of the first start row upstream of the staging plane [m]."""
    launch_overhead_s: float | None = None
    """Predicted time from mission start to the end of the climb-out (HEARTBEAT discovery, arming,
    OFFBOARD/GUIDED, takeoff) [s], used to stagger the launches so that arrivals at the inlet follow
    the source rate; None: measured default of the personality (``LAUNCH_OVERHEAD_S``)."""
    emulator_workers: int = 0
    """Processes hosting the emulators (0: automatic, 1 per 200 vehicles, at most one per CPU)."""
    agent_workers: int = 0
    """Processes hosting the agents (0: automatic, 1 per 200 vehicles, at most one per CPU)."""
    compare: bool = True
    """Also run ``fisc-sim run`` (vectorised) on the same map/duration/mode and write comparison.json: at the
    population that flies as many agents in the tunnel as the emulation flew vehicles
    (``sim.emulate.analysis.matched_population``), and at the launched population ``agents``."""
    figures: bool = True
    """Write the PNG figures."""
    seed: int = 0
    """Seed of the comparison run (the emulated run itself is deterministic up to OS scheduling)."""
    reference_seeds: int = 5
    """``fisc-sim run`` references flown for the comparison (seeds ``seed``, ``seed + 1``, ...): its run
    values are their mean, with their standard deviation (at 50 agents one run's pressure nRMSE varies
    by about 0.03 from seed to seed, as much as the difference being measured); the first one's
    outputs are written to ``run_reference/``."""
    worker_log_level: str = "WARNING"
    """Log level inside the worker processes (agents log every mission transition at INFO)."""
    swarm: str | None = None
    """Zenoh swarm name: when set, every agent publishes its telemetry on
    ``<prefix>/<swarm>/agents/<id>/telemetry`` as a deployed fleet does, so ``fisc-ground monitor``
    and ``status`` can watch the emulated swarm; None: no Zenoh."""
    zenoh_config: str | None = None
    """Standard Zenoh JSON5 config file for the agents' session (None: the lab default, peer mode on
    loopback, listening on ``tcp/127.0.0.1:7447`` if free, else connecting to it)."""
    zenoh_prefix: str = "fisc"
    """Zenoh key-expression prefix."""
    telemetry_rate_hz: float = 5.0
    """Zenoh telemetry rate per agent [Hz] (with ``swarm``)."""
    trusted_key: str | None = None
    """Ground Ed25519 public key (.pub) the agents trust for maps and fleet commands over Zenoh
    (required with ``swarm``, as on a real fleet)."""
    flight_logs: str | None = None
    """Directory for each emulated agent's own flight log, ``agent_<id>.csv`` (the CSV of ``fisc-agent
    --flight-log``: state, reported position and velocity, setpoint, CV, tracking parcel per tick);
    None: none."""
    mcap: str | None = None
    """Also write the flight as a Foxglove/MCAP flight log to this path: the emulators' true states
    (map frame) and the agents' mission states as telemetry, one fleet sample every
    ``sample_interval_s``, with the channels of ``fisc-ground monitor --record``; None: no log."""

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
        need(self.plant in PLANTS, f"plant {self.plant!r}: choose one of {', '.join(PLANTS)}")
        need(self.plant != PX4_LOOP_PLANT or self.personality == "px4",
             f"plant {PX4_LOOP_PLANT} is PX4's velocity loop: it needs the px4 personality")
        need(not self.estimate_error or self.personality == "px4",
             "estimate_error is stock PX4's, measured on SIH: it needs the px4 personality")
        need(self.exit_policy in EXIT_POLICIES, f"exit_policy {self.exit_policy!r}: choose one of {EXIT_POLICIES}")
        need(isinstance(self.reference_seeds, int) and self.reference_seeds >= 1,
             f"reference_seeds must be >= 1, is {self.reference_seeds!r}")
        need(0.0 < self.entry_radius_fraction <= 1.0,
             f"entry_radius_fraction must be in (0, 1], is {self.entry_radius_fraction!r}")
        need(self.geofence is None or self.geofence in GEOFENCE_POLICIES,
             f"geofence {self.geofence!r}: choose one of {GEOFENCE_POLICIES}")
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
        need(not self.safety_net or self.swarm is not None,
             "the safety net hears the other agents over Zenoh: safety_net / --safety-net needs swarm / --swarm")
        need(self.swarm is None or self.trusted_key is not None,
             "a Zenoh swarm needs the ground's public key (trusted_key / --trusted-key) for maps and commands")

    def agent_settings(self, recommended_mode: str | None = None) -> "SimpleNamespace":
        """``mode`` and ``lookahead_s`` the agents are started with (None: the map's recommended;
        ``paper`` preset: mean, no look-ahead unless given).  ``recommended_mode``: the map's
        recommended mode, given to the agents explicitly when no mode is set, so that they fly a
        ``kinetic`` recommendation's deviations (under streamline tracking on the tracking parcel) as
        ``fisc-sim run``'s agents do (emulated ducts have no physical wall; a real, tracking agent
        flies that recommendation as ``staggered`` unless told), and not given with ``fleet_mode``."""
        paper = self.preset == "paper"
        mode = self.mode if self.mode is not None else (
            "mean" if paper else None if self.fleet_mode else recommended_mode)
        return SimpleNamespace(mode=mode,
                               lookahead_s=self.lookahead_s if self.lookahead_s is not None or not paper else 0.0)

    def agent_geofence(self) -> str:
        """The geofence policy the agents fly: ``geofence`` if given, else fisc-agent's default with
        ``fleet_mode`` (a real fleet holds a vehicle that leaves the map) and ``return`` without it."""
        if self.geofence is not None:
            return self.geofence
        from fisc_agent.config import AgentConfig

        return AgentConfig.geofence.value if self.fleet_mode else "return"

    def workers(self) -> tuple[int, int]:
        """(emulator processes, agent processes) actually used.  Automatic: one emulator process
        and one agent process per 200 vehicles (since the fast MAVLink codec an emulator costs about
        what an agent costs), at most one per CPU."""
        ncpu = os.cpu_count() or 1
        emu = self.emulator_workers or min(ncpu, max(1, math.ceil(self.agents / 200)))
        agent = self.agent_workers or min(ncpu, max(1, math.ceil(self.agents / 200)))
        return emu, agent
