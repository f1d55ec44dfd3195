"""Axisymmetric (x, r) solutions: the CSV importer and the revolve into a 3-D node field.

An axisymmetric solution (``x, r, u_x, u_r, p[, rho][, T]``, e.g. the cell centres of an
OpenFOAM wedge) is turned into a 3-D field by sampling it on the Cartesian node lattice of the
Fluent-style export (:func:`fisc_ground.reference.analytic.body_lattice`: spacing 0.1 m, nodes at
multiples of the spacing, nodes strictly inside the wall). The wall radius R(x) is taken from
explicit wall samples when the caller has them (mesh vertices of a VTU), otherwise estimated
from the data: per axial column of cells, the outermost centre plus the half-height of the wall
cell extrapolated from the local radial grading, joined by a cubic spline. Values are
interpolated linearly on a Delaunay triangulation of the (x, r) points mirrored about the axis
(the mirror puts the axis inside the triangulation),
with nearest-point fallback outside it (wall layer, inlet/outlet half-cells); the radial
velocity is rotated into y and z (``u_y = u_r y / r``, 0 on the axis).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial import cKDTree

from fisc_ground.reference.analytic import LATTICE_SPACING_M, WALL_TOLERANCE_M, body_lattice
from fisc_ground.reference.field import ReferenceError, ReferenceField
from fisc_ground.reference.fluent_csv import (
    check_duplicates,
    check_finite,
    find_column,
    read_numeric_table,
    to_gauge,
)

log = logging.getLogger(__name__)

_X = ("x", "x-coordinate", "axial-coordinate")
_R = ("r", "radius", "radial-coordinate", "y", "y-coordinate")
_UX = ("u-x", "ux", "u", "axial-velocity", "x-velocity")
_UR = ("u-r", "ur", "v", "radial-velocity", "y-velocity")
_P = ("p", "pressure", "static-pressure")
_P_ABS = ("absolute-pressure", "p-abs")
_RHO = ("rho", "density")
_Z = ("z", "z-coordinate")


def looks_axisymmetric(keys: tuple[str, ...]) -> bool:
    """True when normalised header keys describe an (x, r) table rather than a 3-D export."""
    has_r = any(k in keys for k in ("r", "radius", "radial-coordinate"))
    has_ur = any(k in keys for k in ("u-r", "ur", "radial-velocity"))
    has_z = any(k in keys for k in _Z)
    return (has_r or has_ur) and not has_z


def axial_bins(x: np.ndarray) -> np.ndarray:
    """Bin id per point in about sqrt(n)/2 equal x bins: the fallback for scattered data."""
    nb = max(2, int(np.sqrt(x.size) / 2))
    edges = np.linspace(x.min(), x.max(), nb + 1)
    return np.clip(np.searchsorted(edges, x, side="right") - 1, 0, nb - 1)


def axial_columns(x: np.ndarray) -> np.ndarray | None:
    """Group points into axial columns (cluster id per point), or None if x is not clustered.

    Columns are separated by gaps of the sorted x values larger than 0.3 times the largest
    gap; the clustering is rejected (scattered data) unless every column has at least 3 points
    and spans less in x than the narrowest gap between columns.
    """
    order = np.argsort(x, kind="stable")
    xs = x[order]
    gaps = np.diff(xs)
    if gaps.size < 3:
        return None
    thr = 0.3 * float(gaps.max())
    if thr <= 0.0:
        return None
    breaks = gaps > thr
    cid_sorted = np.concatenate([[0], np.cumsum(breaks)])
    n_col = int(cid_sorted[-1]) + 1
    if n_col < 2:
        return None
    counts = np.bincount(cid_sorted, minlength=n_col)
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    spans = xs[starts + counts - 1] - xs[starts]
    if counts.min() < 3 or spans.max() >= gaps[breaks].min():
        return None
    cid = np.empty_like(cid_sorted)
    cid[order] = cid_sorted
    return cid


def estimate_wall_from_cells(x: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Estimate wall samples (x_w, R_w) from cell-centred axisymmetric data.

    Per axial column: outermost centre r_N plus its half cell height, extrapolated from the
    last two centre spacings d1 = r_N - r_{N-1}, d2 = r_{N-1} - r_{N-2} assuming geometric
    grading q = d1/d2: ``R = r_N + d1 q / (1 + q)`` (exactly d1/2 for a uniform mesh). Without a
    column structure, falls back to the maximum r per x bin (an underestimate by half a cell).
    """
    cid = axial_columns(x)
    if cid is None:
        cid = axial_bins(x)
        o = np.lexsort((r, cid))
        last = np.r_[np.nonzero(np.diff(cid[o]))[0], o.size - 1]
        return x[o][last], r[o][last]
    o = np.lexsort((r, cid))
    cs, rs, xs = cid[o], r[o], x[o]
    last = np.r_[np.nonzero(np.diff(cs))[0], o.size - 1]
    first = np.r_[0, last[:-1] + 1]
    size = last - first + 1
    r_n = rs[last]
    r_n1 = np.where(size >= 2, rs[np.maximum(last - 1, 0)], r_n)
    r_n2 = np.where(size >= 3, rs[np.maximum(last - 2, 0)], r_n1)
    d1 = r_n - r_n1
    d2 = r_n1 - r_n2
    q = np.clip(np.divide(d1, d2, out=np.ones_like(d1), where=d2 > 0), 0.5, 2.0)
    return xs[last], r_n + d1 * q / (1.0 + q)


def _wall_spline(x_w: np.ndarray, r_w: np.ndarray):
    """Cubic spline R(x) through wall samples (duplicate x merged by their maximum)."""
    xu, inv = np.unique(x_w, return_inverse=True)
    ru = np.full(xu.shape, -np.inf)
    np.maximum.at(ru, inv.reshape(-1), r_w)
    if xu.size < 2:
        raise ReferenceError("too few wall samples to define the body of revolution")
    if xu.size < 4:
        return lambda q: np.interp(q, xu, ru)
    return CubicSpline(xu, ru, extrapolate=True)


def _linear_interpolate(xy: np.ndarray, values: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Piecewise-linear interpolation on the Delaunay triangulation of scattered 2-D points.

    Returns (m, k) values at ``query`` (m, 2), NaN outside the triangulation. Uses matplotlib's
    triangulation and trapezoid-map point location plus vectorised barycentric weights (scipy's
    LinearNDInterpolator builds per-simplex LAPACK transforms, which crawl when OpenBLAS threads
    compete on a loaded machine).
    """
    from matplotlib.tri import Triangulation  # ground-side dependency; only needed here

    tri = Triangulation(xy[:, 0], xy[:, 1])
    idx = np.asarray(tri.get_trifinder()(query[:, 0], query[:, 1]))
    out = np.full((query.shape[0], values.shape[1]), np.nan)
    ok = idx >= 0
    v = tri.triangles[idx[ok]]
    a, b, c = xy[v[:, 0]], xy[v[:, 1]], xy[v[:, 2]]
    qa, ba, ca = query[ok] - a, b - a, c - a
    det = ba[:, 0] * ca[:, 1] - ba[:, 1] * ca[:, 0]
    l1 = (qa[:, 0] * ca[:, 1] - qa[:, 1] * ca[:, 0]) / det
    l2 = (ba[:, 0] * qa[:, 1] - ba[:, 1] * qa[:, 0]) / det
    l0 = 1.0 - l1 - l2
    out[ok] = (l0[:, None] * values[v[:, 0]] + l1[:, None] * values[v[:, 1]]
               + l2[:, None] * values[v[:, 2]])
    return out


def revolve_axisymmetric(x: np.ndarray, r: np.ndarray, u_x: np.ndarray, u_r: np.ndarray,
                         p: np.ndarray, rho: np.ndarray | None,
                         spacing_m: float = LATTICE_SPACING_M,
                         *, wall_x_m: np.ndarray | None = None,
                         wall_radius_m: np.ndarray | None = None,
                         x_range_m: tuple[float, float] | None = None,
                         wall_tolerance_m: float = WALL_TOLERANCE_M,
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Revolve scattered axisymmetric data (x, r) into a 3-D node field on the Cartesian lattice.

    Returns ``(points (n,3), velocity (n,3), pressure (n,), density (n,) | None)``.
    ``wall_x_m``/``wall_radius_m``: exact wall samples (else estimated from cell-centred data,
    see :func:`estimate_wall_from_cells`). ``x_range_m``: axial extent of the domain (else
    the data's x range widened by half the axial cell size at both ends). Lattice nodes
    closer than ``wall_tolerance_m`` to the wall are excluded. Pure function (no I/O).
    """
    x = np.asarray(x, float)
    r = np.asarray(r, float)
    cols = [np.asarray(u_x, float), np.asarray(u_r, float), np.asarray(p, float)]
    if rho is not None:
        cols.append(np.asarray(rho, float))
    n = x.size
    if any(a.shape != (n,) for a in [r, *cols]):
        raise ReferenceError("revolve_axisymmetric: x, r and the fields must be (n,) arrays")
    if n < 4:
        raise ReferenceError(f"revolve_axisymmetric: need at least 4 points, got {n}")
    if wall_x_m is None or wall_radius_m is None:
        wall_x, wall_r = estimate_wall_from_cells(x, r)
    else:
        wall_x, wall_r = np.asarray(wall_x_m, float), np.asarray(wall_radius_m, float)
    radius = _wall_spline(wall_x, wall_r)
    if x_range_m is None:
        cid = axial_columns(x)
        if cid is not None:
            n_col = int(cid.max()) + 1
            counts = np.bincount(cid, minlength=n_col)
            centres = np.bincount(cid, weights=x, minlength=n_col) / counts
            centres.sort()
            half_lo = 0.5 * (centres[1] - centres[0])
            half_hi = 0.5 * (centres[-1] - centres[-2])
        else:
            half_lo = half_hi = 0.0
        x_lo, x_hi = float(x.min()) - half_lo, float(x.max()) + half_hi
        x_tol = 0.5 * max(half_lo, half_hi, 1e-6 * spacing_m)
    else:
        x_lo, x_hi = float(x_range_m[0]), float(x_range_m[1])
        x_tol = 1e-6 * spacing_m
    pts = body_lattice(x_lo, x_hi, radius, spacing_m, wall_tolerance_m, x_tol)
    if pts.shape[0] == 0:
        raise ReferenceError("revolve_axisymmetric: no lattice node falls inside the body")
    vals = np.column_stack(cols)
    keep = r > 0.0
    xy = np.concatenate([np.column_stack([x, r]), np.column_stack([x[keep], -r[keep]])])
    mirrored = vals[keep].copy()
    mirrored[:, 1] *= -1.0  # u_r changes sign across the axis
    vv = np.concatenate([vals, mirrored])
    rq = np.hypot(pts[:, 1], pts[:, 2])
    q = np.column_stack([pts[:, 0], rq])
    out = _linear_interpolate(xy, vv, q)
    bad = np.isnan(out[:, 0])
    if bad.any():
        _, idx = cKDTree(xy).query(q[bad])
        out[bad] = vv[idx]
    log.debug("revolved %d points onto %d lattice nodes (%d nearest-filled)",
              n, pts.shape[0], int(bad.sum()))
    with np.errstate(invalid="ignore", divide="ignore"):
        cy = np.where(rq > 0.0, pts[:, 1] / rq, 0.0)
        cz = np.where(rq > 0.0, pts[:, 2] / rq, 0.0)
    vel = np.column_stack([out[:, 0], out[:, 1] * cy, out[:, 1] * cz])
    density = out[:, 3].copy() if rho is not None else None
    return pts, vel, out[:, 2].copy(), density


def read_axisym_csv(path: str | Path, pressure_kind: str = "gauge",
                    spacing_m: float = LATTICE_SPACING_M,
                    name: str | None = None) -> ReferenceField:
    """Read an axisymmetric ``x,r,u_x,u_r,p[,rho][,T]`` CSV and revolve it into a 3-D field.

    Columns are matched case-insensitively in any order (aliases: ``radius``, ``axial-velocity``,
    ``radial-velocity``, ``pressure``, ``absolute-pressure``, ``density``); others are ignored.
    Pressure handling as :func:`fisc_ground.reference.fluent_csv.read_fluent_csv`.
    """
    table = read_numeric_table(path)
    src = table.path
    cols: dict[str, int] = {}
    missing = []
    for label, aliases in (("x", _X), ("r", _R), ("u_x", _UX), ("u_r", _UR)):
        j = find_column(table, aliases)
        if j is None:
            missing.append(label)
        else:
            cols[label] = j
    kind = pressure_kind
    jp = find_column(table, _P)
    if jp is None:
        jp = find_column(table, _P_ABS)
        kind = "absolute" if jp is not None else kind
    if jp is None:
        missing.append("p")
    else:
        cols["p"] = jp
    if missing:
        raise ReferenceError(f"{src}: line {table.header_line}: missing required column(s): "
                             f"{', '.join(missing)}; header is {list(table.columns)}")
    if find_column(table, _Z) is not None:
        raise ReferenceError(f"{src}: line {table.header_line}: has a z column: this is a 3-D "
                             "export, use read_fluent_csv")
    jr = find_column(table, _RHO)
    if jr is not None:
        cols["rho"] = jr
    check_finite(table, cols)
    d = table.data
    r = d[:, cols["r"]]
    if np.any(r < 0.0):
        i = int(np.argmax(r < 0.0))
        raise ReferenceError(f"{src}: line {table.line_numbers[i]}, "
                             f"{table.column_label(cols['r'])}: negative radius {r[i]!r}")
    check_duplicates(table, np.column_stack([d[:, cols["x"]], r]))
    gauge, kind = to_gauge(d[:, cols["p"]], kind, src)
    pts, vel, pres, dens = revolve_axisymmetric(
        d[:, cols["x"]], r, d[:, cols["u_x"]], d[:, cols["u_r"]], gauge,
        d[:, jr] if jr is not None else None, spacing_m)
    return ReferenceField(
        points_m=pts, velocity_m_s=vel, pressure_gauge_pa=pres, density_kg_m3=dens,
        name=name or Path(src).stem, source=src, source_sha256=table.sha256, pressure_kind=kind,
        extras={"format": "axisym-csv", "revolved": True, "lattice_spacing_m": spacing_m,
                "axisym_points": int(d.shape[0])})
