"""Figures on the CV grid: XZ-plane maps of CFD targets vs fitted and swarm fields (PNG).

Paper figures reproduced from a command map by ``plot_map_figures``: 5a/5b (velocity), 7a/7b
(pressure), 8a/8b (density) and an N* map.  The generic helpers (``xz_field_panel``,
``plot_xz_comparison``, ``plot_centreline``, ``plot_centreline_profiles``,
``plot_density_with_vectors``, ``plot_swarm_snapshot``) are reused by the simulator report
(figs. 4, 9, 10 and the swarm panels "c" of 5/7/8).  Each ``plot_*`` of those writes the Figure that
its ``*_figure`` twin draws (``save_figure``), so a caller can inspect a figure before it is written.
Figures use matplotlib's constrained layout: no axis label runs into another panel's title.

XZ plane.  The grid has the tunnel axis (y = 0) on cell faces, so no CV layer is centred on
y = 0: the plane shown is the average of the layers whose centres are nearest y = 0, i.e.
the two layers y = -l/2 and y = +l/2 adjacent to the axis (for a grid with a layer centred
on y = 0 that single layer).  Each (x, z) cell shows the mean over those layers of the CVs
present; cells without a CV are blank.  The CV grid is drawn as thin lines on cell faces.

Matplotlib runs on the Agg backend; functions write files and return their paths, nothing
is shown.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402
from matplotlib.colors import BoundaryNorm  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from fisc_agent.map.codec import CommandMap  # noqa: E402

log = logging.getLogger(__name__)

WallRadius = Callable[[np.ndarray], np.ndarray]
_DPI = 120
_GRID_LINE = {"edgecolors": (0.2, 0.2, 0.2, 0.7), "linewidths": 0.4}


# --------------------------------------------------------------------------------------------
# XZ slicing


def xz_slice(centers_m: np.ndarray, values: np.ndarray, cell_size_m: float,
             rel_tol: float = 1e-6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Average ``values`` over the CV layers nearest y = 0 onto the XZ cell grid.

    ``values``: (n_cv,) or (n_cv, k).  Returns ``(x_edges (nx+1,), z_edges (nz+1,),
    grid (nz, nx) or (nz, nx, k))`` with NaN in cells without a (finite) value.
    """
    c = np.asarray(centers_m, dtype=float)
    v = np.asarray(values, dtype=float)
    if c.ndim != 2 or c.shape[1] != 3 or v.shape[0] != c.shape[0]:
        raise ValueError(f"centers_m must be (n, 3) and values (n, ...); got {c.shape} and {v.shape}")
    if c.shape[0] == 0:
        raise ValueError("no CVs to plot")
    l = float(cell_size_m)
    ay = np.abs(c[:, 1])
    sel = ay <= ay.min() + rel_tol * max(l, 1.0)
    cs, vs = c[sel], v[sel].reshape(int(sel.sum()), -1)
    x0, z0 = cs[:, 0].min(), cs[:, 2].min()
    ix = np.rint((cs[:, 0] - x0) / l).astype(np.int64)
    iz = np.rint((cs[:, 2] - z0) / l).astype(np.int64)
    nx, nz = int(ix.max()) + 1, int(iz.max()) + 1
    flat = iz * nx + ix
    grid = np.full((nz * nx, vs.shape[1]), np.nan)
    for k in range(vs.shape[1]):
        ok = np.isfinite(vs[:, k])
        s = np.bincount(flat[ok], weights=vs[ok, k], minlength=nz * nx)
        n = np.bincount(flat[ok], minlength=nz * nx)
        grid[:, k] = np.where(n > 0, s / np.maximum(n, 1), np.nan)
    grid = grid.reshape(nz, nx, vs.shape[1])
    if v.ndim == 1:
        grid = grid[:, :, 0]
    x_edges = x0 - l / 2 + l * np.arange(nx + 1)
    z_edges = z0 - l / 2 + l * np.arange(nz + 1)
    return x_edges, z_edges, grid


def _draw_cv_grid(ax: Axes, x_edges: np.ndarray, z_edges: np.ndarray, present: np.ndarray,
                  facecolor: str = "none") -> None:
    """Wireframe of the cell faces of the (nz, nx) cells where ``present`` is True (filled with
    ``facecolor``, a plain colour: no colour map, so it carries no data)."""
    iz, ix = np.nonzero(present)
    if iz.size == 0:
        return
    x0, x1, z0, z1 = x_edges[ix], x_edges[ix + 1], z_edges[iz], z_edges[iz + 1]
    verts = np.stack([np.stack([x0, z0], 1), np.stack([x1, z0], 1), np.stack([x1, z1], 1),
                      np.stack([x0, z1], 1)], axis=1)
    ax.add_collection(PolyCollection(verts, facecolors=facecolor, **_GRID_LINE))


def _draw_wall(ax: Axes, x_edges: np.ndarray, wall_radius: WallRadius | None) -> None:
    if wall_radius is None:
        return
    x = np.linspace(x_edges[0], x_edges[-1], 200)
    r = np.asarray(wall_radius(x), dtype=float)
    ax.plot(x, r, color="k", linewidth=1.2)
    ax.plot(x, -r, color="k", linewidth=1.2)


def xz_field_panel(ax: Axes, centers_m: np.ndarray, values: np.ndarray, cell_size_m: float, title: str,
                   cmap: str = "viridis", vmin: float | None = None, vmax: float | None = None,
                   label: str | None = None, wall_radius: WallRadius | None = None,
                   velocity_m_s: np.ndarray | None = None, norm=None):
    """Colour map of a per-CV field on the XZ plane with the CV grid, optional wall and vectors.

    ``velocity_m_s`` (n_cv, 3): draws (v_x, v_z) arrows at cell centres, length proportional to
    the in-plane speed (the largest arrow spans 0.9 cell).  Returns the QuadMesh.
    """
    x_edges, z_edges, grid = xz_slice(centers_m, values, cell_size_m)
    masked = np.ma.masked_invalid(grid)
    kw = {"norm": norm} if norm is not None else {"vmin": vmin, "vmax": vmax}
    mesh = ax.pcolormesh(x_edges, z_edges, masked, cmap=cmap, shading="flat", **kw)
    _draw_cv_grid(ax, x_edges, z_edges, ~np.ma.getmaskarray(masked))
    if velocity_m_s is not None:
        _quiver(ax, centers_m, velocity_m_s, cell_size_m)
    _draw_wall(ax, x_edges, wall_radius)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("z [m]")
    ax.set_title(title, fontsize=10)
    cb = ax.figure.colorbar(mesh, ax=ax, fraction=0.025, pad=0.01)
    if isinstance(norm, BoundaryNorm):  # discrete levels: ticks at the integers
        cb.set_ticks(0.5 * (norm.boundaries[:-1] + norm.boundaries[1:]))
    if label:
        cb.set_label(label)
    return mesh


def _quiver(ax: Axes, centers_m: np.ndarray, velocity_m_s: np.ndarray, cell_size_m: float) -> None:
    x_edges, z_edges, vgrid = xz_slice(centers_m, np.asarray(velocity_m_s, dtype=float)[:, [0, 2]], cell_size_m)
    xc = 0.5 * (x_edges[:-1] + x_edges[1:])
    zc = 0.5 * (z_edges[:-1] + z_edges[1:])
    X, Z = np.meshgrid(xc, zc)
    U, W = vgrid[:, :, 0], vgrid[:, :, 1]
    ok = np.isfinite(U) & np.isfinite(W)
    if not ok.any():
        return
    vmax = float(np.max(np.hypot(U[ok], W[ok])))
    if not vmax > 0.0:
        return
    ax.quiver(X[ok], Z[ok], U[ok], W[ok], angles="xy", scale_units="xy", scale=vmax / (0.9 * cell_size_m),
              width=0.0025, color="k", alpha=0.8)


def save_figure(fig: Figure, path: str | Path) -> Path:
    """Write ``fig`` as a PNG at ``path`` (parents created), close it and return the path.

    A figure with a layout engine (constrained layout) is written at its own size: its layout already
    keeps every label inside, and ``bbox_inches="tight"`` would draw it twice (a third of a run's figure
    time).  Others are cropped to their drawn content.  zlib level 3, not PIL's 6: the same pixels (PNG is
    lossless), encoded in 0.6x the time, files ~8 % larger."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=_DPI, bbox_inches=None if fig.get_layout_engine() is not None else "tight",
                pil_kwargs={"compress_level": 3})
    plt.close(fig)
    log.debug("wrote %s", path)
    return path


# --------------------------------------------------------------------------------------------
# Generic figures


def plot_xz_comparison(centers_m: np.ndarray, fields: dict[str, np.ndarray], cell_size_m: float, title: str,
                       path: str | Path, cmap: str = "viridis", shared_scale: bool = True,
                       label: str | None = None, vectors: dict[str, np.ndarray] | None = None,
                       wall_radius: WallRadius | None = None) -> Path:
    """``xz_comparison_figure`` written to ``path``."""
    return save_figure(xz_comparison_figure(centers_m, fields, cell_size_m, title, cmap=cmap,
                                            shared_scale=shared_scale, label=label, vectors=vectors,
                                            wall_radius=wall_radius), path)


def xz_comparison_figure(centers_m: np.ndarray, fields: dict[str, np.ndarray], cell_size_m: float, title: str,
                         cmap: str = "viridis", shared_scale: bool = True, label: str | None = None,
                         vectors: dict[str, np.ndarray] | None = None,
                         wall_radius: WallRadius | None = None) -> Figure:
    """Stacked XZ panels, one per entry of ``fields`` (e.g. CFD / fitted / swarm), one figure.

    ``shared_scale``: one colour range for all panels (use it for normalised fields).
    ``vectors``: optional panel name -> (n_cv, 3) velocities drawn as arrows.
    A value of None in ``fields`` gives an empty panel saying the field is unavailable.
    """
    if not fields:
        raise ValueError("plot_xz_comparison: no fields given")
    finite = [np.asarray(v, dtype=float) for v in fields.values() if v is not None]
    finite = [v[np.isfinite(v)] for v in finite]
    finite = [v for v in finite if v.size]
    vmin = min(float(v.min()) for v in finite) if shared_scale and finite else None
    vmax = max(float(v.max()) for v in finite) if shared_scale and finite else None
    span = np.ptp(np.asarray(centers_m)[:, 0]) + cell_size_m
    height = np.ptp(np.asarray(centers_m)[:, 2]) + cell_size_m
    panel_h = max(1.6, 9.0 * height / max(span, 1e-9)) + 0.8
    fig, axes = plt.subplots(len(fields), 1, figsize=(10, panel_h * len(fields)), squeeze=False,
                             layout="constrained")
    for ax, (name, values) in zip(axes[:, 0], fields.items()):
        arr = None if values is None else np.asarray(values, dtype=float)
        if arr is None or not np.isfinite(arr).any():
            ax.text(0.5, 0.5, f"{name}: not available", ha="center", va="center", transform=ax.transAxes)
            ax.set_axis_off()
            continue
        xz_field_panel(ax, centers_m, arr, cell_size_m, name, cmap=cmap, vmin=vmin, vmax=vmax, label=label,
                       wall_radius=wall_radius, velocity_m_s=(vectors or {}).get(name))
    fig.suptitle(title)
    return fig


def plot_centreline(x_m: np.ndarray, profiles: dict[str, np.ndarray], path: str | Path, title: str = "",
                    ylabel: str = "normalised value") -> Path:
    """Line plot of centreline profiles (label -> (n,) values at ``x_m``) on one axes."""
    fig, ax = plt.subplots(figsize=(7, 3.5), layout="constrained")
    styles = ["-", "--", ":", "-."]
    for i, (name, y) in enumerate(profiles.items()):
        ax.plot(x_m, np.asarray(y, dtype=float), styles[i % len(styles)], marker="o", markersize=3, label=name)
    ax.set_xlabel("x [m]")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend()
    return save_figure(fig, path)


def plot_centreline_profiles(profiles, path: str | Path, title: str = "Centreline profiles",
                             target_label: str = "CFD", swarm_label: str = "swarm",
                             extra_swarm: dict[str, dict] | None = None) -> Path:
    """``centreline_profiles_figure`` written to ``path``."""
    return save_figure(centreline_profiles_figure(profiles, title, target_label, swarm_label, extra_swarm), path)


def centreline_profiles_figure(profiles, title: str = "Centreline profiles", target_label: str = "CFD",
                               swarm_label: str = "swarm", extra_swarm: dict[str, dict] | None = None) -> Figure:
    """Paper fig. 10: density, pressure and velocity centreline profiles, target vs swarm.

    ``profiles``: a ``fisc_ground.fields.metrics.CentrelineProfiles``; ``extra_swarm``: label -> further
    swarm profiles on the same slices (e.g. the paper preset beside the default), drawn dotted.
    """
    names = list(profiles.target)
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.5), squeeze=False, layout="constrained")
    for ax, q in zip(axes[0], names):
        ax.plot(profiles.x_m, profiles.target[q], "-", marker="o", markersize=3, label=target_label)
        ax.plot(profiles.x_m, profiles.swarm[q], "--", marker="s", markersize=3, label=swarm_label)
        for label, prof in (extra_swarm or {}).items():
            ax.plot(profiles.x_m, prof[q], ":", marker="^", markersize=3, label=label)
        ax.set_title(q)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("normalised " + q)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    return fig


def plot_density_with_vectors(centers_m: np.ndarray, density: np.ndarray, velocity_m_s: np.ndarray,
                              cell_size_m: float, path: str | Path, title: str = "Density and velocity",
                              label: str = "density [kg/m^3]", wall_radius: WallRadius | None = None) -> Path:
    """``density_with_vectors_figure`` written to ``path``."""
    return save_figure(density_with_vectors_figure(centers_m, density, velocity_m_s, cell_size_m, title, label,
                                                   wall_radius), path)


def density_with_vectors_figure(centers_m: np.ndarray, density: np.ndarray, velocity_m_s: np.ndarray,
                                cell_size_m: float, title: str = "Density and velocity",
                                label: str = "density [kg/m^3]", wall_radius: WallRadius | None = None) -> Figure:
    """Paper fig. 9: (time-averaged) density colour map with velocity vectors (length ~ speed)."""
    span = np.ptp(np.asarray(centers_m)[:, 0]) + cell_size_m
    height = np.ptp(np.asarray(centers_m)[:, 2]) + cell_size_m
    fig, ax = plt.subplots(figsize=(10, max(2.0, 9.0 * height / max(span, 1e-9)) + 1.0), layout="constrained")
    xz_field_panel(ax, centers_m, density, cell_size_m, title, cmap="viridis", label=label,
                   wall_radius=wall_radius, velocity_m_s=velocity_m_s)
    return fig


def plot_swarm_snapshot(positions_m: np.ndarray, centers_m: np.ndarray, cell_size_m: float, t_s: float,
                        path: str | Path, wall_radius: WallRadius | None = None,
                        slab_half_width_m: float | None = None) -> Path:
    """``swarm_snapshot_figure`` written to ``path``."""
    return save_figure(swarm_snapshot_figure(positions_m, centers_m, cell_size_m, t_s, wall_radius,
                                             slab_half_width_m), path)


def swarm_snapshot_figure(positions_m: np.ndarray, centers_m: np.ndarray, cell_size_m: float, t_s: float,
                          wall_radius: WallRadius | None = None,
                          slab_half_width_m: float | None = None) -> Figure:
    """Paper fig. 4: agents as dots projected on the XZ plane over the CV wireframe at time ``t_s``.

    ``slab_half_width_m``: only agents with |y| <= this are drawn (None: all agents).
    """
    pos = np.asarray(positions_m, dtype=float).reshape(-1, 3)
    pos = pos[np.all(np.isfinite(pos), axis=1)]
    if slab_half_width_m is not None:
        pos = pos[np.abs(pos[:, 1]) <= slab_half_width_m]
    x_edges, z_edges, grid = xz_slice(centers_m, np.ones(np.asarray(centers_m).shape[0]), cell_size_m)
    span = x_edges[-1] - x_edges[0]
    height = z_edges[-1] - z_edges[0]
    fig, ax = plt.subplots(figsize=(10, max(2.0, 9.0 * height / max(span, 1e-9)) + 1.0), layout="constrained")
    _draw_cv_grid(ax, x_edges, z_edges, np.isfinite(grid), facecolor="0.94")
    ax.set_xlim(x_edges[0], x_edges[-1])
    ax.set_ylim(z_edges[0], z_edges[-1])
    _draw_wall(ax, x_edges, wall_radius)
    ax.scatter(pos[:, 0], pos[:, 2], s=3, color="tab:blue", linewidths=0)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("z [m]")
    ax.set_title(f"t = {t_s:.1f} s, {pos.shape[0]} agents")
    return fig


# --------------------------------------------------------------------------------------------
# Map figures (fisc-ground plot)


def design_tunnel_wall(cmap: CommandMap) -> WallRadius | None:
    """The DESIGN.md section 2 wall R(x) when the map's CVs are consistent with that tunnel.

    Consistent: CV centres span x within [-l, 15 + l] and every centre lies within R(x) + l of
    the axis.  Other geometries get no wall outline.
    """
    from fisc_ground.reference.analytic import tunnel_radius_m

    c = np.asarray(cmap["cv_center_m"], dtype=float)
    l = cmap.cell_size_m
    if c.shape[0] == 0 or c[:, 0].min() < -l or c[:, 0].max() > 15.0 + l:
        return None
    r = np.hypot(c[:, 1], c[:, 2])
    if np.any(r > tunnel_radius_m(np.clip(c[:, 0], 0.0, 15.0)) + l):
        return None
    return lambda x: tunnel_radius_m(np.clip(x, 0.0, 15.0))


def _minmax(values: np.ndarray) -> np.ndarray:
    v = np.asarray(values, dtype=float)
    lo, hi = np.nanmin(v), np.nanmax(v)
    return np.zeros_like(v) if not hi > lo else (v - lo) / (hi - lo)


def requested_density(cmap: CommandMap) -> tuple[str, np.ndarray]:
    """Panel (b) of the density figure: what the map asks the swarm for, (title, (n_cv,) values).

    A schema-2 map carries its designed swarm density rho_d (``cv_design_density``,
    ``fisc_ground.fit.staggered.design_density``, relative, mean 1); a schema-1 map asks for N*_j
    agents per CV, i.e. the fitted density N* m / dV [kg/m^3]."""
    if "cv_design_density" in cmap.arrays:
        return "(b) designed density rho_d (relative): what the map asks the swarm for", \
            np.asarray(cmap["cv_design_density"], dtype=float)
    mass_kg = float(cmap.body.get("agent_mass_kg", 1.0))
    return "(b) fitted density N* m / dV", np.asarray(cmap["n_star"], dtype=float) * mass_kg / cmap.cell_size_m ** 3


def plot_map_figures(cmap: CommandMap, out_dir: str | Path,
                     wall_radius: WallRadius | None | str = "auto") -> list[Path]:
    """The map's target-vs-fit figures (paper figs. 5a/5b, 7a/7b, 8a/8b) and an N* map.

    Writes ``velocity_target_vs_fit.png`` (speed / field max, with vectors),
    ``pressure_target_vs_fit.png`` (CFD gauge pressure and achieved fitted swarm pressure, each
    min-max normalised to [0, 1] so the patterns compare), ``density_target_vs_fit.png`` (CFD
    density and what the map asks the swarm for, ``requested_density``, each on its own scale) and
    ``n_star.png``.  ``wall_radius``: a callable R(x), None, or "auto" (``design_tunnel_wall``).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    wall = design_tunnel_wall(cmap) if isinstance(wall_radius, str) else wall_radius
    c = np.asarray(cmap["cv_center_m"], dtype=float)
    l = cmap.cell_size_m
    target_v = np.asarray(cmap["target_velocity_m_s"], dtype=float)
    fit_v = np.asarray(cmap["fit_mean_velocity_m_s"], dtype=float)
    paths = []

    def by_max(v):
        speed = np.linalg.norm(v, axis=1)
        top = np.nanmax(speed)
        return speed / top if top > 0 else speed

    paths.append(plot_xz_comparison(
        c, {"(a) CFD target velocity": by_max(target_v), "(b) fitted velocity (mean of N* vectors)": by_max(fit_v)},
        l, "Velocity magnitude / field max, XZ plane", out / "velocity_target_vs_fit.png", cmap="viridis",
        label="|v| / max |v|", wall_radius=wall,
        vectors={"(a) CFD target velocity": target_v, "(b) fitted velocity (mean of N* vectors)": fit_v}))
    paths.append(plot_xz_comparison(
        c, {"(a) CFD target static (gauge) pressure": _minmax(cmap["target_pressure_gauge_pa"]),
            "(b) fitted swarm pressure P_s,d": _minmax(cmap["fit_pressure"])},
        l, "Pressure, min-max normalised, XZ plane", out / "pressure_target_vs_fit.png", cmap="coolwarm",
        label="(P - min P) / (max P - min P)", wall_radius=wall))
    n_star = np.asarray(cmap["n_star"], dtype=float)
    asked_title, asked = requested_density(cmap)
    paths.append(plot_xz_comparison(
        c, {"(a) CFD target density [kg/m^3]": np.asarray(cmap["target_density_kg_m3"], dtype=float),
            asked_title + ("" if "cv_design_density" in cmap.arrays else " [kg/m^3]"): asked},
        l, "Density, XZ plane", out / "density_target_vs_fit.png", cmap="viridis", shared_scale=False,
        label=None if "cv_design_density" in cmap.arrays else "kg/m^3", wall_radius=wall))
    lo, hi = (int(v) for v in cmap.body["n_range"])
    fig, ax = plt.subplots(figsize=(10, 3.2))
    norm = BoundaryNorm(np.arange(lo - 0.5, hi + 1.5), plt.get_cmap("viridis").N)
    xz_field_panel(ax, c, n_star, l, f"Fitted agent count N* per CV (N in [{lo}, {hi}])", cmap="viridis",
                   label="N*", wall_radius=wall, norm=norm)
    paths.append(save_figure(fig, out / "n_star.png"))
    return paths
