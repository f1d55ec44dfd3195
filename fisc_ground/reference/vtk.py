"""Importer for VTK unstructured grids (.vtu / legacy .vtk) via meshio: OpenFOAM ``foamToVTK``
and ParaView exports.

Data: cell data when it holds velocity and pressure (points = cell centroids, computed per cell
block as the mean of the cell's vertices), else point data. Names (first match wins):
velocity ``U``/``velocity``/``Velocity``/``u``, pressure ``p``/``pressure``/``Pressure``, optional
density ``rho``/``density``/``Density``. Pressure is converted to gauge per ``pressure_kind``
(default ``auto``: absolute when the median exceeds 5e4 Pa, as OpenFOAM's ``p`` is).

Axisymmetric wedges: OpenFOAM runs axisymmetric cases on a thin wedge (here 5 degrees), which is
not a 3-D tunnel. When the points' azimuthal span about the x axis is below
``WEDGE_MAX_SPAN_DEG`` (or the mesh is a thin slab in z), the field is converted to
(x, r, u_x, u_r, p, rho) with r the distance from the x axis and u_r the radial velocity
component, and revolved into 3-D on the node lattice of the Fluent-style export by
:func:`fisc_ground.reference.axisym.revolve_axisymmetric`. The wall radius R(x) comes from the
mesh vertices (projected onto the wedge's mid-plane, where the wedge holds R exactly), so the
lattice node set is that of the Fluent-style export of the same case.
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import numpy as np

from fisc_ground.reference.analytic import LATTICE_SPACING_M
from fisc_ground.reference.axisym import axial_bins, axial_columns, revolve_axisymmetric
from fisc_ground.reference.field import ReferenceError, ReferenceField
from fisc_ground.reference.fluent_csv import to_gauge

log = logging.getLogger(__name__)

#: A mesh whose azimuthal span about the x axis is below this is an axisymmetric sector [deg].
WEDGE_MAX_SPAN_DEG = 30.0
#: A mesh thinner in z than this fraction of its y extent is a 2-D slab (treated as a sector).
SLAB_MAX_THICKNESS_RATIO = 0.02

_VELOCITY = ("U", "velocity", "Velocity", "u", "VELOCITY")
_PRESSURE = ("p", "pressure", "Pressure", "P", "PRESSURE")
_DENSITY = ("rho", "density", "Density", "RHO", "DENSITY")
_VOLUME_CELLS = {"tetra", "hexahedron", "wedge", "pyramid", "tetra10", "hexahedron20",
                 "hexahedron27", "wedge15", "wedge18", "pyramid13", "pyramid14", "polyhedron"}


def _pick(names, candidates):
    for c in candidates:
        if c in names:
            return c
    return None


def _cell_field(mesh, name: str, blocks: list[int]) -> np.ndarray:
    return np.concatenate([np.asarray(mesh.cell_data[name][b], dtype=np.float64) for b in blocks])


def _centroids(mesh, blocks: list[int], src: str) -> np.ndarray:
    """Vertex-mean centroid of every cell of the chosen blocks, vectorised per block."""
    pts = np.asarray(mesh.points, dtype=np.float64)
    if pts.shape[1] == 2:
        pts = np.column_stack([pts, np.zeros(pts.shape[0])])
    out = []
    for b in blocks:
        block = mesh.cells[b]
        conn = block.data
        if isinstance(conn, list) or conn.dtype == object:
            raise ReferenceError(f"{src}: cell block {b} ({block.type}) has variable-size cells "
                                 "(polyhedra); export point data or decompose the polyhedra")
        out.append(pts[conn].mean(axis=1))
    return np.concatenate(out)


def read_vtk(path: str | Path, pressure_kind: str = "auto", spacing_m: float = LATTICE_SPACING_M,
             name: str | None = None) -> ReferenceField:
    """Read a .vtu/.vtk flow solution into a :class:`ReferenceField` (wedges are revolved)."""
    import meshio  # local import: only this importer needs it
    import meshio.vtk
    import meshio.vtu

    p = Path(path)
    if not p.is_file():
        raise ReferenceError(f"{p}: file not found")
    src = str(p)
    from fisc_ground.reference.files import MAX_REFERENCE_BYTES, check_vtk_head
    from fisc_agent.common.safe_files import read_regular_file

    check_vtk_head(p)
    raw = read_regular_file(p, what="VTK export", max_bytes=MAX_REFERENCE_BYTES, error=ReferenceError)
    sha = hashlib.sha256(raw).hexdigest()
    # the format readers directly: meshio.read() prints and calls sys.exit() on a bad file
    readers = {".vtu": meshio.vtu.read, ".vtk": meshio.vtk.read}
    reader = readers.get(p.suffix.lower())
    if reader is None:
        raise ReferenceError(f"{src}: unsupported extension {p.suffix!r}; expected .vtu or .vtk")
    try:
        mesh = reader(str(p))
    except Exception as exc:  # meshio raises many types (ReadError, ParseError, KeyError, ...)
        detail = str(exc).strip() or "meshio gave no details; the file is damaged or not a complete export"
        raise ReferenceError(f"{src}: cannot read as VTK: {type(exc).__name__}: {detail}") from exc

    # prefer cell data (OpenFOAM's native values) over interpolated point data
    vol = [i for i, c in enumerate(mesh.cells) if c.type in _VOLUME_CELLS]
    blocks = vol if vol else list(range(len(mesh.cells)))
    cname_u = _pick(mesh.cell_data, _VELOCITY)
    cname_p = _pick(mesh.cell_data, _PRESSURE)
    if cname_u and cname_p and blocks:
        location = "cell"
        points = _centroids(mesh, blocks, src)
        vel = _cell_field(mesh, cname_u, blocks)
        pres = _cell_field(mesh, cname_p, blocks)
        rname = _pick(mesh.cell_data, _DENSITY)
        rho = _cell_field(mesh, rname, blocks) if rname else None
        names = (cname_u, cname_p, rname)
    else:
        pname_u = _pick(mesh.point_data, _VELOCITY)
        pname_p = _pick(mesh.point_data, _PRESSURE)
        if not (pname_u and pname_p):
            raise ReferenceError(
                f"{src}: no velocity {_VELOCITY} and pressure {_PRESSURE} arrays found in "
                f"cell data "
                f"{sorted(mesh.cell_data)} or point data {sorted(mesh.point_data)}")
        location = "point"
        points = np.asarray(mesh.points, dtype=np.float64)
        if points.shape[1] == 2:
            points = np.column_stack([points, np.zeros(points.shape[0])])
        vel = np.asarray(mesh.point_data[pname_u], dtype=np.float64)
        pres = np.asarray(mesh.point_data[pname_p], dtype=np.float64)
        rname = _pick(mesh.point_data, _DENSITY)
        rho = np.asarray(mesh.point_data[rname], dtype=np.float64) if rname else None
        names = (pname_u, pname_p, rname)
    n = points.shape[0]
    if n == 0:
        raise ReferenceError(f"{src}: no cells or points")
    if vel.ndim != 2 or vel.shape[1] not in (2, 3) or vel.shape[0] != n:
        raise ReferenceError(f"{src}: {location} array {names[0]!r} is not an (n, 3) vector field "
                             f"(shape {vel.shape})")
    if vel.shape[1] == 2:
        vel = np.column_stack([vel, np.zeros(n)])
    pres = pres.reshape(n, -1)[:, 0] if pres.ndim > 1 else pres
    if rho is not None:
        rho = rho.reshape(n, -1)[:, 0] if rho.ndim > 1 else rho
    for label, arr in ((names[0], vel), (names[1], pres), (names[2], rho), ("points", points)):
        if arr is None:
            continue
        bad = ~np.isfinite(arr.reshape(n, -1)).all(axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            raise ReferenceError(f"{src}: {location} data {label!r}: non-finite value at "
                                 f"{location} {i}: {arr[i]!r}")
    gauge, kind = to_gauge(pres, pressure_kind, src)

    extras = {"format": "vtk", "data_location": location,
              "arrays": {"velocity": names[0], "pressure": names[1], "density": names[2]}}
    sector = _sector_geometry(np.asarray(mesh.points, dtype=np.float64))
    if sector is None:
        return ReferenceField(points_m=points, velocity_m_s=vel, pressure_gauge_pa=gauge,
                              density_kg_m3=rho, name=name or p.stem, source=src,
                              source_sha256=sha, pressure_kind=kind, extras=extras)

    # axisymmetric sector: (x, r, u_x, u_r, p, rho) -> revolve into 3-D
    axis_dir, span_deg = sector
    ry = points[:, 1] * axis_dir[0] + points[:, 2] * axis_dir[1]
    rz = -points[:, 1] * axis_dir[1] + points[:, 2] * axis_dir[0]
    r = np.hypot(ry, rz)
    with np.errstate(invalid="ignore", divide="ignore"):
        u_r = np.where(r > 0.0, (vel[:, 1] * points[:, 1] + vel[:, 2] * points[:, 2]) / r, 0.0)
    if span_deg is None:  # planar slab: r = |y'|, keep the sign convention of u_r
        r = np.abs(ry)
    wall_x, wall_r = _wall_from_vertices(np.asarray(mesh.points, dtype=np.float64), axis_dir)
    xall = np.asarray(mesh.points, dtype=np.float64)[:, 0]
    pts3, vel3, p3, rho3 = revolve_axisymmetric(
        points[:, 0], r, vel[:, 0], u_r, gauge, rho, spacing_m, wall_x_m=wall_x,
        wall_radius_m=wall_r, x_range_m=(float(xall.min()), float(xall.max())))
    extras.update(revolved=True, sector_span_deg=span_deg, axisym_points=int(n),
                  lattice_spacing_m=spacing_m)
    log.debug("%s: axisymmetric sector (span %s deg) revolved to %d nodes", src, span_deg,
              pts3.shape[0])
    return ReferenceField(points_m=pts3, velocity_m_s=vel3, pressure_gauge_pa=p3,
                          density_kg_m3=rho3, name=name or p.stem, source=src, source_sha256=sha,
                          pressure_kind=kind, extras=extras)


def _sector_geometry(mesh_points: np.ndarray) -> tuple[np.ndarray, float | None] | None:
    """Detect an axisymmetric sector about the x axis.

    Returns ``(mid-plane direction (cos, sin) in the y-z plane, azimuthal span [deg] or None for
    a thin z slab)``, or None for a genuinely 3-D mesh.
    """
    y, z = mesh_points[:, 1], mesh_points[:, 2]
    rr = np.hypot(y, z)
    scale = float(rr.max()) if rr.size else 0.0
    if scale <= 0.0:
        return None
    off = rr > 1e-9 * scale
    theta = np.arctan2(z[off], y[off])
    c, s = float(np.cos(theta).mean()), float(np.sin(theta).mean())
    norm = np.hypot(c, s)
    if norm > 1e-6:
        c, s = c / norm, s / norm
        sin_t, cos_t = np.sin(theta), np.cos(theta)
        rel = np.arctan2(sin_t * c - cos_t * s, cos_t * c + sin_t * s)
        span = float(np.degrees(rel.max() - rel.min()))
        if span < WEDGE_MAX_SPAN_DEG:
            return np.array([c, s]), span
    if np.ptp(z) <= SLAB_MAX_THICKNESS_RATIO * max(float(np.ptp(y)), 1e-300):
        return np.array([1.0, 0.0]), None
    return None


def _wall_from_vertices(mesh_points: np.ndarray, axis_dir: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Wall samples (x, R) from mesh vertices: the largest mid-plane radius per axial column.

    Vertices are projected onto the sector's mid-plane direction (a wedge holds the true radius
    R(x) there; its off-plane vertices sit at R / cos(half-angle)).
    """
    x = mesh_points[:, 0]
    rp = np.abs(mesh_points[:, 1] * axis_dir[0] + mesh_points[:, 2] * axis_dir[1])
    cid = axial_columns(x)
    if cid is None:  # scattered vertices: bin in x
        cid = axial_bins(x)
    o = np.lexsort((rp, cid))
    last = np.r_[np.nonzero(np.diff(cid[o]))[0], o.size - 1]
    return x[o][last], rp[o][last]
