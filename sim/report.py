"""Outputs of a ``fisc-sim run`` beyond the shared field files: metrics.json and report.md.

The per-CV columns, their definitions and fields.csv live in ``fisc_ground.fields.field_report`` (shared
with ``fisc-ground replay``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from fisc_ground.fields.field_report import PAPER_FIGURES, json_safe, write_json

#: A ``sim.run.RunResult`` (not imported: sim.run imports this module).
RunResult = Any


def compute_metrics(result: RunResult) -> dict:
    """metrics.json content: the run's ``FieldRun.metrics`` (fidelity, DESIGN.md section 4) plus
    agent counts, speed and the configuration."""
    cfg = result.config
    c = result.counters
    out = result.field_run.metrics()
    out["flight_settings"] = {"mode": result.settings.mode, "lookahead_s": result.settings.lookahead_s,
                              "persistence_s": result.settings.persistence_s, "preset": cfg.preset,
                              "map_schema_version": result.cmap.schema_version}
    out["spread_realised_over_fitted"] = spread_ratio_summary(result, cfg.min_samples)
    paper = getattr(result, "paper", None)
    if paper is not None and paper.metrics:
        out["paper_preset"] = {k: paper.metrics[k] for k in (
            "nrmse_velocity", "nrmse_pressure", "nrmse_density", "pearson_velocity", "pearson_pressure",
            "pearson_density", "centreline_max_dev_velocity", "centreline_max_dev_pressure",
            "centreline_max_dev_density", "n_cv_compared", "wall_time_s")}
    out.update(
        agents={"injected": c.injected, "exited": c.exited, "escaped": c.escaped, "removed": c.removed,
                "alive": int(result.alive), "return_agent_steps": c.returned},
        steps=c.steps, agent_steps=c.agent_steps, simulated_s=c.steps * cfg.dt_s,
        wall_time_s=result.wall_time_s,
        agent_steps_per_s=c.agent_steps / result.wall_time_s if result.wall_time_s > 0 else None,
        average_window_s=list(result.window_s),
        scale=result.scale, inflow_rate_per_s=result.inflow_rate_per_s, collisions=result.collisions,
        config=cfg.as_dict(),
    )
    net = getattr(result, "safety_net", None)
    if net is not None:
        out["safety_net"] = net
        out["safety_net_acting_fraction"] = net["acting_fraction"]
    approach = getattr(result, "approach", None)
    if approach is not None:
        out.update(approach.as_dict())
        out["separation_interval_s"] = cfg.separation_interval_s
    return json_safe(out)


def spread_realised_over_fitted(result: RunResult, min_samples: int) -> np.ndarray:
    """(n_cv,) realised per-agent rms velocity deviation about the CV's local mean, over the fitted
    spread sqrt(mean_k ||S v_k - S v_mean||^2) of the map (NaN where too few samples or no spread).

    Realised: ``swarm_pressure_random`` = 2/3 rho_s <||v - U||^2> with rho_s = m count / l^3."""
    from fisc_agent.map.lookup import CommandField
    from fisc_ground.fields.field_report import random_pressure

    f = result.fields
    fitted = CommandField.from_map(result.cmap, scale=result.scale).spread_m_s
    mass = float(result.cmap.body.get("agent_mass_kg", 1.0))
    l3 = result.cmap.cell_size_m ** 3
    count = np.asarray(f.count, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        var = random_pressure(f) * 1.5 * l3 / (mass * count)
        ratio = np.sqrt(var) / fitted
    ok = (np.asarray(f.samples) >= min_samples) & (fitted > 0.1 * np.max(fitted)) & np.isfinite(ratio)
    return np.where(ok, ratio, np.nan)


def spread_ratio_summary(result: RunResult, min_samples: int) -> dict:
    """Median and quartiles of ``spread_realised_over_fitted`` over the CVs with a fitted spread of at
    least a tenth of the largest (the throat's ~0 spread makes the ratio meaningless there)."""
    r = spread_realised_over_fitted(result, min_samples)
    v = r[np.isfinite(r)]
    if v.size == 0:
        return {"median": None, "p25": None, "p75": None, "n_cv": 0}
    return {"median": float(np.median(v)), "p25": float(np.percentile(v, 25)),
            "p75": float(np.percentile(v, 75)), "n_cv": int(v.size)}


def write_metrics_json(result: RunResult, path: Path) -> Path:
    """metrics.json (``compute_metrics``; NaN written as null)."""
    return write_json(path, result.metrics or compute_metrics(result))


def _fmt(v) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) >= 1e3 else f"{v:.3f}"
    return str(v)


def separation_line(m: dict) -> str:
    """The closest approach of metrics.json ``m`` as one sentence."""
    d, ids, t = m.get("closest_approach_m"), m.get("closest_approach_ids"), m.get("closest_approach_time_s")
    head = ("Closest approach: never two agents in the tunnel at once" if d is None else
            f"Closest approach {d:.3f} m (agents {ids[0]} and {ids[1]} at t = {t:.1f} s)")
    every = m.get("separation_interval_s")
    return (f"{head}; {m['near_misses']} near-misses (pairs closer than d_min = {m['d_min_m']:.2f} m, the map's "
            f"designed spacing, counted once per encounter) over {m.get('separation_steps')} evaluations"
            + (f", one every {every:g} s of the agents in the tunnel." if every else "."))


def safety_net_line(m: dict) -> str:
    """The safety net's work of metrics.json ``m`` (``--safety-net``) as one sentence."""
    net = m["safety_net"]
    frac, pairs = net.get("acting_fraction"), net.get("mean_candidate_pairs")
    return (f"Safety net on (`--safety-net`, sim.safety_net): it changed the command in {net['acting_agent_steps']} of "
            f"{net['agent_steps']} agent-steps ({'n/a' if frac is None else f'{100 * frac:.1f} %'}), checking "
            f"{'n/a' if pairs is None else f'{pairs:.0f}'} candidate pairs per step on average.")


def statistics_lines(m: dict) -> list[str]:
    """report.md lines of the bootstrap intervals, the axial profile and the samples per CV (none
    when metrics.json ``m`` has no ``intervals``)."""
    iv, prof, spc = m.get("intervals"), m.get("axial_profile"), m.get("samples_per_cv")
    if not iv:
        return []
    n_blocks = next(iter(iv.values())).get("n_blocks")
    lines = ["", "## How far the figures can be trusted", "",
             f"95 % block-bootstrap intervals over {n_blocks} time blocks (basic intervals: for the figure with "
             "unlimited samples; sampling noise inflates an nRMSE and deflates an r, by about the bias shown):", "",
             "| figure | value | 95 % interval | noise bias |", "|---|---|---|---|"]
    rows = [(k, iv[k]) for k in iv] + [(f"axial profile {k}", prof[k]) for k in
                                       ("nrmse_density", "pearson_density", "nrmse_pressure", "pearson_pressure")
                                       if prof and k in prof]
    for k, d in rows:
        lines.append(f"| {k} | {_fmt(d['value'])} | [{_fmt(d['lo'])}, {_fmt(d['hi'])}] | {_fmt(d.get('bias'))} |")
    if prof:
        lines += ["", f"Axial profile: per {prof['slice_m'] or 0:g} m slice, density = time-averaged agents in the "
                  "slice / its CVs' volume, pressure from the slice's velocity spread, against the CFD's "
                  f"volume-weighted slice means; {int(sum(prof['compared']))} of {len(prof['x_m'])} slices compared."]
    if spc and spc.get("n_cv"):
        lines += ["", f"Samples per CV: min {spc['min']}, median {spc['median']:.0f}, max {spc['max']}; "
                  f"{100 * spc['fraction_below_min_samples']:.0f} % of the {spc['n_cv']} CVs have fewer than "
                  f"{spc['min_samples']} (left out)."]
    return lines


def write_report_md(result: RunResult, path: Path) -> Path:
    """report.md: our metrics beside the paper's, agent counts, speed, figures."""
    m = result.metrics or compute_metrics(result)
    cfg = result.config
    lines = [
        "# FISC swarm simulation report", "",
        f"Scenario **{cfg.scenario}**, preset **{cfg.preset}**, mode **{result.settings.mode}**, look-ahead "
        f"**{result.settings.lookahead_s:g} s**, map schema {result.cmap.schema_version}, collisions **{'on' if cfg.collisions else 'off'}**, "
        f"map `{m['map']['reference']}` (sha256 {result.cmap.sha256[:12]}...), S = {result.scale:.3f}, "
        f"{m['simulated_s']:.1f} s simulated at dt = {cfg.dt_s} s, fields averaged over "
        f"t = {result.window_s[0]:.1f}-{result.window_s[1]:.1f} s ({m['time_samples']} samples), seed {cfg.seed}.", "",
        "## Fidelity (DESIGN.md section 4) beside the paper", "",
    ]
    pp = m.get("paper_preset")
    if pp:
        lines += ["| metric | this run | `--preset paper` (Algorithm 1, same reference) | paper |",
                  "|---|---|---|---|"]
    else:
        lines += ["| metric | this run | paper |", "|---|---|---|"]
    for k in ("nrmse_velocity", "nrmse_pressure", "nrmse_density", "centreline_max_dev_velocity",
              "centreline_max_dev_pressure", "centreline_max_dev_density", "pearson_velocity",
              "pearson_pressure", "pearson_density"):
        mid = f" {_fmt(pp.get(k))} |" if pp else ""
        lines.append(f"| {k} | {_fmt(m.get(k))} |{mid} {PAPER_FIGURES.get(k, '-')} |")
    sr = m.get("spread_realised_over_fitted") or {}
    if sr.get("n_cv"):
        lines += ["", f"Realised / fitted per-agent velocity spread over {sr['n_cv']} CVs: median "
                  f"{_fmt(sr['median'])} (quartiles {_fmt(sr['p25'])}-{_fmt(sr['p75'])}); the fitted spread is what "
                  "carries the CFD pressure pattern (DESIGN.md section 3)."]
    lines += ["", f"CVs compared: {m['n_cv_compared']} of {m['n_cv']} (>= {m['min_samples']} agent samples).", "",
              "Swarm pressure: " + m["pressure_definition"] + ".  Other definitions, same normalisation:", ""]
    for name, d in m["other_pressures"].items():
        lines.append(f"* {name}: nRMSE {_fmt(d['nrmse_pressure'])}, Pearson {_fmt(d['pearson_pressure'])}")
    if m.get("other_densities"):
        lines += ["", "Swarm density: " + m.get("density_definition", "") + ".  With the CFD's open volume "
                  "A_j dx_j (the map's cv_open_fraction) instead:", ""]
        for name, d in m["other_densities"].items():
            lines.append(f"* {name}: nRMSE {_fmt(d['nrmse_density'])}, Pearson {_fmt(d['pearson_density'])}")
    lines += statistics_lines(m)
    a = m["agents"]
    lines += ["", "## Agents", "",
              f"injected {a['injected']}, exited through the outlet {a['exited']}, escaped {a['escaped']}, "
              f"alive at the end {a['alive']} (injected = alive + exited + escaped); "
              f"{a['return_agent_steps']} agent-steps under the return-to-map policy.", ""]
    if result.inflow_rate_per_s is not None:
        lines.append(f"Reservoir source rate (eq. source_rate, summed over the inlet): {result.inflow_rate_per_s:.1f} agents/s.")
    if result.collisions:
        lines.append(f"Collisions: {result.collisions}.")
    if m.get("d_min_m") is not None and m.get("near_misses") is not None:
        lines += ["", "## Separation", "", separation_line(m)]
    if m.get("safety_net"):
        lines += ["", safety_net_line(m)]
    lines += ["", "## Speed", "",
              f"{m['steps']} steps, {m['agent_steps']} agent-steps in {m['wall_time_s']:.2f} s wall "
              f"({_fmt(m['agent_steps_per_s'])} agent-steps/s).", ""]
    figs = [p for k, p in result.paths.items() if str(p).endswith(".png")]
    if figs:
        lines += ["## Figures", ""] + [f"* [{Path(p).name}]({Path(p).name})" for p in figs]
    lines += ["", "See docs/studies/fidelity.md for what limits each metric.", ""]
    path.write_text("\n".join(lines))
    return path
