"""The ``fisc-sim run`` job: a scenario on a command map, time-averaged swarm fields, outputs.

``simulate(config, cmap)`` is the computation (no file I/O); ``run(config)`` loads the map,
simulates and writes ``fields.csv``, ``metrics.json``, ``report.md`` and the figures into
``config.out_dir`` (see docs/simulation.md).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from fisc_agent.map.lookup import (
    COMMAND_MODES,
    FACE_MODES,
    PAPER_SETTINGS,
    CommandField,
    FlightSettings,
    map_flight_settings,
)
from fisc_agent.map.codec import MAGIC, CommandMap, load_map
from fisc_agent.common.safe_files import read_head
from fisc_ground.fields.field_report import write_fields_csv
from fisc_ground.fields.field_run import FieldRun, FieldSource
from fisc_ground.monitor.flight_log import FlightLog, LogSettings, SimulatedTelemetry, map_bytes
from fisc_ground.figures.forked import ForkedCall, can_fork
from fisc_ground.fit.scaling import DEFAULT_MAX_SPEED_M_S
from fisc_ground.fields.intervals import honest_statistics, stats_inputs
from fisc_ground.fields.separation_stats import ApproachTracker, ClosestApproach
from fisc_ground.fields.swarm_fields import FieldAccumulator, SwarmFields
from fisc_ground.fields.time_blocks import DEFAULT_BLOCK_S, BlockAccumulator
from fisc_agent.flight.safety_net import DuctAxis
from fisc_agent.map.separation import map_separation
from sim import report
from sim.close_pairs import close_pairs_lister
from sim.collisions import CollisionModel, CollisionParams
from sim.plant.fit import plant_preset
from sim.safety_net import SwarmSafetyNet
from sim.scenarios import Reservoir, StaggeredInlet, scale_for_agents, seed_positions
from sim.moments import swarm_moments
from sim.swarm import MAP_TO_NED, Swarm, SwarmConfig, SwarmCounters

log = logging.getLogger(__name__)

SCENARIOS = ("reservoir", "seed")
#: ``--preset`` values (``RunConfig.preset``).
PRESETS = ("default", "paper")
#: Default population target of a run (the paper's run holds about 10^3 agents; N* as fitted
#: would hold ~6000 on the default map for the same fidelity, see docs/simulation.md).
DEFAULT_AGENTS = 1000
#: Agent speed limit [m/s] for the maps a run fits itself (no ``--map``, or a reference spec).
#: The paper's speed regime: it flew S = 0.1 on 22.4 m/s peaks, i.e. ~2.2 m/s peak commands.
#: With the plant's ~0.58 s lag the lag distance u tau is then ~1.2 m (about 2 CVs) instead of
#: ~2.9 m at 5 m/s, which halves the velocity error (docs/studies/fidelity.md, "Fidelity").
SIM_MAX_SPEED_M_S = DEFAULT_MAX_SPEED_M_S
#: Case 2 simulated time [s]: the paper's run.
RESERVOIR_DURATION_S = 300.0
#: Case 2 averaging window [s]: the last 260 s of the 300, i.e. from t = 40 s, 10 s after the swarm is
#: steady (seed 0, agents in the CVs over 10 s windows: 631 at 20 s, 846 at 30 s, then 831-908 without
#: a trend up to 400 s; docs/studies/fidelity.md, "The averaging window").  The min-max normalised density and
#: pressure are set by their extreme CVs, so the per-CV sampling noise (~0.055 of the mean density per
#: CV at 100 s, 1000 agents) moves them from seed to seed: on the default map, seeds 0-9, the density
#: nRMSE was 0.206-0.260 averaged over the last 200 s and 0.207-0.229 over the last 260 s; the paper
#: preset's figures do not move.
RESERVOIR_WINDOW_S = 260.0
#: Most steps ``simulate`` flies in one ``Swarm.step`` call when nothing happens between them (no batch
#: entering, no sample, no evaluation): the fused kernel then loops over them itself.
MAX_QUIET_STEPS = 16
#: Paper fig. 4 snapshot times [s].
PAPER_SNAPSHOT_TIMES_S = (0.5, 6.0, 10.0, 15.0)


@dataclass(frozen=True)
class RunConfig:
    """Everything one ``fisc-sim run`` needs (recorded in metrics.json)."""

    map: str | None = None
    """Command map: a ``.fiscmap`` path, a reference spec (built-in name such as ``cd_nozzle``, or
    a CFD file) to fit on the fly, or None for the embedded default map."""
    scenario: str = "reservoir"
    """``reservoir`` (paper Case 2) or ``seed`` (paper Case 1)."""
    agents: int | None = DEFAULT_AGENTS
    """Population target N: N* is scaled by N / sum N* (seed: exactly N agents seeded;
    reservoir: the source rate is scaled so a swarm keeping the seeded density holds ~N).  None: N* as fitted.
    Default ``DEFAULT_AGENTS`` = 1000, the paper's population."""
    duration_s: float | None = None
    """Simulated time [s]; None: ``RESERVOIR_DURATION_S`` (300 s, the paper's run) for the reservoir, 20 s for seeding
    (a seeded swarm has flown through the 15 m tunnel by then)."""
    average_window_s: float | None = None
    """The swarm fields are time-averaged over the last this many seconds [s]; None:
    ``RESERVOIR_WINDOW_S`` (260 s) for the reservoir (steady state), the whole run for seeding (a transient)."""
    sample_interval_s: float | None = None
    """Interval between the time samples of the average [s] (a multiple of dt is used); None: 0.2 s
    for the reservoir (1300 samples over its 260 s window: an agent stays ~0.3-1 s in a CV, so samples 0.1 s apart
    are strongly correlated; measured over a 100 s window: 0.2 s gave the figures of 0.1 s within
    0.003), 0.1 s for seeding (a 20 s transient)."""
    preset: str = "default"
    """``default``: fit a schema-2 map (staggered field, designed density) and fly its recommended
    flight settings; ``paper``: the paper's Algorithm 1 (schema-1 map, mean commands, no look-ahead)."""
    mode: str | None = None
    """Command mode (``fisc_agent.map.lookup.COMMAND_MODES``); None: the map's recommended mode (the
    preset's)."""
    collisions: bool = False
    """Enable the paper's collision layer (sim.collisions)."""
    collision_radius_m: float = 0.1
    """Agent radius r of the collision layer [m] (collision when closer than 2 r)."""
    safety_net: bool = False
    """Fly the agents' separation safety net (``fisc_agent.flight.safety_net``, default settings, the map's
    d_min) between the flow law's command and the plant, every agent hearing every other at once
    (``sim.safety_net``); metrics.json then reports ``safety_net_acting_fraction``.  The paper companion
    flies without it."""
    staggered_admission: bool = False
    """Case 2: admit one agent every ``admission_period_s`` of the map (the agents' own admission,
    ``sim.scenarios.StaggeredInlet``) instead of the eq. source_rate batches; ``agents`` then does not set
    the inflow.  The map must record its admission budget (``fisc-ground inspect``)."""
    seed: int = 0
    """Random seed (positions of seeded and injected agents)."""
    scale: float | None = None
    """Override of the map's speed scale S (the paper flew S = 0.1); None: the map's S."""
    max_speed_m_s: float = SIM_MAX_SPEED_M_S
    """Agent speed limit [m/s] that sets S when the run fits its map itself (no map given, or a
    reference spec); a ``.fiscmap`` file keeps its own S.  Default ``SIM_MAX_SPEED_M_S``."""
    x_axial_m: float = math.inf
    """Case 1: seed the CVs with centre x <= this [m] (inf: the full tunnel)."""
    source_interval_s: float = 0.2
    """Case 2: interval between reservoir batches, dt_source [s] (each batch is spread over the
    distance its agents would have flown in the interval, so the inflow is effectively continuous)."""
    dt_s: float = 0.05
    """Time step of Algorithm 1 [s]."""
    escape_grace_s: float = 5.0
    """Return policy: longest time outside every CV before an agent counts as escaped [s]."""
    lookahead_s: float | None = None
    """Command look-ahead t_lead [s] (``SwarmConfig.lookahead_s``): agents fly the command at
    x + u t_lead to compensate the plant lag; 0 = the paper's Algorithm 1; None: the map's
    recommended value (the preset's)."""
    persistence_s: float | None = None
    """Mode ``kinetic``: how long an agent keeps one deviation direction [s]; None: the map's
    recommended value (the preset's), as ``fisc-agent`` flies it."""
    min_samples: int = 10
    """CVs with fewer agent samples in the window are left out of the metrics."""
    separation_interval_s: float = 5.0
    """Interval between the closest-approach evaluations over the agents in the tunnel [s] (a multiple
    of dt; each costs ~1 ms at 10^3 agents, most of it listing the ~10^4 pairs closer than d_min (numba's
    cell grid, ``sim.close_pairs``; twice that by the KD-tree), so every 5 s (61 evaluations of the 300 s
    run) keeps the main job within a few % of its time).
    Near-misses are the pairs closer than the map's d_min at an evaluation that were not at the one before."""
    block_s: float = DEFAULT_BLOCK_S
    """Length of the time blocks of the bootstrap intervals [s] (``fisc_ground.fields.time_blocks``)."""
    snapshot_times_s: tuple[float, ...] = PAPER_SNAPSHOT_TIMES_S
    """Times of the XZ swarm snapshots (paper fig. 4) [s]; times beyond the run are skipped."""
    figures: bool = True
    """Write the PNG figures."""
    compare_paper: bool = True
    """``run`` (not ``simulate``) also flies the paper's preset on the same reference, for report.md and
    the figures side by side (skipped when this run is the paper preset itself)."""
    plant: str = "paper"
    """Vehicle model: a named ``sim.plant.fit.PLANT_PRESETS`` entry (``paper``: the paper's nominal
    quadrotor; ``px4-sih``: fitted to real PX4 SITL flights)."""
    out_dir: str = "out/run"
    """Output directory."""
    mcap: str | None = None
    """Also write the run as a Foxglove/MCAP flight log to this path (``fisc_ground.monitor.flight_log``: the
    channels of ``fisc-ground monitor --record``, one fleet sample every ``sample_interval_s``); None: no log."""

    def __post_init__(self) -> None:
        if self.scenario not in SCENARIOS:
            raise ValueError(f"scenario {self.scenario!r}: choose one of {', '.join(SCENARIOS)}")
        if self.staggered_admission and self.scenario != "reservoir":
            raise ValueError("staggered_admission is an inflow of the reservoir scenario, not of seeding")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ValueError(f"duration_s must be > 0, got {self.duration_s!r}")
        if self.average_window_s is not None and not self.average_window_s > 0:
            raise ValueError(f"average_window_s must be > 0, got {self.average_window_s!r}")
        if self.agents is not None and self.agents < 0:
            raise ValueError(f"agents must be >= 0, got {self.agents!r}")
        if self.scale is not None and not self.scale > 0:
            raise ValueError(f"scale must be > 0, got {self.scale!r}")
        if not (self.max_speed_m_s > 0 and math.isfinite(self.max_speed_m_s)):
            raise ValueError(f"max_speed_m_s must be finite and > 0, got {self.max_speed_m_s!r}")
        if self.preset not in PRESETS:
            raise ValueError(f"preset {self.preset!r}: choose one of {', '.join(PRESETS)}")
        if self.mode is not None and self.mode not in COMMAND_MODES:
            raise ValueError(f"mode {self.mode!r}: choose one of {', '.join(COMMAND_MODES)}")
        if self.lookahead_s is not None and not (self.lookahead_s >= 0 and math.isfinite(self.lookahead_s)):
            raise ValueError(f"lookahead_s must be finite and >= 0, got {self.lookahead_s!r}")
        if self.sample_interval_s is not None and not self.sample_interval_s > 0:
            raise ValueError(f"sample_interval_s must be > 0, got {self.sample_interval_s!r}")
        if not (self.separation_interval_s > 0 and math.isfinite(self.separation_interval_s)):
            raise ValueError(f"separation_interval_s must be finite and > 0, got {self.separation_interval_s!r}")
        if not (self.block_s > 0 and math.isfinite(self.block_s)):
            raise ValueError(f"block_s must be finite and > 0, got {self.block_s!r}")

    def flight_settings(self, cmap: CommandMap) -> FlightSettings:
        """The settings flown on ``cmap``: explicit mode/look-ahead, else the preset's (paper) or the
        map's recommended ones (``fisc_agent.map.lookup.map_flight_settings``)."""
        base = PAPER_SETTINGS if self.preset == "paper" else map_flight_settings(cmap)
        return FlightSettings(base.mode if self.mode is None else self.mode,
                              base.lookahead_s if self.lookahead_s is None else float(self.lookahead_s),
                              base.persistence_s if self.persistence_s is None else float(self.persistence_s))

    def as_dict(self) -> dict:
        """JSON-ready dict of the configuration (inf -> "inf"; defaults of duration and window applied)."""
        out = {}
        for k, v in asdict(self).items():
            if isinstance(v, float) and not math.isfinite(v):
                v = str(v)
            out[k] = list(v) if isinstance(v, tuple) else v
        out["duration_s"], out["average_window_s"] = self.duration, self.window
        out["sample_interval_s"] = self.sample_interval
        return out

    @property
    def duration(self) -> float:
        """Simulated time with the scenario default applied [s]."""
        if self.duration_s is not None:
            return float(self.duration_s)
        return RESERVOIR_DURATION_S if self.scenario == "reservoir" else 20.0

    @property
    def sample_interval(self) -> float:
        """Sampling interval with the scenario default applied [s]."""
        if self.sample_interval_s is not None:
            return float(self.sample_interval_s)
        return 0.2 if self.scenario == "reservoir" else 0.1

    @property
    def window(self) -> float:
        """Averaging window with the scenario default applied [s] (at most the run)."""
        if self.average_window_s is not None:
            return min(float(self.average_window_s), self.duration)
        return min(RESERVOIR_WINDOW_S, self.duration) if self.scenario == "reservoir" else self.duration


@dataclass
class RunResult:
    """Outcome of a simulation (``simulate``) and, after ``run``, where its outputs are."""

    config: RunConfig
    """The configuration."""
    field_run: FieldRun
    """The swarm-field estimate (map, time-averaged fields, snapshots): what every FISC run produces."""
    settings: FlightSettings
    """The flight settings flown (mode, look-ahead, persistence)."""
    counters: SwarmCounters
    """Agent bookkeeping (injected / exited / escaped ...)."""
    alive: int
    """Agents alive at the end."""
    wall_time_s: float
    """Wall time of the stepping loop (excludes map loading and output) [s]."""
    window_s: tuple[float, float]
    """Start and end of the averaging window [s]."""
    inflow_rate_per_s: float | None
    """Case 2: nominal source rate of eq. source_rate summed over the inlet [agents/s]."""
    collisions: dict | None
    """Collision statistics (counts by type) when the collision layer was on."""
    safety_net: dict | None = None
    """What the safety net did (``sim.safety_net.SafetyNetCounts.as_dict``) when it was on."""
    metrics: dict = field(default_factory=dict)
    """metrics.json content (filled by ``sim.report.compute_metrics``)."""
    paths: dict[str, Path] = field(default_factory=dict)
    """Written outputs by name."""
    paper: "RunResult | None" = None
    """``run``: the companion run of the paper's preset (``RunConfig.compare_paper``), else None."""
    approach: ClosestApproach | None = None
    """Closest approach and near-misses of the agents in the tunnel (every ``separation_interval_s``)."""

    @property
    def cmap(self) -> CommandMap:
        """The command map flown."""
        return self.field_run.cmap

    @property
    def fields(self) -> SwarmFields:
        """Time-averaged swarm fields per CV over the averaging window."""
        return self.field_run.fields

    @property
    def scale(self) -> float:
        """The speed scale S actually used."""
        return self.field_run.scale

    @property
    def target_command_m_s(self) -> np.ndarray:
        """(n_cv, 3) S * CFD target velocity: the reference of the dispersion pressure [m/s]."""
        return self.field_run.target_command_m_s


def load_command_map(spec: str | None, max_speed_m_s: float | None = None, preset: str = "default") -> CommandMap:
    """The map of ``RunConfig.map``: default, a .fiscmap file, or a reference to fit now.

    ``max_speed_m_s``: speed limit that sets S of a map fitted here (the default reference, or a
    reference spec); None: the map builder's default (``FitConfig.max_speed_m_s``).  A
    ``.fiscmap`` file is loaded as it is.  ``preset`` ``paper`` fits the paper's schema-1 map.
    """
    from fisc_ground.maps.build import FitConfig

    kw = {} if max_speed_m_s is None else {"max_speed_m_s": float(max_speed_m_s)}
    fit = FitConfig(staggered=preset != "paper", **kw)
    if spec is None:
        from fisc_ground.maps.build import build_default_map

        return build_default_map(fit)
    p = Path(spec)
    if p.suffix == ".fiscmap" or (p.is_file() and read_head(p, 8, what="map or reference file") == MAGIC):
        return load_map(p)
    from fisc_ground.maps.build import build_map_from_reference

    return build_map_from_reference(spec, fit)


def simulate(config: RunConfig, cmap: CommandMap,
             progress: Callable[[float], None] | None = None, telemetry: SimulatedTelemetry | None = None,
             measures: bool = True) -> RunResult:
    """Run the scenario on ``cmap`` and time-average the swarm fields (no file output).

    ``measures``: also track the closest approach and bootstrap the figures' intervals (``False`` for the
    paper companion, whose figures only stand beside the run's).

    ``progress(fraction_done)`` is called now and then (for a progress bar).  ``telemetry``: every
    ``sample_interval_s`` of the whole run, the fleet is also sent there as agent telemetry (state
    FLOW inside a CV, RETURN outside; the run's clock as receive time).
    """
    scale = cmap.scale if config.scale is None else float(config.scale)
    cf = CommandField.from_map(cmap, scale=scale)
    target_cmd = scale * np.asarray(cmap["target_velocity_m_s"], dtype=float)
    collider = None
    if config.collisions:
        collider = CollisionModel(CollisionParams(radius_m=config.collision_radius_m,
                                                  v_max_m_s=float(cmap.body.get("max_speed_m_s", 5.0)) * 1.5),
                                  cf.cell_size_m)
    d_min_m = map_separation(cmap.body).d_min_m
    plant = plant_preset(config.plant)
    x_lo = float(cf.origin_m[0])
    net = (SwarmSafetyNet(d_min_m, lag_s=float(np.max(plant.tau_v_s)),
                          duct=DuctAxis(x_lo, x_lo + cf.grid_cv.shape[0] * float(cf.cell_size_m)))
           if config.safety_net else None)
    settings = config.flight_settings(cmap)
    if settings.mode in FACE_MODES and cf.face_u_m_s is None:
        raise ValueError(f"mode {settings.mode!r} needs a schema-2 map with the staggered face field; "
                         f"this map is schema {cmap.schema_version} (refit it with fisc-ground fit)")
    swarm = Swarm(cf, plant, SwarmConfig(dt_s=config.dt_s, mode=settings.mode,
                                                 escape_grace_s=config.escape_grace_s,
                                                 lookahead_s=settings.lookahead_s,
                                                 persistence_s=settings.persistence_s),
                  collider=collider, command_filter=net)
    rng = np.random.default_rng(config.seed)
    reservoir = None
    if config.scenario == "seed":
        swarm.add_agents(seed_positions(cf, rng, config.x_axial_m, config.agents))
    else:
        reservoir = _inflow(config, cf, cmap, settings)
    acc = FieldAccumulator(cf.n_cv, cf.cell_size_m ** 3)
    blocks = BlockAccumulator(cf.n_cv, config.block_s)
    approach = ApproachTracker(d_min_m, close_pairs_lister())  # numba's cell grid: the KD-tree's pairs
    mass = float(cmap.body.get("agent_mass_kg", 1.0))
    n_steps = max(1, int(round(config.duration / config.dt_s)))
    window = min(config.window, n_steps * config.dt_s)
    first_sample = n_steps - int(round(window / config.dt_s))
    every = max(1, int(round(config.sample_interval / config.dt_s)))
    sep_every = max(1, int(round(config.separation_interval_s / config.dt_s)))
    snap_steps = {int(round(t / config.dt_s)): t for t in config.snapshot_times_s if t <= n_steps * config.dt_s}
    snapshots: list[tuple[float, np.ndarray]] = []
    report_every = max(1, n_steps // 200)

    def busy(j: int, t_s: float) -> bool:
        """Whether the loop has something to do at step ``j`` (at time ``t_s``) before stepping it."""
        return (j == n_steps or j in snap_steps or (j > first_sample and (n_steps - j) % every == 0)
                or (measures and (n_steps - j) % sep_every == 0)
                or (telemetry is not None and (n_steps - j) % every == 0)
                or (reservoir is not None and reservoir.is_due(t_s)))

    t0 = time.perf_counter()
    k = 0
    while True:
        if reservoir is not None and k < n_steps:
            for _ in range(reservoir.due(swarm.t_s)):
                pos, ids = reservoir.entering(rng, swarm.next_id, swarm.t_s)
                swarm.add_agents(pos, ids=ids)
        if k in snap_steps:
            swarm.assign()
            snapshots.append((snap_steps[k], swarm.pos_m.copy()))
        if k > first_sample and (n_steps - k) % every == 0:
            cv = swarm.assign()
            mom = swarm_moments(cv, swarm.vel_ned_m_s, MAP_TO_NED, mass, cf.n_cv, target_cmd)
            acc.add_moments(mom)
            blocks.add_moments(k * config.dt_s, mom)
        if measures and (n_steps - k) % sep_every == 0:
            inside = swarm.assign() >= 0
            approach.add(k * config.dt_s, swarm.ids[inside], swarm.pos_m[inside])
        if telemetry is not None and (n_steps - k) % every == 0:
            cv = swarm.assign()
            telemetry.sample(k * config.dt_s, swarm.ids, swarm.pos_m, swarm.velocity_map(),
                             np.where(cv >= 0, "FLOW", "RETURN"), cv)
        if k == n_steps:
            break
        # the steps up to the next one with something to do, in one call (one kernel call where it applies)
        m, t_s = 1, swarm.t_s + config.dt_s
        while m < MAX_QUIET_STEPS and not (progress is not None and (k + m - 1) % report_every == 0) \
                and not busy(k + m, t_s):
            m, t_s = m + 1, t_s + config.dt_s
        swarm.step(m)
        k += m
        if progress is not None and (k - 1) % report_every == 0:
            progress((k - 1) / n_steps)
    wall = time.perf_counter() - t0
    if progress is not None:
        progress(1.0)
    stats = honest_statistics(blocks.sums(), stats_inputs(cmap, config.min_samples),
                              blocks.last_t_s - blocks.first_t_s + every * config.dt_s, seed=config.seed) \
        if measures else None
    fr = FieldRun(source=FieldSource.SIMULATION, cmap=cmap, fields=acc.result(), scale=scale,
                  min_samples=config.min_samples, scenario=config.scenario, mode=settings.mode,
                  collisions=config.collisions, snapshots=tuple(snapshots), statistics=stats)
    return RunResult(
        config=config, field_run=fr, settings=settings, counters=swarm.counters, alive=swarm.n, wall_time_s=wall,
        window_s=(first_sample * config.dt_s, n_steps * config.dt_s),
        inflow_rate_per_s=None if reservoir is None else reservoir.rate_per_s,
        collisions=None if collider is None else collider.stats.as_dict(),
        safety_net=None if net is None else net.counts.as_dict(),
        approach=approach.result() if measures else None)


def _inflow(config: RunConfig, cf: CommandField, cmap: CommandMap,
            settings: FlightSettings) -> Reservoir | StaggeredInlet:
    """Case 2's inflow: the paper's reservoir, or one agent per the map's admission period."""
    if not config.staggered_admission:
        return Reservoir(cf, config.source_interval_s, scale_for_agents(cf, config.agents),
                         settings.persistence_s if settings.mode == "kinetic" else None)
    period = map_separation(cmap.body).admission_period_s
    if period is None:
        raise ValueError("--staggered-admission: the map records no separation.admission_period_s (refit it with "
                         "fisc-ground fit)")
    return StaggeredInlet(cf, period)


def paper_companion(config: RunConfig, cmap: CommandMap) -> RunResult:
    """The ``--preset paper`` run beside a run of ``config`` on ``cmap`` (its map, if a map file was
    given; else the paper's schema-1 fit of the same reference), with its metrics."""
    pcfg = replace(config, preset="paper", mode=None, lookahead_s=None, safety_net=False)
    pmap = cmap if config.map is not None and Path(config.map).suffix == ".fiscmap" else \
        load_command_map(config.map, config.max_speed_m_s, "paper")
    paper = simulate(pcfg, pmap, measures=False)
    paper.metrics = report.compute_metrics(paper)
    return paper


def run(config: RunConfig, progress: Callable[[float], None] | None = None) -> RunResult:
    """The ``fisc-sim run`` job: load the map, simulate, write all outputs into ``config.out_dir``.

    The paper companion (``paper_companion``) flies in a forked process beside the main run where
    that is possible (``fisc_ground.figures.forked``), else after it; the results are the same."""
    cmap = load_command_map(config.map, config.max_speed_m_s, config.preset)
    settings_are_paper = config.preset == "paper" or config.flight_settings(cmap) == PAPER_SETTINGS
    companion = config.compare_paper and not settings_are_paper
    beside = ForkedCall(paper_companion, config, cmap, name="fisc-paper-companion") \
        if companion and can_fork() else None
    telemetry = None
    try:
        if config.mcap is not None:
            telemetry = SimulatedTelemetry(FlightLog(LogSettings(sample_period_s=config.sample_interval,
                                                                 stale_after_s=1.5 * config.sample_interval,
                                                                 source="fisc-sim run"), mcap_path=config.mcap),
                                           cmap, map_bytes(cmap))
        result = simulate(config, cmap, None if progress is None else (lambda f: progress(0.85 * f)), telemetry)
    except BaseException:
        if beside is not None:
            beside.cancel()
        raise
    finally:
        if telemetry is not None:
            telemetry.close()
    if telemetry is not None:
        result.paths["mcap"] = Path(config.mcap)
    if companion:
        paper = beside.result() if beside is not None else paper_companion(config, cmap)
        result.paper = paper
        result.field_run = replace(result.field_run, companion=paper.field_run)
    if progress is not None:
        progress(0.9)
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result.metrics = report.compute_metrics(result)
    result.paths["fields"] = write_fields_csv(result.field_run, out / "fields.csv")
    result.paths["metrics"] = report.write_metrics_json(result, out / "metrics.json")
    if config.figures:
        from fisc_ground.figures import field_figures as figures

        result.paths.update(figures.write_run_figures(result.field_run, out))
    result.paths["report"] = report.write_report_md(result, out / "report.md")
    if progress is not None:
        progress(1.0)
    log.info("run written to %s", out)
    return result
