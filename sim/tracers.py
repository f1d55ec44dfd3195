"""Ideal tracers through a staggered command field: the density a swarm without lag would hold.

A tracer moves exactly with the field, dx/dt = u(x) (``CommandField.staggered_at``: no vehicle lag,
no kinetic deviation).  Tracers are seeded on a regular m x m grid of points on every inlet face of
the first slice, each carrying the number flux the design sends through its patch of the face,
rho_d u_x dA (the inlet CV's designed density times the face's axial velocity).  In steady state a
CV then holds density sum_i q_i t_ij / l^3, t_ij being the time tracer i spends in CV j: in the
design's own units, so a field that carries its design gives back ``cv_design_density`` itself,
not just its pattern.

Why: ``fisc_ground.fit.staggered.project`` makes the discrete divergence of rho_d u vanish in every CV,
and inside a cube each component runs linearly between its two faces.  Whether tracers then keep
the designed density is a property of the field alone; this module measures it, so that the swarm's
departures from the design can be split into what the field does and what the vehicles do
(``benchmarks/density_profile.py``, docs/studies/density_study.md).  The forward-Euler integrator holds each
velocity over its step, as a vehicle without lag flying commands streamed every ``dt_s``.

Pure numerics: arrays in, arrays out; vectorised over tracers (numpy).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from fisc_agent.map.lookup import CommandField

#: A prime that shuffles the first-step phases of a face's seeds (coprime with any seed count below it).
PHASE_STRIDE = 7919


class Integrator(enum.Enum):
    """How a tracer's path is integrated."""

    RK4 = "rk4"
    """Classical 4th-order Runge-Kutta: the exact path to the step's accuracy."""
    EULER = "euler"
    """Forward Euler: the velocity at the start of a step held over the step (a vehicle without lag
    that receives a new command every ``dt_s``)."""


@dataclass(frozen=True)
class TracerDensity:
    """Steady tracer density per CV (``tracer_density``)."""

    density: np.ndarray
    """(n_cv,) number density in the units of the designed density (its mean over CVs is 1 when
    the field carries its design) [-]."""
    inflow: float
    """Total number flux seeded at the inlet, sum of rho_d u_x dA [m^3/s in design units]."""
    lost_fraction: float
    """Fraction of the inflow that left the CVs elsewhere than through the outlet, or was still
    inside after ``max_time_s`` [-]."""
    tracers: int
    """Tracers seeded."""


def inlet_seeds(field: CommandField, design_density: np.ndarray,
                seeds_per_axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Seed points (n, 3) just inside the inlet faces of the first slice and the number flux (n,) each
    carries, rho_d u_x dA, on a regular ``seeds_per_axis`` x ``seeds_per_axis`` grid per face (cell
    midpoints of the face's sub-squares).  Faces with inflow u_x <= 0 get no seeds."""
    if seeds_per_axis < 1:
        raise ValueError(f"seeds_per_axis must be >= 1, got {seeds_per_axis!r}")
    if field.face_u_m_s is None:
        raise ValueError("the field has no staggered face velocities (a schema-1 map)")
    rho = np.asarray(design_density, dtype=float)
    if rho.shape != (field.n_cv,) or not np.all(np.isfinite(rho)) or not np.all(rho > 0):
        raise ValueError(f"design_density must hold {field.n_cv} finite values > 0")
    grid = np.asarray(field.grid_cv)
    j, k = np.nonzero(grid[0] >= 0)
    u_in = field.face_u_m_s[0][0, j, k]
    flowing = u_in > 0
    j, k, u_in = j[flowing], k[flowing], u_in[flowing]
    cv = grid[0, j, k]
    h = float(field.cell_size_m)
    sub = (np.arange(seeds_per_axis) + 0.5) / seeds_per_axis
    a, b = (g.ravel() for g in np.meshgrid(sub, sub, indexing="ij"))
    o = np.asarray(field.origin_m, dtype=float)
    pts = np.empty((j.size, a.size, 3))
    pts[..., 0] = o[0] + 1e-9 * h
    pts[..., 1] = o[1] + (j[:, None] + a[None, :]) * h
    pts[..., 2] = o[2] + (k[:, None] + b[None, :]) * h
    flux = np.repeat(rho[cv] * u_in * (h / seeds_per_axis) ** 2, a.size)
    return pts.reshape(-1, 3), flux


def tracer_density(field: CommandField, design_density: np.ndarray, seeds_per_axis: int = 8, dt_s: float = 0.02,
                   integrator: Integrator = Integrator.RK4, max_time_s: float = 600.0) -> TracerDensity:
    """Steady density of ideal tracers in ``field`` (see the module docstring).

    ``design_density`` (n_cv,) rho_d, used for the inflow (the inlet CVs' designed density); ``dt_s``
    the integration step [s]; tracers still inside after ``max_time_s`` count as lost.  Residence
    time is booked to the CV a tracer is in at the start of each step; the tracers' first steps are
    staggered over [0, dt) so that this booking averages out over the tracers."""
    if not (dt_s > 0 and np.isfinite(dt_s)):
        raise ValueError(f"dt_s must be finite and > 0, got {dt_s!r}")
    integrator = Integrator(integrator)
    pts, flux = inlet_seeds(field, design_density, seeds_per_axis)
    x_out = float(field.origin_m[0] + np.asarray(field.grid_cv).shape[0] * field.cell_size_m)

    def velocity(p: np.ndarray) -> np.ndarray:
        rows, frac, _ = field.locate(p)
        return field.staggered_at(rows, frac)

    booked = np.zeros(field.n_cv)
    lost = 0.0
    # the first step of tracer i lasts phi_i dt, the m^2 seeds of each face taking the phases
    # (r + 1/2) / m^2 (r = 0 .. m^2 - 1, shuffled over the face): tracers seeded together do not cross
    # the CV faces in step, and booking each step wholly to the CV it starts in averages out over each
    # face's seeds.  The first, partial step stands for the step in which the tracer crossed the inlet,
    # so it is booked as such a step is: to the side it started on (the reservoir, no CV)
    m2 = seeds_per_axis ** 2
    rank = (np.arange(flux.size) % m2) * PHASE_STRIDE % m2
    step = dt_s * ((rank + 0.5) / m2)[:, None]
    p, q = pts, flux
    rows, frac, cv = field.locate(p)
    t = 0.0
    while q.size and t < max_time_s:
        if t > 0:
            booked += np.bincount(cv, weights=q, minlength=field.n_cv) * dt_s
        k1 = field.staggered_at(rows, frac)
        if integrator is Integrator.EULER:
            p = p + step * k1
        else:
            k2 = velocity(p + 0.5 * step * k1)
            k3 = velocity(p + 0.5 * step * k2)
            k4 = velocity(p + step * k3)
            p = p + (step / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        t += dt_s
        rows, frac, cv = field.locate(p)  # where the next step starts
        inside = cv >= 0
        lost += float(q[~inside & (p[:, 0] < x_out)].sum())
        p, q, rows, frac, cv = p[inside], q[inside], rows[inside], frac[inside], cv[inside]
        step = np.full((q.size, 1), dt_s)
    lost += float(q.sum())
    total = float(flux.sum())
    return TracerDensity(density=booked / field.cell_size_m ** 3, inflow=total,
                         lost_fraction=lost / total if total > 0 else 0.0, tracers=int(flux.size))
