"""Outputs of a ``fisc-sim run``: fields.csv, metrics.json and report.md (no plotting here).

The swarm pressure compared with the CFD (column ``swarm_pressure``) is the paper's simulation
pressure: eq. pressure_constraint evaluated with the agents' actual velocities against the CV's
target command ``S v_target,j`` and the time-averaged agent density,
``P = 2 m / (3 dV) <sum_i ||u_i - S v_target,j||^2>`` (``SwarmFields.p_dispersion_pa``).  The
kinetic P_s (eq. swarm_pressure) and internal P_s,internal (eq. internal_pressure) are written
beside it.

Density: ``swarm_density`` is eq. swarm_density with the CV cube l^3 as the volume (the agents
fly in the whole cube).  ``swarm_density_open_volume`` / ``swarm_pressure_open_volume`` divide by
the CFD's open volume A_j dx_j = l^3 * ``cv_open_fraction`` instead (1.0 for maps without that
optional array); both are scored in metrics.json (``other_densities``, ``other_pressures``).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from fisc_ground.metrics import fidelity_metrics

if TYPE_CHECKING:
    from sim.run import RunResult

#: The paper's reported ranges (Results and Discussion), for report.md.
PAPER_FIGURES = {
    "nrmse_velocity": "0.15 - 0.9",
    "nrmse_pressure": "0 - 0.937",
    "nrmse_density": "0.61 - 0.98",
    "centreline_max_dev_velocity": "~0.10",
    "centreline_max_dev_pressure": "~0.10",
    "centreline_max_dev_density": "larger ('more variation')",
}

FIELD_COLUMNS = (
    "cv_id", "cv_x", "cv_y", "cv_z", "target_u_axial", "target_pressure", "target_density",
    "target_command_u_axial", "fit_pressure", "swarm_u_axial", "swarm_pressure", "swarm_density",
    "swarm_temperature", "swarm_pressure_kinetic", "swarm_pressure_internal", "swarm_pressure_random",
    "swarm_count",
    "swarm_u_x", "swarm_u_y", "swarm_u_z", "samples",
    "cv_open_fraction", "swarm_density_open_volume", "swarm_pressure_open_volume",
)


def open_fraction(cmap) -> np.ndarray:
    """(n_cv,) open-volume fraction A_j dx_j / l^3 of every CV from the map's optional
    ``cv_open_fraction`` array; 1.0 everywhere for maps without it."""
    n = int(np.asarray(cmap["cv_center_m"]).shape[0])
    if "cv_open_fraction" in cmap.arrays:
        return np.asarray(cmap["cv_open_fraction"], dtype=float).reshape(n)
    return np.ones(n)


def random_pressure(fields) -> np.ndarray:
    """2/3 rho_s <||v - U||^2> = 4/3 rho_s T_s,rand / K_b,s: the internal pressure about the full
    local mean velocity U (eq. internal_pressure with U for u_s), i.e. the velocity variance only."""
    from fisc_ground.swarm_fields import SwarmGasParams

    t = np.nan_to_num(np.asarray(fields.t_rand_m2_s2, dtype=float))
    return 4.0 / 3.0 * np.asarray(fields.rho_s_kg_m3, dtype=float) * t / SwarmGasParams().k_b_s


def swarm_columns(result: "RunResult") -> dict[str, np.ndarray]:
    """Per-CV columns of fields.csv (SI units)."""
    f = result.fields
    cmap = result.cmap
    c = np.asarray(cmap["cv_center_m"], dtype=float)
    frac = open_fraction(cmap)
    return {
        "cv_id": np.arange(c.shape[0]),
        "cv_x": c[:, 0], "cv_y": c[:, 1], "cv_z": c[:, 2],
        "target_u_axial": np.asarray(cmap["target_velocity_m_s"], dtype=float)[:, 0],
        "target_pressure": np.asarray(cmap["target_pressure_gauge_pa"], dtype=float),
        "target_density": np.asarray(cmap["target_density_kg_m3"], dtype=float),
        "target_command_u_axial": result.target_command_m_s[:, 0],
        "fit_pressure": np.asarray(cmap["fit_pressure"], dtype=float),
        "swarm_u_axial": f.u_axial_m_s,
        "swarm_pressure": f.p_dispersion_pa,
        "swarm_density": f.rho_s_kg_m3,
        "swarm_temperature": f.t_s_m2_s2,
        "swarm_pressure_kinetic": f.p_s_pa,
        "swarm_pressure_internal": f.p_internal_pa,
        "swarm_pressure_random": random_pressure(f),
        "swarm_count": f.count,
        "swarm_u_x": f.mean_velocity_m_s[:, 0],
        "swarm_u_y": f.mean_velocity_m_s[:, 1],
        "swarm_u_z": f.mean_velocity_m_s[:, 2],
        "samples": f.samples,
        # eq. swarm_density / pressure_constraint with the CFD's open volume A_j dx_j instead of l^3
        "cv_open_fraction": frac,
        "swarm_density_open_volume": f.rho_s_kg_m3 / frac,
        "swarm_pressure_open_volume": f.p_dispersion_pa / frac,
    }


def _metrics_for(cols: dict[str, np.ndarray], pressure: np.ndarray, min_samples: int,
                 density: np.ndarray | None = None) -> dict:
    return fidelity_metrics(np.stack([cols["cv_x"], cols["cv_y"], cols["cv_z"]], axis=1),
                            cols["target_u_axial"], cols["target_pressure"], cols["target_density"],
                            cols["swarm_u_axial"], pressure, cols["swarm_density"] if density is None else density,
                            cols["samples"], min_samples=min_samples).as_dict()


def compute_metrics(result: "RunResult") -> dict:
    """metrics.json content: fidelity (DESIGN.md section 4), agent counts, speed, config."""
    from sim.run import config_dict

    cols = swarm_columns(result)
    cfg = result.config
    fid = _metrics_for(cols, cols["swarm_pressure"], cfg.min_samples)
    alt = {}
    for name in ("swarm_pressure_kinetic", "swarm_pressure_internal", "swarm_pressure_random",
                 "swarm_pressure_open_volume"):
        m = _metrics_for(cols, cols[name], cfg.min_samples)
        alt[name] = {"nrmse_pressure": m["nrmse_pressure"], "pearson_pressure": m["pearson_pressure"],
                     "centreline_max_dev_pressure": m["centreline_max_dev_pressure"]}
    m = _metrics_for(cols, cols["swarm_pressure"], cfg.min_samples, density=cols["swarm_density_open_volume"])
    alt_rho = {"swarm_density_open_volume": {
        "nrmse_density": m["nrmse_density"], "pearson_density": m["pearson_density"],
        "centreline_max_dev_density": m["centreline_max_dev_density"]}}
    c = result.counters
    out = dict(fid)
    out.update(
        n_cv=int(cols["cv_x"].size),
        pressure_definition="swarm_pressure = 2 m/(3 dV) <sum ||u_i - S v_target,j||^2> (eq. pressure_constraint, "
                            "time-averaged density)",
        other_pressures=alt,
        density_definition="swarm_density = M_j / l^3 (eq. swarm_density with the CV cube as the swarm's volume: "
                           "the agents fly in the whole cube)",
        other_densities=alt_rho,
        agents={"injected": c.injected, "exited": c.exited, "escaped": c.escaped, "removed": c.removed,
                "alive": int(result.alive), "return_agent_steps": c.returned},
        steps=c.steps, agent_steps=c.agent_steps, simulated_s=c.steps * cfg.dt_s,
        wall_time_s=result.wall_time_s,
        agent_steps_per_s=c.agent_steps / result.wall_time_s if result.wall_time_s > 0 else None,
        average_window_s=list(result.window_s), time_samples=int(result.fields.n_time_samples),
        scale=result.scale, inflow_rate_per_s=result.inflow_rate_per_s, collisions=result.collisions,
        map={"sha256": result.cmap.sha256, "map_version": result.cmap.map_version,
             "reference": result.cmap.body.get("provenance", {}).get("reference", {}).get("name")},
        config=config_dict(cfg),
    )
    return _json_safe(out)


def _json_safe(obj):
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return None if not math.isfinite(float(obj)) else float(obj)
    return obj


def write_fields_csv(result: "RunResult", path: Path) -> Path:
    """fields.csv: one row per CV, columns ``FIELD_COLUMNS`` (SI; empty cells are NaN)."""
    cols = swarm_columns(result)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(FIELD_COLUMNS)
        data = np.column_stack([np.asarray(cols[k], dtype=float) for k in FIELD_COLUMNS])
        for row in data:
            w.writerow([str(int(v)) if k in ("cv_id", "samples") else repr(float(v))
                        for k, v in zip(FIELD_COLUMNS, row)])
    return path


def write_metrics_json(result: "RunResult", path: Path) -> Path:
    """metrics.json (``compute_metrics``; NaN written as null)."""
    path.write_text(json.dumps(result.metrics or compute_metrics(result), indent=2, sort_keys=True) + "\n")
    return path


def _fmt(v) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) >= 1e3 else f"{v:.3f}"
    return str(v)


def write_report_md(result: "RunResult", path: Path) -> Path:
    """report.md: our metrics beside the paper's, agent counts, speed, figures."""
    m = result.metrics or compute_metrics(result)
    cfg = result.config
    lines = [
        "# FISC swarm simulation report", "",
        f"Scenario **{cfg.scenario}**, mode **{cfg.mode}**, collisions **{'on' if cfg.collisions else 'off'}**, "
        f"map `{m['map']['reference']}` (sha256 {result.cmap.sha256[:12]}...), S = {result.scale:.3f}, "
        f"{m['simulated_s']:.1f} s simulated at dt = {cfg.dt_s} s, fields averaged over "
        f"t = {result.window_s[0]:.1f}-{result.window_s[1]:.1f} s ({m['time_samples']} samples), seed {cfg.seed}.", "",
        "## Fidelity (DESIGN.md section 4) beside the paper", "",
        "| metric | this run | paper |", "|---|---|---|",
    ]
    for k in ("nrmse_velocity", "nrmse_pressure", "nrmse_density", "centreline_max_dev_velocity",
              "centreline_max_dev_pressure", "centreline_max_dev_density", "pearson_velocity",
              "pearson_pressure", "pearson_density"):
        lines.append(f"| {k} | {_fmt(m.get(k))} | {PAPER_FIGURES.get(k, '-')} |")
    lines += ["", f"CVs compared: {m['n_cv_compared']} of {m['n_cv']} (>= {m['min_samples']} agent samples).", "",
              "Swarm pressure: " + m["pressure_definition"] + ".  Other definitions, same normalisation:", ""]
    for name, d in m["other_pressures"].items():
        lines.append(f"* {name}: nRMSE {_fmt(d['nrmse_pressure'])}, Pearson {_fmt(d['pearson_pressure'])}")
    if m.get("other_densities"):
        lines += ["", "Swarm density: " + m.get("density_definition", "") + ".  With the CFD's open volume "
                  "A_j dx_j (the map's cv_open_fraction) instead:", ""]
        for name, d in m["other_densities"].items():
            lines.append(f"* {name}: nRMSE {_fmt(d['nrmse_density'])}, Pearson {_fmt(d['pearson_density'])}")
    a = m["agents"]
    lines += ["", "## Agents", "",
              f"injected {a['injected']}, exited through the outlet {a['exited']}, escaped {a['escaped']}, "
              f"alive at the end {a['alive']} (injected = alive + exited + escaped); "
              f"{a['return_agent_steps']} agent-steps under the return-to-map policy.", ""]
    if result.inflow_rate_per_s is not None:
        lines.append(f"Reservoir source rate (eq. source_rate, summed over the inlet): {result.inflow_rate_per_s:.1f} agents/s.")
    if result.collisions:
        lines.append(f"Collisions: {result.collisions}.")
    lines += ["", "## Speed", "",
              f"{m['steps']} steps, {m['agent_steps']} agent-steps in {m['wall_time_s']:.2f} s wall "
              f"({_fmt(m['agent_steps_per_s'])} agent-steps/s).", ""]
    figs = [p for k, p in result.paths.items() if str(p).endswith(".png")]
    if figs:
        lines += ["## Figures", ""] + [f"* [{Path(p).name}]({Path(p).name})" for p in figs]
    lines += ["", "See docs/simulation.md for what limits each metric.", ""]
    path.write_text("\n".join(lines))
    return path
