"""The ``fisc-sim emulate`` job: map, plan, flight, analysis, then fields.csv, metrics.json, figures,
emulation.json, comparison.json, report.md (and the MCAP flight log)."""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, replace
from dataclasses import field as dataclass_field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from fisc_agent.flight.frames import DEFAULT_ORIGIN_NED_M, DeploymentTransform
from fisc_agent.flight.point_command import tracked_mode
from fisc_agent.map.wall import WALL_ARRAY
from fisc_agent.map.lookup import CommandField, map_flight_settings
from fisc_agent.map.codec import CommandMap
from fisc_agent.map.separation import map_separation
from sim.emulate.analysis import (compare_fields, emulated_approach, emulated_statistics, entry_statistics,
                                  flowing_vehicles, ground_truth_fields,
                                  matched_population, position_snapshots, realtime_summary, sample_window, states_at,
                                  steady_start_s, swarm_counters)
from sim.emulate.config import LAUNCH_OVERHEAD_S, EmulateConfig
from sim.emulate.fly import SwarmRun, fly_swarm
from sim.emulate.plan import LaunchPlan, launch_plan, prepare_map

log = logging.getLogger(__name__)


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


def _run_config(config: EmulateConfig, map_path: Path, cmap: CommandMap):
    """The ``fisc-sim run`` settings of the emulation's report and reference run: its mode is the one the
    agents fly (with ``fleet_mode``, a recommended ``kinetic`` flown on the staggered field, with its
    deviations where the map carries the duct's real wall: ``fisc-sim run``'s ``kinetic``, whose deviations
    are isotropic where the agents' are turned across the stream)."""
    from sim.run import RunConfig

    mode = config.mode
    if mode is None and config.fleet_mode and config.preset != "paper" and config.tracking:
        field, deviations = tracked_mode(map_flight_settings(cmap).mode, None, WALL_ARRAY in cmap.arrays)
        mode = "kinetic" if deviations else field
    return RunConfig(map=str(map_path), scenario="reservoir", agents=config.agents, duration_s=config.duration_s,
                     average_window_s=config.average_window_s, sample_interval_s=config.sample_interval_s,
                     mode=mode, lookahead_s=config.lookahead_s, preset=config.preset,
                     seed=config.seed, dt_s=1.0 / config.rate_hz, min_samples=config.min_samples,
                     figures=config.figures, out_dir=config.out_dir)


def _emulation_section(res: EmulateResult) -> str:
    cfg, rt, en = res.config, res.realtime, res.entries
    lines = [
        "", "## Emulation (MAVLink in the loop)", "",
        f"{cfg.agents} {cfg.personality} autopilot emulators and {cfg.agents} fisc-agent runners talking MAVLink 2 "
        f"over loopback UDP, {cfg.duration_s:.0f} s of real time, exit policy `{cfg.exit_policy}`, "
        f"{cfg.rate_hz:.0f} Hz setpoints, emulators served at {cfg.physics_rate_hz:.0f} Hz (physics step "
        f"{cfg.physics_dt_s} s), {cfg.telemetry} telemetry.  " +
        ("Fields come from the states the emulated autopilots report: their estimates, which stray from the truth "
         "as stock PX4's on SIH do (`--estimate-error`), as a ground station sees a real fleet"
         if cfg.estimate_error else "Fields come from the emulators' true vehicle states") +
        " (map frame, default deployment transform).", "",
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
        ref = res.comparison["run_reference"]
        flow = ref["flowing_vehicles"]
        lines += ["", "### Difference to `fisc-sim run` (same map, duration, mode, vehicles flowing)", "",
                  f"`run` is `fisc-sim run --agents {ref['population']}`, the mean over {len(ref['seeds'])} seeds "
                  f"({', '.join(str(k) for k in ref['seeds'])}), sd their spread: it flies "
                  f"{_fmtv(flow['run'])} agents in the CVs on average, the emulation {_fmtv(flow['emulate'])} vehicles "
                  f"(of {cfg.agents}: the others fly back to the inlet), where `--agents {ref['launched_population']}` "
                  f"flies {_fmtv(flow['run_launched_population'])}.  The last column is the difference to that "
                  "launched population's run (fewer samples per CV make the min-max metrics noisier).", "",
                  "| metric | emulate | run | run sd | emulate - run | emulate - run at the launched population |",
                  "|---|---|---|---|---|---|"]
        for k, d in res.comparison["metrics"].items():
            lines.append(f"| {k} | {_fmtv(d['emulate'])} | {_fmtv(d['run'])} | {_fmtv(d['run_sd'])} | "
                         f"{_fmtv(d['difference'])} | {_fmtv(res.comparison['launched_population'][k]['difference'])} |")
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
    from fisc_ground.fields.field_report import json_safe, write_fields_csv, write_json
    from fisc_ground.fields.field_run import FieldRun, FieldSource
    from sim import report
    from sim.run import PAPER_SNAPSHOT_TIMES_S, RunConfig, RunResult
    from sim.run import run as sim_run
    from sim.run import simulate

    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if config.flight_logs is not None:
        Path(config.flight_logs).mkdir(parents=True, exist_ok=True)
    map_path, cmap = prepare_map(config.map, out, config.preset)
    transform = DeploymentTransform(DEFAULT_ORIGIN_NED_M, 0.0)
    cf = CommandField.from_map(cmap)
    plan = launch_plan(cf, config.agents, transform, entry_radius_fraction=config.entry_radius_fraction,
                       spacing_m=config.start_spacing_m, gap_m=config.start_gap_m,
                       overhead_s=config.launch_overhead_s if config.launch_overhead_s is not None
                       else LAUNCH_OVERHEAD_S[config.personality], duration_s=config.duration_s)
    swarm = fly_swarm(map_path, plan, config, progress)

    target_cmd = cmap.scale * np.asarray(cmap["target_velocity_m_s"], dtype=float)
    window = sample_window(swarm.sample_t_s, config.duration_s, config.average_window_s)
    fields, cv = ground_truth_fields(swarm, cmap, transform, window, target_cmd)
    n_steps = int(round(config.duration_s * config.rate_hz))
    counters, alive = swarm_counters(swarm.agents, cv[-1], n_steps, sum(a["ticks"] for a in swarm.agents))
    entries = entry_statistics(swarm.agents, plan)
    first_entry = entries["first_entry_s"] if entries["first_entry_s"] is not None else float(plan.arrival_time_s[0])
    rcfg = _run_config(config, map_path, cmap)
    t_win = swarm.sample_t_s[window] if window.size else np.array([0.0, 0.0])
    settings = rcfg.flight_settings(cmap)
    stats = emulated_statistics(swarm, cmap, transform, window, cv, target_cmd, config.min_samples, rcfg.block_s)
    fr = FieldRun(source=FieldSource.EMULATION, cmap=cmap, fields=fields, scale=cmap.scale,
                  min_samples=config.min_samples, scenario=rcfg.scenario, mode=settings.mode,
                  snapshots=tuple(position_snapshots(swarm, cv, transform, PAPER_SNAPSHOT_TIMES_S, first_entry)),
                  statistics=stats)
    rr = RunResult(config=rcfg, field_run=fr, settings=settings, counters=counters, alive=alive,
                   wall_time_s=swarm.duration_s, window_s=(float(np.nanmin(t_win)), float(np.nanmax(t_win))),
                   inflow_rate_per_s=plan.inflow_rate_per_s, collisions=None,
                   approach=emulated_approach(swarm, transform, map_separation(cmap.body).d_min_m))
    res = EmulateResult(config=config, run_result=rr, swarm=swarm, plan=plan, entries=entries,
                        realtime=realtime_summary(swarm, config.rate_hz, config.agents,
                                                  steady_start_s(plan, config.duration_s)))
    rr.metrics = report.compute_metrics(rr)
    rr.metrics["separation_interval_s"] = config.sample_interval_s  # every fleet sample, every vehicle
    rr.metrics["emulation"] = json_safe({"entries": entries, "real_time": {
        k: v for k, v in res.realtime.items() if k not in ("agent_loops", "emulator_loops")}})
    res.paths["map"] = map_path
    res.paths["fields"] = write_fields_csv(fr, out / "fields.csv")
    res.paths["metrics"] = report.write_metrics_json(rr, out / "metrics.json")
    if config.figures:
        from fisc_ground.figures import field_figures as figures

        rr.paths.update(figures.write_run_figures(fr, out))
        res.paths.update(rr.paths)
    if config.compare:
        # the reference flies the simulator's own step (paper: 0.05 s), whatever the agents' rate
        # (and, first, at the launched population N, to learn how many agents N keeps flowing)
        ref_cfg = replace(rcfg, out_dir=str(out / "run_reference"), figures=False, dt_s=RunConfig().dt_s)
        seeds = [ref_cfg.seed + k for k in range(config.reference_seeds)]
        launched = [simulate(replace(ref_cfg, seed=s, compare_paper=False), cmap) for s in seeds]
        flow_emu = flowing_vehicles(fields)
        flow_launched = float(np.mean([flowing_vehicles(m.fields) for m in launched]))
        n_ref = matched_population(config.agents, flow_emu, flow_launched)
        ref = sim_run(replace(ref_cfg, agents=n_ref))
        more = [simulate(replace(ref_cfg, agents=n_ref, seed=s, compare_paper=False), cmap) for s in seeds[1:]]
        res.comparison = compare_fields(rr.metrics, [ref.metrics] + [m.field_run.metrics() for m in more], fields,
                                        ref.fields, config.min_samples)
        res.comparison["launched_population"] = compare_fields(
            rr.metrics, [m.field_run.metrics() for m in launched], fields, launched[0].fields,
            config.min_samples)["metrics"]
        res.comparison["run_reference"] = {
            "out_dir": str(out / "run_reference"), "seeds": seeds, "population": n_ref,
            "launched_population": config.agents,
            "flowing_vehicles": {"emulate": flow_emu, "run": float(np.mean(
                [flowing_vehicles(m.fields) for m in [ref] + more])), "run_launched_population": flow_launched},
            "wall_time_s": sum(m.wall_time_s for m in [ref] + more + launched),
            "agents": ref.metrics.get("agents")}
        res.comparison["separation"] = {k: rr.metrics.get(k) for k in (
            "closest_approach_m", "closest_approach_time_s", "closest_approach_ids", "near_misses", "d_min_m")}
        res.comparison["separation"]["run_reference"] = {k: ref.metrics.get(k) for k in (
            "closest_approach_m", "near_misses", "d_min_m")}
        res.comparison["axial_profile"] = {k: {"emulate": rr.metrics["axial_profile"][k],
                                               "run": ref.metrics.get("axial_profile", {}).get(k)}
                                           for k in ("pearson_density", "pearson_pressure", "nrmse_density",
                                                     "nrmse_pressure")}
        res.paths["comparison"] = write_json(out / "comparison.json", res.comparison)
    if config.mcap is not None:
        res.paths["mcap"] = write_flight_log(Path(config.mcap), swarm, cmap, map_path, transform, cv,
                                             config.sample_interval_s)
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


def write_flight_log(path: Path, swarm: SwarmRun, cmap: CommandMap, map_path: Path, transform: DeploymentTransform,
                     cv: np.ndarray, sample_interval_s: float) -> Path:
    """The flight as a Foxglove/MCAP flight log (``fisc_ground.monitor.flight_log``): every ground-truth sample
    (map frame) with the agents' mission states, as the telemetry a monitor would have recorded, the
    run's clock (s since launch) as receive time."""
    from fisc_ground.monitor.flight_log import FlightLog, LogSettings, SimulatedTelemetry

    states = states_at(swarm.agents, swarm.sample_t_s)
    log_ = SimulatedTelemetry(FlightLog(LogSettings(sample_period_s=sample_interval_s,
                                                    stale_after_s=1.5 * sample_interval_s, source="fisc-sim emulate"),
                                        mcap_path=path), cmap, Path(map_path).read_bytes())
    try:
        for k, t in enumerate(swarm.sample_t_s.tolist()):
            if not np.isfinite(t):
                continue
            pos = transform.ned_to_map(swarm.pos_ned_m[k])
            vel = transform.vel_ned_to_map(swarm.vel_ned_m_s[k])
            ok = np.isfinite(pos).all(axis=1) & np.isfinite(vel).all(axis=1)
            log_.sample(t, swarm.agent_ids[ok], pos[ok], vel[ok], states[k][ok], cv[k][ok])
    finally:
        log_.close()
    return path
