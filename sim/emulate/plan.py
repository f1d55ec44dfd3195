"""Launch plan (start grid, staggered launches at the source rate) and the map the agents load."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fisc_agent.flight.control import MapGeometry, ScalarField, entry_points
from fisc_agent.flight.routes import join_waypoints
from fisc_agent.flight.frames import DeploymentTransform
from fisc_agent.map.lookup import CommandField
from fisc_agent.map.codec import MAGIC, CommandMap, load_map
from fisc_agent.common.safe_files import read_head
from sim.scenarios import Reservoir, scale_for_agents
from sim.emulate.config import LAUNCH_OVERHEAD_S, MAP_FILE_NAME



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
    join path (``fisc_agent.flight.routes.join_waypoints`` to its ``entry_point``) at ``join_speed_m_s``.
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
    entries = entry_points(geom, sfield, entry_radius_fraction)  # agent i enters at entry_point(i, ...)
    for i in range(n_agents):  # once, at set-up (not a hot path)
        entry = entries[i % len(entries)]
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
    from fisc_ground.maps.build import DEFAULT_REFERENCE, FitConfig, build_map
    from fisc_ground.maps.write import write_map
    from fisc_ground.reference.load import load_reference

    meta, arrays = build_map(load_reference(spec or DEFAULT_REFERENCE), FitConfig(staggered=preset != "paper"))
    path = out_dir / MAP_FILE_NAME
    write_map(path, meta, arrays)
    return path, load_map(path)
