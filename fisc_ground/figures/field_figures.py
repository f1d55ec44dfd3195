"""The simulation figures of the paper (figs. 4, 5, 7, 8, 9, 10) for a ``fisc-sim run``."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from fisc_ground.figures import plots
from fisc_ground.figures.workers import FigureJob, render_figures
from fisc_ground.fields.metrics import centreline_profiles

FigureDrawing = Callable[[], Figure]
"""Draws one figure and returns it, unsaved (``run_figure_drawings``)."""

def _minmax(v: np.ndarray, ok: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    out = np.full(v.shape, np.nan)
    if ok.any():
        lo, hi = np.nanmin(v[ok]), np.nanmax(v[ok])
        out[ok] = (v[ok] - lo) / (hi - lo) if hi > lo else 0.0
    return out


def _bymax(v: np.ndarray, ok: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    out = np.full(v.shape, np.nan)
    if ok.any():
        top = np.nanmax(v[ok])
        out[ok] = v[ok] / top if top > 0 else np.nan
    return out


def write_run_figures(run: Any, out_dir: Path, parallel: bool = True) -> dict[str, Path]:
    """Write the PNGs of a ``fisc_ground.fields.field_run.FieldRun`` into ``out_dir``; returns name -> path.

    ``parallel``: draw them on two processes (``fisc_ground.figures.workers``)."""
    jobs = run_figure_jobs(run, out_dir)
    light = [n for n in jobs if n.startswith("snapshot_")]  # drawn last: both processes end together
    paths = render_figures({n: jobs[n] for n in [*(n for n in jobs if n not in light), *light]}, parallel)
    return {n: paths[n] for n in jobs}


def companion_on_cvs(run: Any) -> dict[str, np.ndarray]:
    """The companion run's per-CV fields on this run's CVs, matched by grid cell: the paper's map keeps
    every covered cube, the default's designed staircase a subset of them.  CVs the companion's map lacks
    (or a companion on another grid) get NaN and no samples."""
    cmap, other = run.cmap, run.companion.cmap
    pf = run.companion.fields
    same_grid = (tuple(cmap.grid_shape) == tuple(other.grid_shape) and cmap.cell_size_m == other.cell_size_m
                 and np.allclose(cmap.origin_m, other.origin_m))
    n = np.asarray(cmap["cv_center_m"]).shape[0]
    ids = (np.asarray(other["grid_cv"])[tuple(np.asarray(cmap["cv_index"], dtype=np.int64).T)] if same_grid
           else np.full(n, -1))
    have = ids >= 0

    def take(values: np.ndarray, missing: float) -> np.ndarray:
        return np.where(have, np.asarray(values, dtype=float)[np.maximum(ids, 0)], missing)

    return {"u": take(pf.u_axial_m_s, np.nan), "p": take(pf.p_dispersion_pa, np.nan),
            "rho": take(pf.rho_s_kg_m3, np.nan), "samples": take(pf.samples, 0.0)}


def _varies(values: np.ndarray) -> bool:
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return v.size > 0 and float(v.max()) > float(v.min())


def run_figure_jobs(run: Any, out_dir: Path) -> dict[str, FigureJob]:
    """The figures of ``write_run_figures`` as jobs, name -> job (writes ``out_dir/<name>.png``), in the
    paper's order."""
    return {name: partial(_draw_and_save, draw, Path(out_dir) / f"{name}.png")
            for name, draw in run_figure_drawings(run).items()}


def _draw_and_save(draw: FigureDrawing, path: Path) -> Path:
    return plots.save_figure(draw(), path)


def run_figure_drawings(run: Any) -> dict[str, FigureDrawing]:
    """The figures of ``write_run_figures`` as drawings, name -> drawing, in the paper's order.

    Density panel (b) shows ``plots.requested_density``; a map that asks for the same density in every CV
    (a schema-1 map with one N*) gets no panel (b), and the figure's title says so."""
    cmap, f = run.cmap, run.fields
    c = np.asarray(cmap["cv_center_m"], dtype=float)
    l = cmap.cell_size_m
    wall = plots.design_tunnel_wall(cmap)
    ok = f.samples >= run.min_samples
    everywhere = np.ones(c.shape[0], dtype=bool)
    tgt_v = np.asarray(cmap["target_velocity_m_s"], dtype=float)
    fit_v = np.asarray(cmap["fit_mean_velocity_m_s"], dtype=float)
    jobs: dict[str, FigureDrawing] = {}
    tag = f"{run.scenario}, {run.mode}{', collisions' if run.collisions else ''}"
    for t, pos in run.snapshots:  # fig. 4
        name = f"snapshot_{run.scenario}_{t:05.1f}s".replace(".", "_")
        jobs[name] = partial(plots.swarm_snapshot_figure, pos, c, l, t, wall_radius=wall)
    swarm_u = np.where(ok, f.u_axial_m_s, np.nan)
    # a companion run of the paper's preset (``sim.run``): a fourth panel / curve, on this map's CVs
    pf = companion_on_cvs(run) if run.companion is not None else None
    pok = pf["samples"] >= run.min_samples if pf is not None else None
    p_extra = {"(d) swarm pressure (paper preset)": _minmax(pf["p"], pok)} if pf is not None else {}
    u_extra = ({"(d) swarm u_s / max (paper preset)": _bymax(np.where(pok, pf["u"], np.nan), pok)}
               if pf is not None else {})
    r_extra = {"(d) swarm density (paper preset)": _minmax(pf["rho"], pok)} if pf is not None else {}
    velocity = {"(a) CFD target u_x / max": _bymax(tgt_v[:, 0], everywhere),
                "(b) fitted u_x / max": _bymax(fit_v[:, 0], everywhere),
                f"(c) swarm u_s / max ({tag})": _bymax(swarm_u, ok), **u_extra}
    jobs["velocity_cfd_fit_swarm"] = partial(  # fig. 5
        plots.xz_comparison_figure, c, velocity, l, "Axial velocity normalised by the field maximum, XZ plane",
        label="u / max u", wall_radius=wall)
    pressure = {"(a) CFD gauge pressure": _minmax(cmap["target_pressure_gauge_pa"], everywhere),
                "(b) fitted swarm pressure P_s,d": _minmax(cmap["fit_pressure"], everywhere),
                f"(c) swarm pressure ({tag})": _minmax(f.p_dispersion_pa, ok), **p_extra}
    jobs["pressure_cfd_fit_swarm"] = partial(  # fig. 7
        plots.xz_comparison_figure, c, pressure, l, "Pressure, min-max normalised, XZ plane",
        cmap="coolwarm", label="(P - min) / (max - min)", wall_radius=wall)
    asked_title, asked = plots.requested_density(cmap)
    density_title = "Density, min-max normalised, XZ plane"
    asked_panel = {asked_title: _minmax(asked, everywhere)} if _varies(asked) else {}
    if not asked_panel:
        density_title += f"\n(no panel (b): the map asks for one density everywhere, {asked_title[4:]})"
    density = {"(a) CFD density": _minmax(cmap["target_density_kg_m3"], everywhere), **asked_panel,
               f"(c) time-averaged swarm density ({tag})": _minmax(f.rho_s_kg_m3, ok), **r_extra}
    jobs["density_cfd_fit_swarm"] = partial(  # fig. 8
        plots.xz_comparison_figure, c, density, l, density_title, label="(rho - min) / (max - min)",
        wall_radius=wall)
    jobs["density_velocity_swarm"] = partial(  # fig. 9
        plots.density_with_vectors_figure, c, np.where(ok, f.rho_s_kg_m3, np.nan),
        np.where(ok[:, None], f.mean_velocity_m_s, np.nan), l,
        title=f"Time-averaged swarm density and velocity ({tag})", wall_radius=wall)
    prof = centreline_profiles(c, tgt_v[:, 0], np.asarray(cmap["target_pressure_gauge_pa"], dtype=float),
                               np.asarray(cmap["target_density_kg_m3"], dtype=float), f.u_axial_m_s,
                               f.p_dispersion_pa, f.rho_s_kg_m3, f.samples, run.min_samples)
    extra = None
    if pf is not None:
        extra = {"swarm, paper preset": centreline_profiles(
            c, tgt_v[:, 0], np.asarray(cmap["target_pressure_gauge_pa"], dtype=float),
            np.asarray(cmap["target_density_kg_m3"], dtype=float), pf["u"], pf["p"], pf["rho"], pf["samples"],
            run.min_samples).swarm}
    jobs["centreline"] = partial(  # fig. 10
        plots.centreline_profiles_figure, prof, title=f"Centreline profiles ({tag})", extra_swarm=extra)
    if getattr(run, "statistics", None) is not None and run.statistics.band is not None:
        jobs["axial_profile"] = partial(axial_profile_figure, run.statistics, f"Axial profile ({tag})")
    return jobs


def axial_profile_figure(stats: Any, title: str) -> Figure:
    """The axial profile (``fisc_ground.fields.intervals.HonestStatistics``): per 0.5 m slice, the swarm's
    density and pressure against the CFD's volume-weighted slice means, each min-max normalised, the
    swarm's with its 95 % bootstrap band; the panel titles give r and nRMSE with their intervals."""
    from fisc_ground.fields.intervals import normalised_profile

    fig, axes = plots.plt.subplots(1, 2, figsize=(10.0, 3.8), squeeze=False, layout="constrained")
    axes = axes[0]
    x = stats.profile.x_m
    for ax, q in zip(axes, ("density", "pressure")):
        sw, cfd = normalised_profile(stats.profile, q)
        lo, hi = stats.band[q]
        ax.fill_between(x, lo, hi, color="C1", alpha=0.25, linewidth=0, label="swarm, 95 % interval")
        ax.plot(x, cfd, "-", marker="o", markersize=3, color="C0", label="CFD, volume-weighted")
        ax.plot(x, sw, "--", marker="s", markersize=3, color="C1", label="swarm")
        r, e = stats.intervals[f"profile_pearson_{q}"], stats.intervals[f"profile_nrmse_{q}"]
        ax.set_title(f"{q}: r {r.text(3)}, nRMSE {e.text(3)}", fontsize=9)
        ax.set_xlabel("x [m]")
        ax.set_ylabel(f"normalised {q}")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title)
    return fig
