"""``FieldRun``: one time-averaged swarm-field estimate on a command map, whatever produced it.

``fisc-sim run`` (vectorised simulator), ``fisc-sim emulate`` (emulated autopilots, ground-truth
states) and ``fisc-ground replay`` (recorded telemetry) each produce one ``FieldRun``.  Everything
that only needs the fields and the map lives here or in ``fisc_ground.fields.field_report``: the per-CV
columns of fields.csv, the fidelity metrics (``FieldRun.metrics``, the one metrics call of all
three), the figures (``fisc_ground.figures.field_figures``) and the JSON form (``field_report.json_safe``).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from fisc_agent.map.codec import CommandMap
from fisc_ground.fields.field_report import fidelity_for_columns, swarm_columns
from fisc_ground.fields.intervals import HonestStatistics
from fisc_ground.fields.swarm_fields import SwarmFields

PRESSURE_DEFINITION = ("swarm_pressure = 2 m/(3 dV) <sum ||u_i - S v_target,j||^2> (eq. pressure_constraint, "
                       "time-averaged density)")
DENSITY_DEFINITION = ("swarm_density = M_j / l^3 (eq. swarm_density with the CV cube as the swarm's volume: "
                      "the agents fly in the whole cube)")
#: Pressure columns scored beside ``swarm_pressure`` (metrics.json ``other_pressures``).
OTHER_PRESSURES = ("swarm_pressure_kinetic", "swarm_pressure_internal", "swarm_pressure_random",
                   "swarm_pressure_open_volume")


class FieldSource(enum.Enum):
    """What produced a ``FieldRun``."""

    SIMULATION = "fisc-sim run"
    EMULATION = "fisc-sim emulate"
    REPLAY = "fisc-ground replay"


@dataclass(frozen=True)
class FieldRun:
    """A swarm-field estimate: the map, the time-averaged fields and how they were obtained."""

    source: FieldSource
    """What produced the fields."""
    cmap: CommandMap
    """The command map flown (its CVs index ``fields``)."""
    fields: SwarmFields
    """Time-averaged swarm fields per CV."""
    scale: float
    """Speed scale S flown (the target command is S times the CFD target velocity)."""
    min_samples: int
    """CVs with fewer agent samples are left out of the metrics and figures."""
    scenario: str
    """Scenario label for figures and reports (``reservoir``, ``seed``, ``telemetry``)."""
    mode: str
    """Command mode flown (or ``replay`` when unknown), for figures and reports."""
    collisions: bool = False
    """The collision layer was on (simulation only)."""
    snapshots: tuple[tuple[float, np.ndarray], ...] = ()
    """(t [s], positions (n, 3) in the map frame [m]) at the paper's fig. 4 snapshot times."""
    companion: "FieldRun | None" = None
    """The paper preset flown on the same CVs (``fisc-sim run``), shown beside this run in the figures."""
    statistics: HonestStatistics | None = None
    """The figures' bootstrap intervals, the axial profile and the samples per CV, where the producer kept
    its samples per time block (``fisc_ground.fields.intervals``)."""

    @property
    def target_command_m_s(self) -> np.ndarray:
        """(n_cv, 3) S * CFD target velocity: the reference of the dispersion pressure [m/s]."""
        return self.scale * np.asarray(self.cmap["target_velocity_m_s"], dtype=float)

    def columns(self) -> dict[str, np.ndarray]:
        """Per-CV columns of fields.csv (``field_report.FIELD_COLUMNS``, SI units)."""
        return swarm_columns(self)

    def fidelity(self) -> dict:
        """Fidelity metrics (DESIGN.md section 4: nRMSE, Pearson, centreline deviation of velocity,
        pressure and density) against the map's CFD targets; NaN where undefined."""
        cols = self.columns()
        return fidelity_for_columns(cols, cols["swarm_pressure"], self.min_samples)

    def metrics(self) -> dict:
        """metrics.json core: ``fidelity`` plus the other pressure and density definitions scored
        alike, the definitions, the map and the sample counts."""
        cols = self.columns()
        out = dict(fidelity_for_columns(cols, cols["swarm_pressure"], self.min_samples))
        alt = {}
        for name in OTHER_PRESSURES:
            m = fidelity_for_columns(cols, cols[name], self.min_samples)
            alt[name] = {"nrmse_pressure": m["nrmse_pressure"], "pearson_pressure": m["pearson_pressure"],
                         "centreline_max_dev_pressure": m["centreline_max_dev_pressure"]}
        m = fidelity_for_columns(cols, cols["swarm_pressure"], self.min_samples,
                                 density=cols["swarm_density_open_volume"])
        out.update(
            source=self.source.value, n_cv=int(cols["cv_x"].size), time_samples=int(self.fields.n_time_samples),
            pressure_definition=PRESSURE_DEFINITION, other_pressures=alt,
            density_definition=DENSITY_DEFINITION,
            other_densities={"swarm_density_open_volume": {
                "nrmse_density": m["nrmse_density"], "pearson_density": m["pearson_density"],
                "centreline_max_dev_density": m["centreline_max_dev_density"]}},
            map={"sha256": self.cmap.sha256, "map_version": self.cmap.map_version,
                 "reference": self.cmap.body.get("provenance", {}).get("reference", {}).get("name")},
        )
        if self.statistics is not None:
            out.update(intervals=self.statistics.intervals_dict(), axial_profile=self.statistics.axial_profile_dict(),
                       samples_per_cv=self.statistics.samples)
        return out
