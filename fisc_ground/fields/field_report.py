"""Swarm-field outputs: fields.csv, metrics.json and report.md (no plotting here).

Shared by ``fisc-sim run``, ``fisc-sim emulate`` and ``fisc-ground replay`` (``sim.report`` adds
the run-specific metrics.json and report.md); ``run`` is a ``fisc_ground.fields.field_run.FieldRun``.

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
import enum
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from fisc_ground.fields.metrics import fidelity_metrics


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
    from fisc_ground.fields.swarm_equations import SwarmGasParams

    t = np.nan_to_num(np.asarray(fields.t_rand_m2_s2, dtype=float))
    return 4.0 / 3.0 * np.asarray(fields.rho_s_kg_m3, dtype=float) * t / SwarmGasParams().k_b_s


def swarm_columns(run: Any) -> dict[str, np.ndarray]:
    """Per-CV columns of fields.csv (SI units) of a ``FieldRun``."""
    f = run.fields
    cmap = run.cmap
    c = np.asarray(cmap["cv_center_m"], dtype=float)
    frac = open_fraction(cmap)
    return {
        "cv_id": np.arange(c.shape[0]),
        "cv_x": c[:, 0], "cv_y": c[:, 1], "cv_z": c[:, 2],
        "target_u_axial": np.asarray(cmap["target_velocity_m_s"], dtype=float)[:, 0],
        "target_pressure": np.asarray(cmap["target_pressure_gauge_pa"], dtype=float),
        "target_density": np.asarray(cmap["target_density_kg_m3"], dtype=float),
        "target_command_u_axial": run.target_command_m_s[:, 0],
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


def fidelity_for_columns(cols: dict[str, np.ndarray], pressure: np.ndarray, min_samples: int,
                 density: np.ndarray | None = None) -> dict:
    """Fidelity metrics (DESIGN.md section 4) of per-CV columns with the given swarm pressure (and density)."""
    return fidelity_metrics(np.stack([cols["cv_x"], cols["cv_y"], cols["cv_z"]], axis=1),
                            cols["target_u_axial"], cols["target_pressure"], cols["target_density"],
                            cols["swarm_u_axial"], pressure, cols["swarm_density"] if density is None else density,
                            cols["samples"], min_samples=min_samples).as_dict()


def json_safe(obj: Any) -> Any:
    """Plain-JSON copy (metrics.json, emulation.json ... are strict JSON): numpy arrays/scalars ->
    lists/numbers, paths and enums -> str, NaN/inf -> None, recursively."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(float(obj)) else None
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, enum.Enum):
        return json_safe(obj.value)
    return obj


def write_json(path: Path, obj: Any) -> Path:
    """``json_safe(obj)`` as indented, key-sorted strict JSON (no NaN) into ``path``."""
    Path(path).write_text(json.dumps(json_safe(obj), indent=2, sort_keys=True, allow_nan=False) + "\n")
    return Path(path)


def write_fields_csv(run: Any, path: Path) -> Path:
    """fields.csv of a ``FieldRun``: one row per CV, columns ``FIELD_COLUMNS`` (SI; empty cells are NaN)."""
    cols = swarm_columns(run)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(FIELD_COLUMNS)
        data = np.column_stack([np.asarray(cols[k], dtype=float) for k in FIELD_COLUMNS])
        for row in data:
            w.writerow([str(int(v)) if k in ("cv_id", "samples") else repr(float(v))
                        for k, v in zip(FIELD_COLUMNS, row)])
    return path


