"""The separation budget of a map (pure numerics, issue 37): how many vehicles the tunnel holds at
once, and how often the inlet admits one, so that the swarm keeps the designed spacing d_min
(``fisc_agent.map.separation``).

Model.
- **Where the swarm is.**  The swarm fills the map's CVs (cubes of edge l) at the map's *designed*
  relative density rho_j (``cv_design_density``, mean 1 over the CVs; a schema-1 map without it: the
  CFD density, normalised to mean 1).  With N vehicles in the tunnel, CV j holds on average
  ``N rho_j / sum_k rho_k`` of them, a number density ``n_j = N rho_j / (l^3 sum_k rho_k)``.
- **Nearest neighbour.**  Within a CV the vehicles are taken as a Poisson gas (independent uniform
  positions: the kinetic mode's persistent random deviations): its nearest-neighbour distance has
  ``P(NN > d) = exp(-4 pi n d^3 / 3)`` and mean ``E[NN] = Gamma(4/3) (4 pi n / 3)^(-1/3)``
  (``poisson_nn_mean_m``).
- **The largest swarm.**  ``max_in_tunnel`` is the largest N (at least 1: a lone vehicle has no
  neighbour) whose densest CV keeps ``E[NN] >= d_min``.  This is a mean, not a bound: a Poisson gas
  at that density still has a neighbour inside d_min for a fraction ``1 - exp(-Gamma(4/3)^3)`` (about
  one half) of its vehicles at any instant (``near_fraction``, recorded so that nobody mistakes it for
  a guarantee).  The ordered admission (one vehicle per window, each on its own entry point) is what
  spaces the swarm better than a gas; the near-miss counts of ``fisc-sim run`` and the monitor measure
  how much better.
- **Admission (a flux budget).**  By Little's law N = lambda tau: a swarm admitted at lambda vehicles per
  second, each staying the mean transit time tau, holds lambda tau vehicles.  tau is the designed
  residence time ``l sum_j rho_j / Q`` with Q the mean over axial slices of the designed axial flux
  ``sum_{j in slice} rho_j u_j`` (by continuity the same in every slice of a schema-2 map; u_j the
  CV's scaled axial command [m/s]).  The flux period is ``tau / max_in_tunnel``.  The inlet adds a
  floor: vehicles admitted one after another must enter at least d_min apart along the axis at the
  inlet's designed speed u_in, and an agent starts across in the first ``ENTRY_OPEN_FRACTION`` of its
  window (``fisc_agent.flight.spacing.entry_slot_open``) and within ``ENTRY_TIMING_TOLERANCE_S`` of
  its due time (a real vehicle's lag), so two consecutive entries are ``(1 - ENTRY_OPEN_FRACTION) x
  period - ENTRY_TIMING_TOLERANCE_S`` apart: the inlet period is
  ``(d_min / u_in + ENTRY_TIMING_TOLERANCE_S) / (1 - ENTRY_OPEN_FRACTION)``.  The admission period is the larger of the two
  (``limit`` says which); admitted at it, the tunnel holds ``tau / period`` vehicles on average.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from enum import StrEnum

import numpy as np

from fisc_agent.flight.spacing import ENTRY_OPEN_FRACTION, ENTRY_TIMING_TOLERANCE_S

GAMMA_4_3 = math.gamma(4.0 / 3.0)
"""Gamma(4/3) = 0.8930 of the Poisson gas's mean nearest-neighbour distance."""


class AdmissionLimit(StrEnum):
    """Which constraint sets a map's admission period."""

    FLUX = "flux"
    """The flux budget: tau / max_in_tunnel."""
    INLET = "inlet"
    """The inlet floor: consecutive entries d_min apart along the axis."""


def poisson_nn_mean_m(number_density_per_m3: float) -> float:
    """Mean nearest-neighbour distance of a Poisson gas of ``number_density_per_m3`` points per m^3:
    ``Gamma(4/3) (4 pi n / 3)^(-1/3)`` [m]; +inf for n = 0."""
    n = float(number_density_per_m3)
    if not (math.isfinite(n) and n >= 0):
        raise ValueError(f"number density must be a finite number >= 0 per m^3, is {number_density_per_m3!r}")
    return math.inf if n == 0 else GAMMA_4_3 * (4.0 * math.pi * n / 3.0) ** (-1.0 / 3.0)


def poisson_density_for_nn(nn_m: float) -> float:
    """The number density [1/m^3] whose Poisson mean nearest-neighbour distance is ``nn_m`` (the
    inverse of ``poisson_nn_mean_m``): ``3 / (4 pi) (Gamma(4/3) / d)^3``."""
    d = float(nn_m)
    if not (math.isfinite(d) and d > 0):
        raise ValueError(f"nearest-neighbour distance must be a finite number > 0 m, is {nn_m!r}")
    return 3.0 / (4.0 * math.pi) * (GAMMA_4_3 / d) ** 3


def near_fraction(number_density_per_m3: float, d_m: float) -> float:
    """Fraction of a Poisson gas's points with a neighbour closer than ``d_m``: ``1 - exp(-4 pi n d^3 / 3)``."""
    return -math.expm1(-4.0 * math.pi * float(number_density_per_m3) * float(d_m) ** 3 / 3.0)


@dataclass(frozen=True)
class SeparationBudget:
    """What a map allows at a spacing d_min (header ``separation``, beside the radius and sigma)."""

    d_min_m: float
    """The spacing designed for [m] (``fisc_agent.map.separation.d_min_m``)."""
    max_in_tunnel: int
    """Largest number of vehicles in the tunnel at once whose densest CV keeps E[NN] >= d_min (>= 1)."""
    densest_nn_m: float
    """Expected nearest-neighbour distance in the densest CV with ``max_in_tunnel`` vehicles [m]."""
    near_fraction: float
    """Fraction of the densest CV's vehicles with a neighbour inside d_min at that swarm (Poisson gas)."""
    mean_transit_s: float
    """Designed mean residence time tau in the tunnel [s]."""
    flux_period_s: float
    """tau / ``max_in_tunnel``: the admission period of the flux budget [s]."""
    inlet_period_s: float
    """(d_min / u_in + ENTRY_TIMING_TOLERANCE_S) / (1 - ENTRY_OPEN_FRACTION): consecutive entries d_min
    apart along the axis [s]."""
    admission_period_s: float
    """One vehicle admitted per this period: the larger of the two [s]."""
    limit: AdmissionLimit
    """Which period sets the admission."""
    in_tunnel_admitted: float
    """Mean number of vehicles in the tunnel when admitted at ``admission_period_s`` (tau / period)."""
    tunnel_volume_m3: float
    """Volume of the map's CVs [m^3]."""
    inlet_speed_m_s: float
    """Designed axial speed u_in of the inlet slice [m/s]."""

    def as_header(self) -> dict:
        """The fields for the map header's ``separation`` table (JSON numbers and strings)."""
        return {k: (int(v) if k == "max_in_tunnel" else str(v) if k == "limit" else float(v))
                for k, v in asdict(self).items()}


def relative_density(design_density: np.ndarray | None, target_density: np.ndarray) -> np.ndarray:
    """The designed relative swarm density per CV, mean 1: ``cv_design_density`` where the map has one,
    else the CFD density normalised to mean 1 (a schema-1 map)."""
    rho = np.asarray(target_density if design_density is None else design_density, dtype=float)
    if rho.ndim != 1 or rho.size == 0 or not np.all(np.isfinite(rho)) or not np.all(rho > 0):
        raise ValueError("separation budget: the relative density must be a non-empty array of finite values > 0")
    return rho / rho.mean()


def slice_fluxes(cv_index: np.ndarray, rho: np.ndarray, u_axial_m_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per occupied axial slice (ascending x index): the designed axial flux sum rho_j u_j [m/s] and
    the density-weighted mean axial speed sum rho u / sum rho [m/s]."""
    ix = np.asarray(cv_index)[:, 0]
    slices, inv = np.unique(ix, return_inverse=True)
    flux = np.bincount(inv, weights=rho * u_axial_m_s, minlength=slices.size)
    mass = np.bincount(inv, weights=rho, minlength=slices.size)
    return flux, flux / mass


def separation_budget(cv_index: np.ndarray, rho: np.ndarray, u_axial_m_s: np.ndarray, cell_size_m: float,
                      d_min_m: float) -> SeparationBudget:
    """The budget of a map whose CVs (grid indices ``cv_index`` (n, 3), edge ``cell_size_m``) carry the
    relative density ``rho`` (``relative_density``) and the scaled axial command ``u_axial_m_s``."""
    l, d = float(cell_size_m), float(d_min_m)
    if not (math.isfinite(l) and l > 0):
        raise ValueError(f"separation budget: the cell size must be > 0 m, is {cell_size_m!r}")
    if not (math.isfinite(d) and d > 0):
        raise ValueError(f"separation budget: d_min must be a finite number > 0 m, is {d_min_m!r}")
    rho, u = np.asarray(rho, dtype=float), np.asarray(u_axial_m_s, dtype=float)
    if rho.shape != u.shape or rho.shape != (len(cv_index),) or not np.all(np.isfinite(u)):
        raise ValueError("separation budget: cv_index, rho and u_axial need one finite row per CV")
    flux, slice_speed = slice_fluxes(cv_index, rho, u)
    q = float(flux.mean())
    if not q > 0:
        raise ValueError(f"separation budget: the map has no net axial flow (mean slice flux {q:g} m/s)")
    u_in = float(slice_speed[0])
    if not u_in > 0:
        raise ValueError(f"separation budget: the inlet slice flows backwards or not at all (u_in {u_in:g} m/s)")
    vol = l ** 3
    total = float(rho.sum())
    n_allowed = poisson_density_for_nn(d)            # densest CV's number density at E[NN] = d_min
    rho_max = float(rho.max())
    n_max = max(1, math.floor(n_allowed * vol * total / rho_max * (1.0 + 1e-12)))
    n_dense = n_max * rho_max / (vol * total)
    tau = l * total / q
    flux_period = tau / n_max
    inlet_period = (d / u_in + ENTRY_TIMING_TOLERANCE_S) / (1.0 - ENTRY_OPEN_FRACTION)
    period = max(flux_period, inlet_period)
    return SeparationBudget(
        d_min_m=d, max_in_tunnel=int(n_max), densest_nn_m=poisson_nn_mean_m(n_dense),
        near_fraction=near_fraction(n_dense, d), mean_transit_s=tau, flux_period_s=flux_period,
        inlet_period_s=inlet_period, admission_period_s=period,
        limit=AdmissionLimit.FLUX if flux_period >= inlet_period else AdmissionLimit.INLET, in_tunnel_admitted=tau / period,
        tunnel_volume_m3=vol * rho.size, inlet_speed_m_s=u_in)
