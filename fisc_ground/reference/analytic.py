"""Dependency-free analytic reference: quasi-1-D isentropic flow through any body of revolution.

Model (subsonic, perfect gas, numpy only):

* Inlet: uniform axial velocity ``u_in`` and static temperature ``T_in``; outlet static pressure
  ``p_out``. Stagnation temperature ``T0 = T_in + u_in^2 / (2 cp)``, ``cp = gamma R / (gamma-1)``.
* Area-Mach relation (subsonic branch) ``A/A* = (1/M) [2/(gamma+1) (1 + (gamma-1)/2 M^2)]^k``,
  ``k = (gamma+1) / (2 (gamma-1))``, with ``A*`` fixed by the inlet Mach number.
* Isentropic relations: ``T = T0 / (1 + (gamma-1)/2 M^2)``, ``p = p0 (T/T0)^(gamma/(gamma-1))``
  with ``p0`` fixed by ``p_out`` at the outlet Mach number, ``rho = p / (R T)``, ``u = M a``.
* 3-D field: the axial velocity is uniform over a section; the radial velocity follows the
  streamline slope, ``u_r = u_x (r / R) dR/dx`` (streamlines are the scaled wall shape).

Also holds :func:`body_lattice`, the 0.1 m Cartesian node lattice inside a body of revolution
that the Fluent-style export uses; the axisymmetric importer samples on the same lattice.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fisc_ground.reference.field import P_REF_PA, ReferenceError, ReferenceField

#: Ratio of specific heats of air.
GAMMA_AIR = 1.4
#: Specific gas constant of air [J/(kg K)].
R_GAS_AIR_J_KG_K = 287.05
#: DESIGN.md section 2 tunnel: length [m], inlet velocity [m/s], inlet temperature [K].
TUNNEL_LENGTH_M = 15.0
TUNNEL_INLET_VELOCITY_M_S = 3.38
TUNNEL_INLET_TEMPERATURE_K = 300.0
#: Default lattice spacing of the node lattice [m] (that of the Fluent-style export).
LATTICE_SPACING_M = 0.1
#: Lattice nodes closer than this to the wall (or outside) are excluded [m].
WALL_TOLERANCE_M = 1.0e-5


def tunnel_radius_m(x_m: np.ndarray | float) -> np.ndarray:
    """Radius R(x) [m] of the DESIGN.md section 2 converging-diverging tunnel (vectorised).

    ``R = 0.75 + 0.375 (1 + cos(pi x / 6))`` for x <= 6, ``0.75 + 0.375 (1 - cos(pi (x-6) / 9))``
    for x > 6 (inlet 1.5 m, throat 0.75 m at x = 6, outlet 1.5 m at x = 15).
    """
    x = np.asarray(x_m, dtype=float)
    return np.where(x <= 6.0, 0.75 + 0.375 * (1.0 + np.cos(np.pi * x / 6.0)),
                    0.75 + 0.375 * (1.0 - np.cos(np.pi * (x - 6.0) / 9.0)))


def tunnel_radius_slope(x_m: np.ndarray | float) -> np.ndarray:
    """dR/dx [-] of :func:`tunnel_radius_m` (vectorised, exact)."""
    x = np.asarray(x_m, dtype=float)
    return np.where(x <= 6.0, -0.375 * np.pi / 6.0 * np.sin(np.pi * x / 6.0),
                    0.375 * np.pi / 9.0 * np.sin(np.pi * (x - 6.0) / 9.0))


def _numeric_slope(radius_m: Callable, x: np.ndarray) -> np.ndarray:
    """Central-difference dR/dx of an arbitrary radius callable."""
    h = 1e-6 * max(1.0, float(np.abs(x).max()))
    return (np.asarray(radius_m(x + h), float) - np.asarray(radius_m(x - h), float)) / (2 * h)


def subsonic_mach_from_area_ratio(area_ratio: np.ndarray, gamma: float = GAMMA_AIR) -> np.ndarray:
    """Subsonic root M in (0, 1] of the area-Mach relation A/A* = f(M) (vectorised Newton).

    Solves ``ln f(M) = ln(A/A*)`` with ``ln f = -ln M + k ln((2 + (gamma-1) M^2)/(gamma+1))``,
    which is strictly decreasing on (0, 1); raises ``ValueError`` for ``A/A* < 1``.
    """
    a = np.asarray(area_ratio, dtype=float)
    if np.any(~np.isfinite(a)) or np.any(a < 1.0 - 1e-12):
        raise ValueError("area ratio A/A* must be finite and >= 1 (the flow would choke)")
    k = (gamma + 1.0) / (2.0 * (gamma - 1.0))
    log_a = np.log(np.maximum(a, 1.0))
    # small-M asymptote as the initial guess (always below the root: ln f is decreasing)
    m = np.minimum(np.exp(k * np.log(2.0 / (gamma + 1.0)) - log_a), 1.0)
    for _ in range(100):
        g = -np.log(m) + k * np.log((2.0 + (gamma - 1.0) * m * m) / (gamma + 1.0)) - log_a
        dg = -1.0 / m + k * 2.0 * (gamma - 1.0) * m / (2.0 + (gamma - 1.0) * m * m)
        step = np.where(dg < 0.0, g / np.where(dg < 0.0, dg, -1.0), 0.0)
        m_new = np.clip(m - step, 0.5 * m, 1.0)
        done = np.all(np.abs(m_new - m) <= 1e-15 * m_new)
        m = m_new
        if done:
            break
    return m


def area_mach_ratio(mach: np.ndarray, gamma: float = GAMMA_AIR) -> np.ndarray:
    """A/A* for Mach number M (the isentropic area-Mach relation)."""
    m = np.asarray(mach, dtype=float)
    k = (gamma + 1.0) / (2.0 * (gamma - 1.0))
    return (1.0 / m) * ((2.0 / (gamma + 1.0)) * (1.0 + 0.5 * (gamma - 1.0) * m * m)) ** k


@dataclass(frozen=True)
class Quasi1DFlow:
    """Quasi-1-D isentropic solution along x (all arrays shaped like ``x_m``)."""

    x_m: np.ndarray
    """Axial stations [m]."""
    radius_m: np.ndarray
    """Wall radius R(x) [m]."""
    area_m2: np.ndarray
    """Section area pi R^2 [m^2]."""
    mach: np.ndarray
    """Mach number [-]."""
    velocity_m_s: np.ndarray
    """Axial velocity u(x) [m/s]."""
    pressure_pa: np.ndarray
    """Absolute static pressure [Pa]."""
    density_kg_m3: np.ndarray
    """Density [kg/m^3]."""
    temperature_k: np.ndarray
    """Static temperature [K]."""
    stagnation_temperature_k: float
    """T0 [K]."""
    stagnation_pressure_pa: float
    """p0 [Pa]."""
    mass_flow_kg_s: float
    """rho u A [kg/s] (constant along x)."""
    gamma: float
    """Ratio of specific heats."""
    r_gas_j_kg_k: float
    """Specific gas constant [J/(kg K)]."""


def isentropic_quasi_1d(x_m: np.ndarray, radius_m: np.ndarray,
                        inlet_velocity_m_s: float = TUNNEL_INLET_VELOCITY_M_S,
                        inlet_temperature_k: float = TUNNEL_INLET_TEMPERATURE_K,
                        outlet_pressure_pa: float = P_REF_PA, gamma: float = GAMMA_AIR,
                        r_gas_j_kg_k: float = R_GAS_AIR_J_KG_K) -> Quasi1DFlow:
    """Subsonic quasi-1-D isentropic flow through sections of radius ``radius_m`` at ``x_m``.

    The first station is the inlet (velocity, static temperature given), the last the outlet
    (static pressure given). Pure function, numpy only.
    """
    x = np.asarray(x_m, dtype=float)
    rad = np.asarray(radius_m, dtype=float)
    if x.ndim != 1 or x.shape != rad.shape or x.size < 2:
        raise ValueError("x_m and radius_m must be 1-D arrays of the same length >= 2")
    if np.any(rad <= 0.0):
        raise ValueError("radius must be positive")
    cp = gamma * r_gas_j_kg_k / (gamma - 1.0)
    t0 = inlet_temperature_k + inlet_velocity_m_s ** 2 / (2.0 * cp)
    m_in = inlet_velocity_m_s / np.sqrt(gamma * r_gas_j_kg_k * inlet_temperature_k)
    area = np.pi * rad ** 2
    a_star = area[0] / area_mach_ratio(m_in, gamma)
    mach = subsonic_mach_from_area_ratio(area / a_star, gamma)
    mach[0] = m_in
    temp = t0 / (1.0 + 0.5 * (gamma - 1.0) * mach ** 2)
    expo = gamma / (gamma - 1.0)
    p0 = outlet_pressure_pa * (t0 / temp[-1]) ** expo
    pres = p0 * (temp / t0) ** expo
    rho = pres / (r_gas_j_kg_k * temp)
    u = mach * np.sqrt(gamma * r_gas_j_kg_k * temp)
    mdot = float(rho[0] * u[0] * area[0])
    return Quasi1DFlow(x, rad, area, mach, u, pres, rho, temp, float(t0), float(p0), mdot,
                       gamma, r_gas_j_kg_k)


def body_lattice(x_min_m: float, x_max_m: float, radius_m: Callable[[np.ndarray], np.ndarray],
                 spacing_m: float = LATTICE_SPACING_M,
                 wall_tolerance_m: float = WALL_TOLERANCE_M,
                 x_tolerance_m: float | None = None) -> np.ndarray:
    """Cartesian lattice nodes (n, 3) inside a body of revolution about the x axis.

    Nodes sit at integer multiples of ``spacing_m`` (so x = 0 and the outlet plane are nodes and
    the y/z lattice is symmetric with nodes on the axis), with x in [x_min, x_max] (widened by
    ``x_tolerance_m``, default 1e-6 spacing) and ``sqrt(y^2+z^2) < R(x) - wall_tolerance_m``
    (nodes on the wall are excluded, as in the Fluent-style export). Coordinates are the
    correctly rounded decimals (``0.3``, not ``3 * 0.1``). Ordered x, then y, then z ascending.
    """
    h = float(spacing_m)
    if not h > 0:
        raise ValueError("spacing_m must be positive")
    tol = 1e-6 * h if x_tolerance_m is None else float(x_tolerance_m)
    i0 = int(np.ceil((x_min_m - tol) / h))
    i1 = int(np.floor((x_max_m + tol) / h))
    xs = np.round(np.arange(i0, i1 + 1) * h, 9)
    rx = np.asarray(radius_m(xs), dtype=float)
    m = int(np.floor(float(np.max(rx)) / h + 1e-9))
    ys = np.round(np.arange(-m, m + 1) * h, 9)
    rr = np.hypot(ys[:, None], ys[None, :])
    inside = rr[None, :, :] < (rx - wall_tolerance_m)[:, None, None]
    ii, jj, kk = np.nonzero(inside)
    return np.column_stack([xs[ii], ys[jj], ys[kk]])


def analytic_nozzle(radius_m: Callable[[np.ndarray], np.ndarray] = tunnel_radius_m,
                    radius_slope: Callable[[np.ndarray], np.ndarray] | None = None,
                    length_m: float = TUNNEL_LENGTH_M,
                    inlet_velocity_m_s: float = TUNNEL_INLET_VELOCITY_M_S,
                    inlet_temperature_k: float = TUNNEL_INLET_TEMPERATURE_K,
                    outlet_pressure_pa: float = P_REF_PA, gamma: float = GAMMA_AIR,
                    r_gas_j_kg_k: float = R_GAS_AIR_J_KG_K,
                    spacing_m: float = LATTICE_SPACING_M, name: str = "analytic") -> ReferenceField:
    """The analytic quasi-1-D isentropic field of a body of revolution on the node lattice.

    ``radius_slope`` defaults to the exact slope for :func:`tunnel_radius_m` and to a central
    difference otherwise. Gauge pressure is relative to ``P_REF_PA``.
    """
    if radius_slope is None:
        radius_slope = tunnel_radius_slope if radius_m is tunnel_radius_m else (
            lambda x: _numeric_slope(radius_m, x))
    pts = body_lattice(0.0, length_m, radius_m, spacing_m)
    if pts.shape[0] == 0:
        raise ReferenceError(f"builtin:{name}: the lattice of spacing {spacing_m} m is empty")
    xs, inv = np.unique(pts[:, 0], return_inverse=True)
    # the 1-D solution needs the true inlet and outlet stations even if no node sits there
    x1 = np.unique(np.concatenate([[0.0], xs, [length_m]]))
    try:
        flow = isentropic_quasi_1d(x1, np.asarray(radius_m(x1), float), inlet_velocity_m_s,
                                   inlet_temperature_k, outlet_pressure_pa, gamma, r_gas_j_kg_k)
    except ValueError as exc:
        raise ReferenceError(f"builtin:{name}: {exc}") from exc
    sel = np.searchsorted(x1, xs)
    u = flow.velocity_m_s[sel][inv]
    rad = flow.radius_m[sel][inv]
    slope = np.asarray(radius_slope(xs), float)[inv]
    y, z = pts[:, 1], pts[:, 2]
    # u_r = u_x (r/R) dR/dx, rotated: u_y = u_r y / r = u_x (y/R) dR/dx (0 on the axis)
    vel = np.column_stack([u, u * slope * y / rad, u * slope * z / rad])
    params = dict(length_m=length_m, inlet_velocity_m_s=inlet_velocity_m_s,
                  inlet_temperature_k=inlet_temperature_k, outlet_pressure_pa=outlet_pressure_pa,
                  gamma=gamma, r_gas_j_kg_k=r_gas_j_kg_k, spacing_m=spacing_m,
                  radius=getattr(radius_m, "__name__", repr(radius_m)))
    digest = hashlib.sha256(json.dumps(params, sort_keys=True).encode()).hexdigest()
    return ReferenceField(
        points_m=pts, velocity_m_s=vel,
        pressure_gauge_pa=flow.pressure_pa[sel][inv] - P_REF_PA,
        density_kg_m3=flow.density_kg_m3[sel][inv].copy(), name=name, source=f"builtin:{name}",
        source_sha256=digest, pressure_kind="gauge",
        extras={"model": "quasi-1-D isentropic, streamline-slope radial velocity",
                "parameters": params, "mass_flow_kg_s": flow.mass_flow_kg_s})
