"""Pressure mapping (kappa) and speed scaling (S) of the command map, DESIGN.md section 3.

Order of use (fisc_ground.maps.build):

1. ``max_dispersion = default_max_dispersion(target_velocity)`` (or a deployment value);
2. ``kappa = choose_kappa(P_cfd, dV, m, n_min, max_dispersion)``;
3. ``P_target = swarm_pressure_target(P_cfd, kappa)``  ->  fitting.fit_velocities(...);
4. ``S = choose_scale(fit.velocities_m_s, max_speed_m_s)``; commands are ``S * v``.

Why these defaults.  The swarm pressure (eq. pressure_constraint) is realised by a velocity
spread: a CV fitted with N agents needs a per-agent rms deviation
``sigma_N = sqrt(P_target 3 dV / (2 m N))`` from its mean.  kappa fixes the largest such spread
over the map (worst CV, fewest agents N = n_min) to ``max_dispersion``, set by default to
``DEFAULT_DISPERSION_RATIO = 0.25`` of the largest target speed: after the common speed scaling S
the spread stays a quarter of the peak mean command, large enough to carry the pressure
pattern, small enough that the flow direction dominates every command.  Then S is the largest
factor that keeps every commanded vector (mean plus deviation) within the agent's speed limit,
so ``S (|mean| + deviation) <= max_speed`` holds by construction.  DEFAULT_MAX_SPEED_M_S = 2 m/s
is the paper's own speed regime (S = 0.1 on 22.4 m/s peaks) and the low end of its 2-10 m/s flyable
range: the vehicles' ~0.58 s response lag then costs about a CV of lag distance instead of five at
5 m/s (docs/studies/fidelity.md, "Defaults chosen").  ``fisc-ground fit`` and ``fisc-sim run`` share it, so
the map a user fits is the map the simulator's default run flies; the inviscid reference gets
S of about 0.13 (schema 2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Default agent speed limit for the commands [m/s] (paper: agents fly 2-10 m/s; see the module docstring).
DEFAULT_MAX_SPEED_M_S = 2.0
#: Default largest per-agent rms velocity deviation, as a fraction of the largest target speed.
DEFAULT_DISPERSION_RATIO = 0.25
#: The same for schema-2 maps (``FitConfig.dispersion_ratio``): their kinetic mode realises the spread
#: as a persistent deviation, which must dominate the tracking error near the throat.
KINETIC_DISPERSION_RATIO = 0.75


@dataclass(frozen=True)
class Scaling:
    """The two scale factors of a command map and the limits they were chosen for."""

    kappa: float
    """Pressure mapping: swarm pressure target = kappa (P_cfd - min P_cfd) (swarm Pa per CFD Pa)."""
    scale: float
    """Speed scale S: commanded velocity = S * fitted velocity (dimensionless)."""
    max_speed_m_s: float
    """Agent speed limit every scaled command respects [m/s]."""
    max_dispersion_m_s: float
    """Largest per-agent rms velocity deviation the fit asks for, before scaling by S [m/s]."""


def swarm_pressure_target(pressure_gauge_pa: np.ndarray, kappa: float) -> np.ndarray:
    """Swarm pressure target per CV, the affine map of DESIGN.md section 3.

    ``P_target = kappa (P_cfd - min P_cfd)``: >= 0 everywhere (as every swarm pressure is),
    zero at the CV of lowest CFD pressure, and the CFD pattern kept.
    """
    p = np.asarray(pressure_gauge_pa, dtype=np.float64)
    if p.size == 0:
        return p.copy()
    if not np.all(np.isfinite(p)):
        j = int(np.flatnonzero(~np.isfinite(p))[0])
        raise ValueError(f"CV {j}: CFD pressure is not finite: {float(p[j])!r}")
    return float(kappa) * (p - p.min())


def default_max_dispersion(
    target_velocity_m_s: np.ndarray, ratio: float = DEFAULT_DISPERSION_RATIO
) -> float:
    """Default flyable dispersion: ``ratio`` times the largest target speed |v_target| [m/s]."""
    v = np.asarray(target_velocity_m_s, dtype=np.float64).reshape(-1, 3)
    if v.shape[0] == 0 or not np.all(np.isfinite(v)):
        raise ValueError("target velocities must be a non-empty finite (n, 3) array")
    if not (np.isfinite(ratio) and ratio > 0):
        raise ValueError(f"dispersion ratio must be positive and finite, got {ratio!r}")
    return float(ratio * np.max(np.linalg.norm(v, axis=1)))


def choose_kappa(
    pressure_gauge_pa: np.ndarray,
    cell_volume_m3: float,
    agent_mass_kg: float,
    n_min: int,
    max_dispersion_m_s: float,
) -> float:
    """kappa such that the largest per-agent dispersion the fit asks for is ``max_dispersion_m_s``.

    The worst case is the CV of largest swarm pressure target ``P_max = kappa (max P - min P)``
    fitted with the fewest agents n_min: ``sigma_max = sqrt(P_max 3 dV / (2 m n_min))``.
    Solving ``sigma_max = max_dispersion`` gives
    ``kappa = max_dispersion^2 2 m n_min / (3 dV (max P - min P))``.  When the CFD pressure is
    uniform (range 0) every target is 0 whatever kappa is, and 1.0 is returned.
    """
    p = np.asarray(pressure_gauge_pa, dtype=np.float64)
    if p.size == 0 or not np.all(np.isfinite(p)):
        raise ValueError("CFD pressures must be a non-empty finite array")
    for name, val in (("cell_volume_m3", cell_volume_m3), ("agent_mass_kg", agent_mass_kg),
                      ("max_dispersion_m_s", max_dispersion_m_s)):
        if not (np.isfinite(val) and val > 0):
            raise ValueError(f"{name} must be positive and finite, got {val!r}")
    if int(n_min) < 1:
        raise ValueError(f"n_min must be >= 1, got {n_min!r}")
    span = float(p.max() - p.min())
    if span == 0.0:
        return 1.0
    return float(max_dispersion_m_s**2 * 2.0 * agent_mass_kg * int(n_min) / (3.0 * cell_volume_m3 * span))


def choose_scale(
    fit_velocities_m_s: np.ndarray,
    max_speed_m_s: float = DEFAULT_MAX_SPEED_M_S,
    max_scale: float | None = None,
) -> float:
    """Largest S with ``S |v_k| <= max_speed_m_s`` for every fitted vector v_k (NaN rows ignored).

    ``fit_velocities_m_s`` is any (..., 3) array, e.g. ``FitResult.velocities_m_s``; the fitted
    means are convex combinations of the vectors, so mean commands are within the limit too.
    ``max_scale`` optionally caps S (e.g. 1.0 to never speed the flow up).  If every vector is
    zero, S = ``max_scale`` or 1.0.
    """
    if not (np.isfinite(max_speed_m_s) and max_speed_m_s > 0):
        raise ValueError(f"max_speed_m_s must be positive and finite, got {max_speed_m_s!r}")
    v = np.asarray(fit_velocities_m_s, dtype=np.float64).reshape(-1, 3)
    present = np.all(np.isfinite(v), axis=1)
    if not present.any():
        raise ValueError("no finite fitted velocity to scale")
    peak = float(np.max(np.linalg.norm(v[present], axis=1)))
    s = max_speed_m_s / peak if peak > 0 else (1.0 if max_scale is None else float(max_scale))
    if max_scale is not None:
        s = min(s, float(max_scale))
    return float(s)
