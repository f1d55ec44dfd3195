"""The ground pipeline: reference field -> control volumes -> velocity fitting -> command map."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from fisc_agent.map.kinetic import DEFAULT_PERSISTENCE_S
from fisc_agent.map.lookup import PAPER_SETTINGS, FlightSettings
from fisc_agent.map.codec import CommandMap, decode_map, encode_map, load_map
from fisc_agent.map.separation import DEFAULT_POSITION_SIGMA_M, DEFAULT_VEHICLE_RADIUS_M, Separation
from fisc_agent.map.wall import WALL_ARRAY
from fisc_ground.fit.length_scale import check_length_scale, scale_reference, time_ratio
from fisc_ground.fit.separation_budget import relative_density, separation_budget
from fisc_ground.maps.duct_wall import duct_wall_from_reference
from fisc_ground.fit.fitting import fit_rmse, fit_velocities
from fisc_ground.fit.partition import ControlVolumes, cv_open_fraction, partition_field
from fisc_ground.fit.staircase import DEFAULT_MIN_STEP_OPEN, DEFAULT_STAIRCASE_CONTRAST
from fisc_ground.reference.field import ReferenceField
from fisc_ground.reference.load import load_reference
from fisc_ground.fit.staggered import (
    DEFAULT_WEIGHT_EXPONENT,
    StaggeredConfig,
    build_staggered,
)
from fisc_ground.fit.scaling import (DEFAULT_DISPERSION_RATIO, DEFAULT_MAX_SPEED_M_S, KINETIC_DISPERSION_RATIO, choose_kappa,
                                 choose_scale, default_max_dispersion, swarm_pressure_target)

log = logging.getLogger(__name__)

DEFAULT_REFERENCE = "cd_nozzle_inviscid"
DEFAULT_MAP_FILE = "default.fiscmap"


#: Recommended flight settings of the maps this project builds (docs/studies/fidelity.md, "Fidelity").
DEFAULT_FLIGHT = FlightSettings("kinetic", 0.5, DEFAULT_PERSISTENCE_S)
#: ``--preset paper``: the fit settings of the paper's schema-1 map.
PAPER_PRESET = "paper"


@dataclass(frozen=True)
class FitConfig:
    """Parameters of one map build; all of them are recorded in the map's provenance."""

    cell_size_m: float = 0.5
    """CV edge length l at length scale 1 [m] (paper: 0.5 m); the map's cubes are ``length_scale`` x this."""
    n_min: int = 2
    """Smallest candidate agent count N per CV (paper: 2)."""
    n_max: int = 10
    """Largest candidate agent count N per CV (paper: 10)."""
    scale: float | None = None
    """Speed scaling S; None chooses the largest S that keeps every command within ``max_speed_m_s``."""
    max_speed_m_s: float = DEFAULT_MAX_SPEED_M_S
    """Agent speed limit used to choose S [m/s] (agents fly 2-10 m/s); default
    ``scaling.DEFAULT_MAX_SPEED_M_S`` (2 m/s), the same limit ``fisc-sim run`` fits its maps with."""
    kappa: float | None = None
    """Pressure mapping P_target = kappa (P_cfd - min P_cfd); None chooses it from ``max_dispersion_m_s``."""
    max_dispersion_m_s: float | None = None
    """Largest rms per-agent velocity dispersion the fit may ask for, before scaling [m/s];
    None = ``dispersion_ratio`` x the peak target speed (``scaling.default_max_dispersion``)."""
    dispersion_ratio: float | None = None
    """Ratio of that dispersion to the peak target speed; None: ``scaling.KINETIC_DISPERSION_RATIO`` (0.75)
    for a schema-2 map, whose kinetic mode realises the spread as a persistent deviation and needs it
    to dominate the tracking error near the throat (docs/simulation.md); 0.25
    (``scaling.DEFAULT_DISPERSION_RATIO``) for the paper's map."""
    agent_mass_kg: float = 1.0
    """Agent mass m_i [kg] in the fitting equations (paper: 1 kg)."""
    min_nodes: int = 1
    """Minimum reference nodes for a CV to exist."""
    staircase_contrast: float | None = DEFAULT_STAIRCASE_CONTRAST
    """Contrast C of the designed staircase (``fisc_ground.fit.staircase``): per axial slice, only the most
    covered cubes that make the swarm's continuity pattern follow the CFD's density pattern become CVs.
    None keeps every covered cube (DESIGN.md section 2).  Schema-1 maps (``staggered`` False, the paper's
    preset) always keep every covered cube."""
    alpha: float = 1.0
    """Weight of the pressure term in the fitting objective."""
    tolerance: float = 1e-6
    """Newton convergence tolerance on the update norm (paper: 1e-6)."""
    seed: int = 0
    """Seed of the perturbed initialisation."""
    map_version: int | None = None
    """Monotonic map version; None uses the creation time in milliseconds."""
    staggered: bool = True
    """Build the continuity-consistent face field and write a schema-2 map (``fisc_ground.fit.staggered``);
    False writes the paper's schema-1 map (``--preset paper``)."""
    continuity_weight: float | None = None
    """beta of the designed swarm density (``fisc_ground.fit.staggered.design_density``).  None: chosen by
    the build within the static field's velocity limit (``StaggeredConfig.continuity_weight``)."""
    density_amplitude: float | None = None
    """k of the designed swarm density: its contrast over the staircase's own
    (``fisc_ground.fit.staggered.StaggeredConfig.density_amplitude``; above 1 trades velocity for density
    fidelity).  None: chosen by the build within the static field's velocity budget."""
    weight_exponent: float = DEFAULT_WEIGHT_EXPONENT
    """p of the projection's lateral face weights (``fisc_ground.fit.staggered.project``)."""
    flight_mode: str = DEFAULT_FLIGHT.mode
    """Recommended command mode written into a schema-2 map (agents use it unless told otherwise)."""
    lookahead_s: float = DEFAULT_FLIGHT.lookahead_s
    """Recommended command look-ahead [s] written into a schema-2 map."""
    persistence_s: float = DEFAULT_FLIGHT.persistence_s
    """Recommended persistence of the kinetic deviation at length scale 1 [s] written into a schema-2 map
    (times ``length_scale``: a flow time, ``fisc_ground.fit.length_scale``)."""
    vehicle_radius_m: float = DEFAULT_VEHICLE_RADIUS_M
    """Vehicle radius r of the separation the map is designed for [m] (``fisc_agent.map.separation``)."""
    position_sigma_m: float = DEFAULT_POSITION_SIGMA_M
    """Relative position uncertainty sigma (1 sigma) of that separation [m]; d_min = 2 r + 3 sqrt(2) sigma."""
    length_scale: float = 1.0
    """L: fly the same flow in an airspace L times larger (lengths x L, velocities kept within
    ``max_speed_m_s``, times x L; ``fisc_ground.fit.length_scale``)."""

    @property
    def staggered_config(self) -> StaggeredConfig:
        """The staggered field's settings of this build (``fisc_ground.fit.staggered``)."""
        return StaggeredConfig(continuity_weight=self.continuity_weight, weight_exponent=self.weight_exponent,
                               density_amplitude=self.density_amplitude)

    @property
    def flight(self) -> FlightSettings:
        """The recommended flight settings this build writes (the paper's for a schema-1 map)."""
        if not self.staggered:
            return PAPER_SETTINGS
        return FlightSettings(self.flight_mode, self.lookahead_s, self.persistence_s)

    def __post_init__(self) -> None:
        FlightSettings(self.flight_mode, self.lookahead_s, self.persistence_s)  # validates
        self.staggered_config  # validates
        ratio = self.dispersion_ratio
        if ratio is not None and not (math.isfinite(ratio) and ratio > 0):
            raise ValueError(f"dispersion_ratio must be positive and finite, got {ratio!r}")
        c = self.staircase_contrast
        if c is not None and not 0.0 < c < 1.0:
            raise ValueError(f"staircase_contrast must lie in (0, 1) (None: every covered cube), got {c!r}")
        if not self.separation.d_min_m > 0:
            raise ValueError("vehicle_radius_m and position_sigma_m are both 0: d_min = 0 m designs no separation "
                             "(give a radius or a sigma > 0)")
        check_length_scale(self.length_scale)

    @property
    def separation(self) -> Separation:
        """The separation this build designs for (``fisc_agent.map.separation``)."""
        return Separation(self.vehicle_radius_m, self.position_sigma_m)




def fit_overrides(values: dict[str, Any]) -> dict[str, Any]:
    """``FitConfig`` overrides with the words ``auto`` and ``off`` read as None (chosen by the build, or
    switched off): how ``fisc-ground fit`` flags and ``fisc-sim sweep`` specs (TOML has no null) say it."""
    return {k: None if v in ("auto", "off") else v for k, v in values.items()}


def _mode(setting: float | None) -> str:
    """How a design setting of the map header came about: "auto" (None, chosen by the build) or "fixed"."""
    return "auto" if setting is None else "fixed"


def _software_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("fisc")
    except PackageNotFoundError:  # run from a source tree without installing
        return "0+unknown"


def build_map(field: ReferenceField, config: FitConfig = FitConfig()) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Partition, fit and scale; returns the map header fields and arrays (ready for ``encode_map``).

    With ``config.length_scale`` L the reference's lengths and the cube edge are L times larger
    (``fisc_ground.fit.length_scale``)."""
    length_scale = check_length_scale(config.length_scale)
    field = scale_reference(field, length_scale)
    cell_size = config.cell_size_m * length_scale
    cvs: ControlVolumes = partition_field(field, cell_size_m=cell_size, min_nodes=config.min_nodes,
                                          staircase_contrast=config.staircase_contrast if config.staggered else None)
    cell_volume = cell_size ** 3
    p = cvs.target_pressure_gauge_pa
    if config.kappa is None:
        ratio = config.dispersion_ratio
        if ratio is None:
            ratio = KINETIC_DISPERSION_RATIO if config.staggered else DEFAULT_DISPERSION_RATIO
        dispersion = (default_max_dispersion(cvs.target_velocity_m_s, ratio) if config.max_dispersion_m_s is None
                      else config.max_dispersion_m_s)
        kappa = choose_kappa(p, cell_volume, config.agent_mass_kg, config.n_min, dispersion)
    else:
        kappa = float(config.kappa)
    swarm_p = swarm_pressure_target(p, kappa)
    log.info("fitting %d CVs for N in [%d, %d]", p.size, config.n_min, config.n_max)
    fit = fit_velocities(cvs.target_velocity_m_s, swarm_p, cell_volume, config.agent_mass_kg,
                         n_min=config.n_min, n_max=config.n_max, alpha=config.alpha,
                         tol=config.tolerance, seed=config.seed)
    scale = choose_scale(fit.velocities_m_s, config.max_speed_m_s) if config.scale is None else float(config.scale)
    vel_rmse, p_rmse = fit_rmse(fit, cvs.target_velocity_m_s, swarm_p)
    arrays = {
        "cv_center_m": cvs.center_m,
        "cv_index": cvs.index,
        "grid_cv": cvs.grid_cv,
        "n_star": fit.n_star,
        "fit_velocity_m_s": fit.velocities_m_s,
        "fit_mean_velocity_m_s": fit.mean_velocity_m_s,
        "fit_pressure": fit.pressure,
        "fit_loss": fit.loss,
        "target_velocity_m_s": cvs.target_velocity_m_s,
        "target_pressure_gauge_pa": cvs.target_pressure_gauge_pa,
        "target_density_kg_m3": cvs.target_density_kg_m3,
        "swarm_pressure_target": swarm_p,
        "node_count": cvs.node_count,
        # optional (not in REQUIRED_ARRAYS): open-volume fraction A_j dx_j / l^3 of eq. swarm_density
        "cv_open_fraction": cv_open_fraction(cvs),
        # optional: the duct's real wall, where an onboard kinetic deviation turns (fisc_agent.map.wall)
        WALL_ARRAY: duct_wall_from_reference(field).as_array(),
    }
    extra = {}
    if config.staggered:
        sc = config.staggered_config
        st = build_staggered(cvs.grid_cv, cvs.target_velocity_m_s, cvs.target_density_kg_m3,
                             cvs.target_pressure_gauge_pa, arrays["cv_open_fraction"], sc)
        arrays.update(face_u_x_m_s=st.face_u_x_m_s, face_u_y_m_s=st.face_u_y_m_s, face_u_z_m_s=st.face_u_z_m_s,
                      cv_design_density=st.design_density)
        log.info("designed density: continuity weight %g (%s), amplitude %g (%s), static field velocity nRMSE "
                 "%.3f (budget %g, limit %g)", st.continuity_weight, _mode(sc.continuity_weight),
                 st.density_amplitude, _mode(sc.density_amplitude), st.static_velocity_nrmse, sc.velocity_budget,
                 sc.velocity_limit)
        f = config.flight
        extra = {"schema_version": 2,
                 "flight": {"mode": f.mode, "lookahead_s": f.lookahead_s,
                            "persistence_s": f.persistence_s * time_ratio(length_scale)},
                 "staggered": {"max_divergence": st.max_divergence, "continuity_weight": st.continuity_weight,
                               "continuity_weight_mode": _mode(sc.continuity_weight),
                               "weight_exponent": sc.weight_exponent, "axial_weight": sc.axial_weight,
                               "density_amplitude": st.density_amplitude,
                               "density_amplitude_mode": _mode(sc.density_amplitude),
                               "velocity_budget": sc.velocity_budget, "velocity_limit": sc.velocity_limit,
                               "static_velocity_nrmse": st.static_velocity_nrmse,
                               "staircase_contrast": cvs.staircase_contrast,
                               "staircase_min_step_open": (None if cvs.staircase_contrast is None
                                                           else DEFAULT_MIN_STEP_OPEN)}}
    else:
        extra = {"schema_version": 1}
    sep = config.separation
    budget = separation_budget(cvs.index, relative_density(arrays.get("cv_design_density"), cvs.target_density_kg_m3),
                               scale * cvs.target_velocity_m_s[:, 0], cell_size, sep.d_min_m)
    log.info("separation: d_min %.3g m, at most %d vehicles in the tunnel, one admitted per %.3g s (%s)",
             sep.d_min_m, budget.max_in_tunnel, budget.admission_period_s, budget.limit.value)
    now = datetime.now(timezone.utc)
    meta = {
        "map_version": int(config.map_version if config.map_version is not None else time.time() * 1000),
        "created_utc": now.isoformat(timespec="seconds"),
        "software_version": _software_version(),
        "frame": {"name": "reference", "axis": [1.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0]},
        "n_cv": int(cvs.center_m.shape[0]),
        "grid": {"origin_m": [float(v) for v in cvs.origin_m], "cell_size_m": float(cell_size),
                 "shape": [int(s) for s in cvs.grid_cv.shape]},
        "n_range": [int(config.n_min), int(config.n_max)],
        "scale": float(scale),
        "kappa": float(kappa),
        "agent_mass_kg": float(config.agent_mass_kg),
        "max_speed_m_s": float(config.max_speed_m_s),
        "length_scale": float(length_scale),
        "separation": {"vehicle_radius_m": float(sep.vehicle_radius_m), "position_sigma_m": float(sep.position_sigma_m),
                       **budget.as_header()},
        "fit": {
            "seconds": float(fit.seconds),
            "velocity_rmse": float(vel_rmse),
            "pressure_rmse": float(p_rmse),
            "tolerance": float(config.tolerance),
            "alpha": float(config.alpha),
            "converged_fraction": float(np.mean(fit.converged)),
            "max_iterations": int(np.max(fit.iterations)) if fit.iterations.size else 0,
        },
        "provenance": {
            "reference": {"name": field.name, "source": field.source, "sha256": field.source_sha256,
                          "pressure_kind": field.pressure_kind, "n_nodes": field.n_nodes},
            "config": {k: v for k, v in asdict(config).items()},
        },
        **extra,
    }
    return meta, arrays


def build_map_from_reference(spec: str, config: FitConfig = FitConfig(),
                             signing_key: bytes | None = None) -> CommandMap:
    """Load ``spec`` (built-in name or path), build, encode and verify a map in memory."""
    meta, arrays = build_map(load_reference(spec), config)
    data = encode_map(meta, arrays, signing_key)
    return decode_map(data, source=f"map of {spec}")


def default_map_path() -> Path:
    """Path of the shipped embedded-default map (``field_maps/default.fiscmap``)."""
    return Path(str(resources.files("field_maps").joinpath(DEFAULT_MAP_FILE)))


def build_default_map(config: FitConfig = FitConfig()) -> CommandMap:
    """The embedded default: the built-in inviscid reference fitted with ``config`` (milliseconds)."""
    return build_map_from_reference(DEFAULT_REFERENCE, config)


def load_shipped_default_map() -> CommandMap:
    """The ready-made default map shipped in ``field_maps/`` (for agents without a ground station)."""
    return load_map(default_map_path())
