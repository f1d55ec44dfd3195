"""Analysis of a flown swarm: ground-truth fields, inlet arrivals, real-time verdict, comparison with
``fisc-sim run`` (pure: arrays in, numbers out)."""

from __future__ import annotations

from collections.abc import Sequence

import math

import numpy as np

from fisc_agent.flight.frames import DeploymentTransform
from fisc_agent.map.lookup import CommandField
from fisc_agent.map.codec import CommandMap
from sim.emulate.fly import SwarmRun
from sim.emulate.plan import LaunchPlan



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


# ------------------------------------------------------------------------------------ analysis
def sample_window(sample_t_s: np.ndarray, duration_s: float, average_window_s: float) -> np.ndarray:
    """Indices of the samples in the averaging window: the last ``average_window_s`` of the run
    (the whole run if it is shorter), as ``fisc-sim run`` averages."""
    start = max(0.0, duration_s - average_window_s)
    return np.flatnonzero(np.nan_to_num(sample_t_s, nan=-1.0) >= start - 1e-9)


def flowing(swarm: SwarmRun) -> np.ndarray:
    """(K, N) bool: the vehicle's agent was in state FLOW at the fleet sample (from the agents'
    transitions, which share the samples' time base)."""
    k, n = swarm.pos_ned_m.shape[:2]
    out = np.zeros((k, n), dtype=bool)
    col = {int(a): j for j, a in enumerate(np.asarray(swarm.agent_ids).tolist())}
    t = np.nan_to_num(np.asarray(swarm.sample_t_s, dtype=float), nan=-np.inf)
    for a in swarm.agents:
        j = col.get(int(a["agent_id"]))
        if j is None:
            continue
        for i, (t_s, _src, dst, _why) in enumerate(a["transitions"]):
            if dst != "FLOW":
                continue
            t_end = next((tt for tt, _s, d, _w in a["transitions"][i + 1:]), math.inf)
            out[(t >= t_s) & (t < t_end), j] = True
    return out


def ground_truth_fields(swarm: SwarmRun, cmap: CommandMap, transform: DeploymentTransform, window: np.ndarray,
                        reference_velocity_m_s: np.ndarray):
    """Time-averaged swarm fields from the emulators' true states (map frame, per CV).

    Returns ``(SwarmFields, cv_ids (K, N))``: every sample in ``window`` is one ``FieldAccumulator.add``
    of the vehicles whose agent flies the field (state FLOW, ``flowing``), as ``fisc-sim run`` counts
    its agents: a vehicle joining, returning, holding or looping back that passes through a CV is not
    part of the flow (cv -1 there, like vehicles outside every CV and NaN samples).
    """
    from fisc_ground.fields.swarm_fields import FieldAccumulator

    field = CommandField.from_map(cmap)
    k, n = swarm.pos_ned_m.shape[:2]
    pos_map = transform.ned_to_map(swarm.pos_ned_m.reshape(-1, 3))
    vel_map = transform.vel_ned_to_map(swarm.vel_ned_m_s.reshape(-1, 3))
    finite = np.all(np.isfinite(pos_map), axis=1) & np.all(np.isfinite(vel_map), axis=1)
    cv = np.full(k * n, -1, dtype=np.int64)
    cv[finite] = field.cv_of(pos_map[finite])
    cv = cv.reshape(k, n)
    cv[~flowing(swarm)] = -1
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


def flowing_vehicles(fields) -> float:
    """Mean number of vehicles (agents) inside the CVs per time sample of a ``SwarmFields`` average."""
    return float(np.sum(fields.count))


def matched_population(n_agents: int, emulated_flowing: float, launched_flowing: float) -> int:
    """Population target of the ``fisc-sim run`` reference that flies as many agents in the tunnel as
    the emulation flew vehicles: ``n_agents * emulated_flowing / launched_flowing``, rounded, at least 1
    (``n_agents`` itself when the launched run flew nobody).

    ``emulated_flowing``: the emulation's mean number of vehicles flowing in the CVs over the window
    (``flowing_vehicles``); ``launched_flowing``: the same of ``fisc-sim run --agents n_agents``.  The
    two differ because N looping vehicles are not N agents fed by an endless reservoir: after each lap a
    vehicle flies back to the inlet for 15-20 s, so about 30 of 50 emulated vehicles fly the field at a
    time against about 43 of the run's 50.  Fewer agents give fewer samples per CV, and the min-max
    normalised metrics grow with that sampling noise (docs/emulation.md), so the comparison of the
    command chain flies the reference at the emulation's own population."""
    if not (math.isfinite(emulated_flowing) and math.isfinite(launched_flowing)) or launched_flowing <= 0.0:
        return int(n_agents)
    return max(1, int(round(n_agents * emulated_flowing / launched_flowing)))


def compare_fields(emu_metrics: dict, run_metrics: Sequence[dict], emu_fields, run_fields, min_samples: int) -> dict:
    """Metric differences (emulate - run) and a direct comparison of the two swarm fields.

    ``run_metrics``: the metrics of one or more ``fisc-sim run`` references (seeds); each metric's
    ``run`` is their mean, ``run_sd`` their standard deviation (None for one), ``run_seeds`` the
    values.  ``run_fields``: the first reference's fields (the direct comparison)."""
    from fisc_ground.fields.metrics import nrmse, normalise, pearson

    if not run_metrics:
        raise ValueError("compare_fields needs at least one fisc-sim run reference")
    diff = {}
    for k in COMPARED_METRICS:
        e = _num(emu_metrics.get(k))
        vals = [_num(m.get(k)) for m in run_metrics]
        r = None if any(v is None for v in vals) else float(np.mean(vals))
        sd = None if r is None or len(vals) < 2 else float(np.std(vals, ddof=1))
        if k == "n_cv_compared":
            e, r = (None if e is None else int(e)), (None if r is None else int(round(r)))
        diff[k] = {"emulate": e, "run": r, "run_sd": sd, "run_seeds": vals,
                   "difference": None if e is None or r is None else e - r}
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


def swarm_counters(agents: list[dict], cv_last: np.ndarray, n_steps: int, agent_steps: int):
    """Run-style bookkeeping: injected = inlet entries, exited = outlet passes (laps), alive =
    vehicles inside a CV at the end, escaped = the rest (left the map sideways: geofence)."""
    from sim.swarm import SwarmCounters

    injected = sum(1 for a in agents for _, src, dst, _ in a["transitions"] if src == "JOIN" and dst == "FLOW")
    exited = sum(a["laps"] for a in agents)
    alive = int(np.sum(cv_last >= 0))
    return SwarmCounters(injected=injected, exited=exited, escaped=max(0, injected - exited - alive),
                         returned=0, steps=n_steps, agent_steps=agent_steps), alive


def position_snapshots(swarm: SwarmRun, cv: np.ndarray, transform: DeploymentTransform,
                       times_s: tuple[float, ...], t_offset_s: float) -> list[tuple[float, np.ndarray]]:
    """Map-frame positions of the vehicles inside a CV at the fleet sample nearest each of
    ``times_s`` (shifted by ``t_offset_s``), for the paper's snapshot figures; times past the
    last sample are skipped."""
    out = []
    for t in times_s:
        tt = t + t_offset_s
        if not np.isfinite(swarm.sample_t_s).any() or tt > np.nanmax(swarm.sample_t_s):
            continue
        i = int(np.nanargmin(np.abs(swarm.sample_t_s - tt)))
        inside = cv[i] >= 0
        out.append((float(swarm.sample_t_s[i]), transform.ned_to_map(swarm.pos_ned_m[i][inside])))
    return out


def states_at(agents: list[dict], t_s: np.ndarray) -> np.ndarray:
    """(K, N) mission state names of each agent (``agents`` in column order) at the times ``t_s``
    since launch, from its transitions; before its first transition an agent is in that
    transition's source state."""
    t_s = np.nan_to_num(np.asarray(t_s, dtype=float), nan=-np.inf)
    out = np.empty((t_s.size, len(agents)), dtype=object)
    for j, a in enumerate(agents):
        tr = a["transitions"]
        if not tr:
            out[:, j] = a["state"]
            continue
        times = np.array([x[0] for x in tr], dtype=float)
        names = np.array([tr[0][1]] + [x[2] for x in tr], dtype=object)
        out[:, j] = names[np.searchsorted(times, t_s, side="right")]
    return out


def emulated_approach(swarm: SwarmRun, transform: DeploymentTransform, d_min_m: float):
    """Closest approach and near-misses over every fleet sample of all emulated vehicles with a finite
    position (map frame; ``fisc_ground.fields.separation_stats``), whatever their state: what a ground
    station sees."""
    from fisc_ground.fields.separation_stats import ApproachTracker

    tracker = ApproachTracker(d_min_m)
    ids = np.asarray(swarm.agent_ids, dtype=np.int64)
    for k, t in enumerate(np.asarray(swarm.sample_t_s, dtype=float).tolist()):
        if math.isfinite(t):
            tracker.add(t, ids, transform.ned_to_map(swarm.pos_ned_m[k]))
    return tracker.result()


def emulated_statistics(swarm: SwarmRun, cmap: CommandMap, transform: DeploymentTransform, window: np.ndarray,
                        cv: np.ndarray, reference_velocity_m_s: np.ndarray, min_samples: int, block_s: float):
    """The bootstrap intervals, axial profile and samples per CV (``fisc_ground.fields.intervals``) of the
    samples ``ground_truth_fields`` averaged (``cv`` its (K, N) CV ids, -1 where not flowing)."""
    from fisc_ground.fields.intervals import honest_statistics, stats_inputs
    from fisc_ground.fields.swarm_fields import cv_moments
    from fisc_ground.fields.time_blocks import BlockAccumulator

    k, n = swarm.pos_ned_m.shape[:2]
    vel = transform.vel_ned_to_map(swarm.vel_ned_m_s.reshape(-1, 3)).reshape(k, n, 3)
    vel = np.where(np.isfinite(vel).all(axis=2, keepdims=True), vel, 0.0)
    blocks = BlockAccumulator(cmap.n_cv, block_s)
    mass = float(cmap.body.get("agent_mass_kg", 1.0))
    t = np.asarray(swarm.sample_t_s, dtype=float)
    for i in window:
        blocks.add_moments(float(t[i]), cv_moments(cv[i], vel[i], mass, cmap.n_cv, reference_velocity_m_s))
    dt = float(np.nanmedian(np.diff(t))) if t.size > 1 else 0.0
    return honest_statistics(blocks.sums(), stats_inputs(cmap, min_samples),
                             blocks.last_t_s - blocks.first_t_s + dt)
