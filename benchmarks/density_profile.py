"""Where a run's swarm density departs from its design, slice by slice (a diagnostic, not a test).

Reads a run's ``fields.csv`` and the schema-2 map it flew, and prints, per axial slice of CVs:

* the CFD density, the designed density rho_d and the realised swarm density, each min-max
  normalised over all compared CVs (the DESIGN.md section 4 normalisation), as slice means;
* realised / designed density (both relative to their mean over the compared CVs);
* the swarm's axial velocity (agent-weighted over the slice), the staggered field's (the mean of
  each cube's two x-face velocities) and the CFD's (scaled by the map's S).  In steady state every
  slice passes the same number flux, so a slice the swarm crosses faster than the field holds less
  than its designed density, and one it crosses slower holds more;

then the within-slice scatter by wall class of the cube (interior, one or two side walls, closed
upstream or downstream face), the CVs furthest above their slice (with several runs: how strongly the
runs' within-slice residuals correlate, i.e. how much of the scatter is systematic) and two "what if"
scores: the realised density given the design's
slice profile (each CV keeping its ratio to its slice mean), and the design itself.  Beside the
swarm, each class also shows what ideal tracers hold in the same field (``sim.tracers``): moving
exactly with it (RK4), and holding each velocity for the command interval (forward Euler, 0.05 s:
the simulator's step and ``fisc-agent``'s 20 Hz stream, a vehicle without lag).  That splits a
departure from the design into the field's share and the flight's.

Last, what the min-max nRMSE is made of: the swarm's range against the range its best affine fit to
the CFD pattern spans (CVs beyond it stretch the normalisation and compress all others), the squared
error by band of the normalised CFD density, and two more "what if" scores: the densest CVs at their
slice's mean, and every CV at its slice's mean (no within-slice scatter at all).  Numbers from
this script are in docs/studies/fidelity.md ("What limits each metric")::

    fisc-sim run -o out/run
    python benchmarks/density_profile.py out/run/fields.csv
    python benchmarks/density_profile.py out/run/fields.csv --plot out/run/density_profile.png
    fisc-ground fit cd_nozzle -o out/cd_nozzle.fiscmap
    fisc-sim run --map out/cd_nozzle.fiscmap -o out/cd_nozzle
    python benchmarks/density_profile.py out/cd_nozzle/fields.csv --map out/cd_nozzle.fiscmap

Several runs of one map (other seeds: ``fisc-sim run --seed N``) are averaged CV by CV before the
diagnostic, which separates the sampling noise from what every run shares::

    python benchmarks/density_profile.py out/seed0/fields.csv out/seed1/fields.csv out/seed2/fields.csv

``--plot PNG`` draws the slice profile: the three normalised densities per slice with the band the
swarm's CVs span in each (the band's extremes are what the min-max normalisation sees), and the
three axial velocities.
"""

from __future__ import annotations

import argparse
import csv
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from fisc_agent.map.lookup import CommandField, cube_mean_u_axial_m_s
from fisc_agent.map.codec import load_map
from fisc_ground.maps.build import default_map_path
from fisc_ground.fields.metrics import normalise_min_max
from fisc_ground.fields.metrics import nrmse
from fisc_ground.fields.metrics import pearson
from sim.tracers import Integrator, tracer_density

#: Seed points per axis of every inlet face for the tracers (16 x 16: the shipped map's tracer density
#: is then within 1 % of its design in the median CV, r 0.99).
TRACER_SEEDS = 16
#: RK4 step of the exact tracers [s].
TRACER_DT_S = 0.02
#: Interval over which the held-command tracers keep each velocity [s] (``sim.run.RunConfig.dt_s``,
#: and the period of ``fisc-agent``'s default 20 Hz setpoint stream).
HELD_COMMAND_S = 0.05
#: Upper edges of the bands of normalised CFD density over which the squared error is split.
ERROR_BANDS = (0.3, 0.7, 0.9, 1.0)
#: How many of the densest CVs the "densest at their slice mean" what-if moves.
DENSEST = 10
#: How many CVs the list of the largest within-slice excess shows.
EXCESS = 10

COLUMNS = ("cv_id", "cv_x", "target_density", "target_u_axial", "swarm_density", "swarm_u_axial", "samples")


def read_fields(path: Path) -> dict[str, np.ndarray]:
    """The columns this diagnostic needs from a run's ``fields.csv`` (empty cells as NaN)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        raise ValueError(f"{path}: no rows")
    missing = [c for c in COLUMNS if c not in rows[0]]
    if missing:
        raise ValueError(f"{path}: missing column(s) {', '.join(missing)}")
    out = {c: np.full(len(rows), np.nan) for c in COLUMNS}
    for line, r in enumerate(rows, start=2):
        for c in COLUMNS:
            try:
                out[c][line - 2] = float(r[c]) if r[c] else np.nan
            except ValueError:
                raise ValueError(f"{path}, line {line}, column {c}: {r[c]!r} is not a number") from None
    return out


def read_runs(paths: Sequence[Path]) -> dict[str, np.ndarray]:
    """``read_fields`` of one run, or of several runs of one map averaged CV by CV: the swarm's
    density and axial velocity are the means over the runs, ``samples`` the fewest any run had;
    ``swarm_density_runs`` (runs, n) keeps each run's density."""
    runs = [read_fields(p) for p in paths]
    if not runs:
        raise ValueError("no fields.csv given")
    first = runs[0]
    for p, r in zip(paths[1:], runs[1:]):
        same = r["cv_id"].shape == first["cv_id"].shape and np.array_equal(r["cv_id"], first["cv_id"])
        if not same or not np.allclose(r["target_density"], first["target_density"], equal_nan=True):
            raise ValueError(f"{p}: not a run of the same map as {paths[0]} (its CVs or CFD targets differ)")
    out = dict(first)
    out["swarm_density_runs"] = np.array([r["swarm_density"] for r in runs])
    for c in ("swarm_density", "swarm_u_axial"):
        out[c] = np.mean([r[c] for r in runs], axis=0)
    out["samples"] = np.min([r["samples"] for r in runs], axis=0)
    return out


def _cv_cells(field: CommandField) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Grid cell indices (i, j, k) of every CV cell and the CV id each holds."""
    grid = np.asarray(field.grid_cv)
    i, j, k = np.nonzero(grid >= 0)
    return i, j, k, grid[i, j, k]


def wall_classes(field: CommandField) -> dict[str, np.ndarray]:
    """(n_cv,) masks of the CVs' wall classes on the staircase."""
    i, j, k, cv = _cv_cells(field)
    walls = np.zeros((cv.size, 3, 2), dtype=bool)
    walls[cv] = field.wall_faces[i, j, k]
    up, down, side = walls[:, 0, 0], walls[:, 0, 1], walls[:, 1:, :].sum(axis=(1, 2))
    open_x = ~up & ~down
    return {"interior": open_x & (side == 0), "one side wall": open_x & (side == 1),
            "two side walls": open_x & (side >= 2), "closed upstream face": up, "closed downstream face": down}


@dataclass(frozen=True)
class Score:
    """A fidelity pair of DESIGN.md section 4."""

    nrmse: float
    """nRMSE of the min-max normalised fields [-]."""
    pearson: float
    """Pearson correlation of the raw fields [-]."""

    @classmethod
    def of(cls, a: np.ndarray, b: np.ndarray) -> "Score":
        """The score of ``a`` against ``b``."""
        return cls(nrmse(normalise_min_max(a), normalise_min_max(b)), pearson(a, b))


@dataclass(frozen=True)
class ErrorBand:
    """The share of the density's squared min-max error in one band of the normalised CFD density."""

    lo: float
    """Lower edge of the band (normalised CFD density, inclusive) [-]."""
    hi: float
    """Upper edge (exclusive; the last band includes 1) [-]."""
    n_cv: int
    """Compared CVs in the band."""
    mean_error: float
    """Mean of normalised swarm minus normalised CFD density over the band [-]."""
    share: float
    """The band's part of the summed squared error [-]."""


@dataclass(frozen=True)
class Excess:
    """A CV whose realised / designed density stands far above its slice's."""

    cv_id: int
    """The CV."""
    centre_m: tuple[float, float, float]
    """Its centre (map frame) [m]."""
    wall_class: str
    """Its wall class (``wall_classes``)."""
    open_fraction: float
    """The part of its cube inside the CFD's flow (the map's ``cv_open_fraction``; NaN if absent) [-]."""
    over_slice: float
    """Its realised / designed density over its slice's mean of that ratio (runs averaged) [-]."""


@dataclass(frozen=True)
class DensityProfile:
    """The diagnostic of one run, or of the mean of several (per axial slice arrays share one order, x
    ascending)."""

    x_m: np.ndarray
    """(k,) slice centres [m]."""
    n_cv: np.ndarray
    """(k,) compared CVs per slice."""
    cfd: np.ndarray
    """(k,) slice mean of the min-max normalised CFD density [-]."""
    design: np.ndarray
    """(k,) slice mean of the min-max normalised designed density [-]."""
    swarm: np.ndarray
    """(k,) slice mean of the min-max normalised realised density [-]."""
    swarm_band: tuple[np.ndarray, np.ndarray]
    """(k,) lowest and (k,) highest min-max normalised realised density of each slice's CVs: the
    within-slice scatter on the scale of the metric (its outliers set the normalisation) [-]."""
    realised_over_designed: np.ndarray
    """(k,) slice mean of realised / designed density, each relative to its mean over the CVs [-]."""
    u_swarm_m_s: np.ndarray
    """(k,) agent-weighted slice mean of the swarm's axial velocity [m/s]."""
    u_field_m_s: np.ndarray
    """(k,) slice mean of the staggered field's axial velocity [m/s]."""
    u_cfd_m_s: np.ndarray
    """(k,) slice mean of the CFD's axial velocity times the map's S [m/s]."""
    within_slice_sd: float
    """Standard deviation of each CV's realised / designed over its slice mean [-]."""
    runs: int
    """How many runs were averaged."""
    residual_r_between_runs: float
    """Mean over pairs of runs of the Pearson correlation of their within-slice residuals (each CV's
    realised / designed over its slice mean): the systematic share of the scatter; NaN for one run [-]."""
    largest_excess: tuple[Excess, ...]
    """The ``EXCESS`` CVs furthest above their slice (the runs' mean), largest first."""
    classes: dict[str, tuple[int, float, float]]
    """Wall class -> (CVs, mean, sd of realised / designed)."""
    tracer_classes: dict[str, tuple[float, float]]
    """Wall class -> mean tracer / designed density of (exact tracers, tracers holding each command for
    ``HELD_COMMAND_S``), over the same CVs (``sim.tracers``; absolute, not relative to the mean)."""
    tracer_pearson: tuple[float, float]
    """Pearson correlation with the designed density of (exact tracers, held-command tracers) [-]."""
    swarm_pearson: float
    """Pearson correlation of the realised density with the designed density [-]."""
    realised: Score
    """The realised density against the CFD's (the run's density figures)."""
    with_design_profile: Score
    """The design's slice profile with this run's within-slice scatter, against the CFD."""
    design_score: Score
    """The designed density against the CFD's."""
    swarm_range: tuple[float, float]
    """(min, max) of the realised density over its median CV [-]."""
    affine_range: tuple[float, float]
    """The realised density's least-squares fit a + b * (normalised CFD density) at 0 and 1, over the
    median CV: the range the CFD pattern asks of this swarm [-]."""
    error_bands: tuple[ErrorBand, ...]
    """The squared min-max error split by band of the normalised CFD density (``ERROR_BANDS``)."""
    densest_at_slice_mean: Score
    """The realised density with its ``DENSEST`` densest CVs set to their slice's mean, against the CFD."""
    slice_means_only: Score
    """Every CV at its slice's mean realised density (no within-slice scatter), against the CFD."""


def _error_bands(swarm: np.ndarray, cfd: np.ndarray) -> tuple[ErrorBand, ...]:
    """``ErrorBand`` s of the min-max normalised ``swarm`` against ``cfd``."""
    c = normalise_min_max(cfd)
    e = normalise_min_max(swarm) - c
    total = float(np.sum(e * e))
    bands, lo = [], 0.0
    for hi in ERROR_BANDS:
        m = (c >= lo) & ((c < hi) if hi < ERROR_BANDS[-1] else (c <= hi))
        bands.append(ErrorBand(lo, hi, int(m.sum()), float(e[m].mean()) if m.any() else float("nan"),
                               float(np.sum(e[m] ** 2)) / total if total > 0 else float("nan")))
        lo = hi
    return tuple(bands)


def density_profile(fields_csv: Path | Sequence[Path], map_path: Path) -> DensityProfile:
    """The diagnostic of the run that wrote ``fields_csv`` flying the schema-2 map ``map_path`` (or of
    several runs of it, averaged: ``read_runs``)."""
    cmap = load_map(map_path)
    if "cv_design_density" not in cmap.arrays:
        raise ValueError(f"{map_path}: a schema-1 map has no designed density")
    paths = [fields_csv] if isinstance(fields_csv, (str, Path)) else list(fields_csv)
    f = read_runs([Path(p) for p in paths])
    ids = f["cv_id"].astype(np.int64)
    if ids.size != cmap.n_cv or np.any(ids != np.arange(cmap.n_cv)):
        raise ValueError(f"{paths[0]}: its CVs are not the {cmap.n_cv} CVs of {map_path} (another map?)")
    field = CommandField.from_map(cmap)
    use = (f["samples"] > 0) & np.isfinite(f["swarm_density"]) & np.isfinite(f["target_density"])
    x = f["cv_x"][use]
    cfd, swarm = f["target_density"][use], f["swarm_density"][use]
    design = np.asarray(cmap["cv_design_density"], dtype=float)[use]

    def over_design(dens: np.ndarray) -> np.ndarray:  # realised / designed, each relative to its mean
        return (dens / dens.mean()) / (design / design.mean())

    ratio = over_design(swarm)
    xs, slice_of = np.unique(x, return_inverse=True)

    def slice_mean(v: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        w = np.ones_like(v) if w is None else w
        return np.bincount(slice_of, v * w) / np.bincount(slice_of, w)

    def slice_extreme(v: np.ndarray, ufunc: np.ufunc, start: float) -> np.ndarray:
        out = np.full(xs.size, start)
        ufunc.at(out, slice_of, v)
        return out

    def within_slice(dens: np.ndarray) -> np.ndarray:  # realised / designed over its slice's mean
        r = over_design(dens)
        return r / slice_mean(r)[slice_of]

    within = within_slice(swarm)
    per_run = [within_slice(d[use]) for d in f["swarm_density_runs"]]
    pairs = [pearson(a, b) for i, a in enumerate(per_run) for b in per_run[i + 1:]]
    masks = {name: m[use] for name, m in wall_classes(field).items() if m[use].any()}
    class_of = np.full(x.size, "", dtype=object)
    for name, m in masks.items():
        class_of[m & (class_of == "")] = name
    centres = np.asarray(cmap["cv_center_m"], dtype=float)[use]
    open_frac = (np.asarray(cmap["cv_open_fraction"], dtype=float)[use] if "cv_open_fraction" in cmap.arrays
                 else np.full(x.size, np.nan))
    used_ids = ids[use]
    excess = tuple(Excess(int(used_ids[i]), tuple(float(v) for v in centres[i]), str(class_of[i]),
                          float(open_frac[i]), float(within[i])) for i in np.argsort(-within)[:EXCESS])
    classes = {name: (int(m.sum()), float(ratio[m].mean()), float(ratio[m].std())) for name, m in masks.items()}
    rho_d = np.asarray(cmap["cv_design_density"], dtype=float)
    slice_level = slice_mean(swarm)[slice_of]
    densest = swarm.copy()
    top = np.argsort(swarm)[-DENSEST:]
    densest[top] = slice_level[top]
    med = float(np.median(swarm))
    swarm_norm = normalise_min_max(swarm)
    b, a = np.polyfit(normalise_min_max(cfd), swarm, 1)
    exact, held = (tracer_density(field, rho_d, TRACER_SEEDS, dt, how).density[use] / design
                   for dt, how in ((TRACER_DT_S, Integrator.RK4), (HELD_COMMAND_S, Integrator.EULER)))
    return DensityProfile(
        x_m=xs, n_cv=np.bincount(slice_of), cfd=slice_mean(normalise_min_max(cfd)),
        design=slice_mean(normalise_min_max(design)), swarm=slice_mean(swarm_norm),
        swarm_band=(slice_extreme(swarm_norm, np.minimum, np.inf), slice_extreme(swarm_norm, np.maximum, -np.inf)),
        realised_over_designed=slice_mean(ratio), u_swarm_m_s=slice_mean(f["swarm_u_axial"][use], swarm),
        u_field_m_s=slice_mean(cube_mean_u_axial_m_s(field.grid_cv, field.face_u_m_s[0])[use]),
        u_cfd_m_s=slice_mean(f["target_u_axial"][use] * cmap.scale),
        within_slice_sd=float(within.std()), runs=len(per_run),
        residual_r_between_runs=float(np.mean(pairs)) if pairs else float("nan"), largest_excess=excess,
        classes=classes,
        tracer_classes={name: (float(exact[m].mean()), float(held[m].mean())) for name, m in masks.items()},
        tracer_pearson=(pearson(exact * design, design), pearson(held * design, design)),
        swarm_pearson=pearson(swarm, design), realised=Score.of(swarm, cfd),
        with_design_profile=Score.of(design * within, cfd), design_score=Score.of(design, cfd),
        swarm_range=(float(swarm.min()) / med, float(swarm.max()) / med), affine_range=(a / med, (a + b) / med),
        error_bands=_error_bands(swarm, cfd), densest_at_slice_mean=Score.of(densest, cfd),
        slice_means_only=Score.of(slice_level, cfd))


def markdown(p: DensityProfile) -> str:
    """The diagnostic as markdown tables."""
    lines = ["| x [m] | CVs | CFD (norm.) | design (norm.) | swarm (norm.) | realised / designed | "
             "u swarm [m/s] | u field [m/s] | u CFD x S [m/s] |", "|" + "---|" * 9]
    cols = (p.cfd, p.design, p.swarm, p.realised_over_designed, p.u_swarm_m_s, p.u_field_m_s, p.u_cfd_m_s)
    for i, xv in enumerate(p.x_m):
        lines.append(f"| {xv:.2f} | {p.n_cv[i]} | " + " | ".join(f"{c[i]:.3f}" for c in cols) + " |")
    lines += ["", f"Within-slice scatter of realised / designed: sd {p.within_slice_sd:.3f}."]
    if p.runs > 1:
        lines.append(f"Its residuals (realised / designed over the slice's) correlate "
                     f"r {p.residual_r_between_runs:.2f} between the {p.runs} runs: the share every run has.")
    lines += ["", f"The {len(p.largest_excess)} CVs furthest above their slice:", "",
              "| CV | centre x, y, z [m] | wall class | open fraction | realised / designed over the slice's |",
              "|---|---|---|---|---|"]
    for e in p.largest_excess:
        lines.append(f"| {e.cv_id} | {', '.join(f'{v:.2f}' for v in e.centre_m)} | {e.wall_class} | "
                     f"{e.open_fraction:.2f} | {e.over_slice:.3f} |")
    lines += ["",
              "| wall class | CVs | realised / designed (mean) | sd | exact tracers / designed | "
              f"tracers, commands held {HELD_COMMAND_S:g} s / designed |", "|---|---|---|---|---|---|"]
    for name, (n, mean, sd) in p.classes.items():
        exact, held = p.tracer_classes[name]
        lines.append(f"| {name} | {n} | {mean:.3f} | {sd:.3f} | {exact:.3f} | {held:.3f} |")
    lines += ["", f"* correlation with the designed density: exact tracers r {p.tracer_pearson[0]:.2f}, tracers with "
              f"commands held {HELD_COMMAND_S:g} s r {p.tracer_pearson[1]:.2f}, the swarm r {p.swarm_pearson:.2f}"]
    for what, s in (("realised against the CFD", p.realised),
                    ("realised with the design's slice profile", p.with_design_profile),
                    ("the design against the CFD", p.design_score)):
        lines.append(f"* {what}: nRMSE {s.nrmse:.3f}, r {s.pearson:.2f}")
    lo, hi = p.swarm_range
    fit_lo, fit_hi = p.affine_range
    lines += ["", "What the min-max density nRMSE is made of:", "",
              f"* the swarm spans {lo:.2f}-{hi:.2f} of its median CV; its best affine fit to the CFD pattern "
              f"spans {fit_lo:.2f}-{fit_hi:.2f}", "",
              "| normalised CFD density | CVs | mean error (swarm - CFD) | share of the squared error |",
              "|---|---|---|---|"]
    for band in p.error_bands:
        lines.append(f"| {band.lo:.1f}-{band.hi:.1f} | {band.n_cv} | {band.mean_error:+.3f} | {band.share:.2f} |")
    lines.append("")
    for what, s in ((f"the {DENSEST} densest CVs at their slice's mean", p.densest_at_slice_mean),
                    ("every CV at its slice's mean", p.slice_means_only)):
        lines.append(f"* {what}: nRMSE {s.nrmse:.3f}, r {s.pearson:.2f}")
    return "\n".join(lines)


def plot(p: DensityProfile, path: Path) -> Path:
    """The slice profile as a figure: the CFD's, the design's and the swarm's normalised density per
    slice with the band the swarm's CVs span in each (top), and the three axial velocities (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True, constrained_layout=True)
    lo, hi = p.swarm_band
    top.fill_between(p.x_m, lo, hi, step="mid", color="tab:orange", alpha=0.25,
                     label="swarm: lowest to highest CV of the slice")
    top.plot(p.x_m, p.cfd, "k-", label="CFD")
    top.plot(p.x_m, p.design, "b--", label="design")
    top.plot(p.x_m, p.swarm, "o-", color="tab:orange", ms=3, label="swarm (slice mean)")
    top.set_ylabel("density, min-max normalised over all CVs")
    top.set_title(f"density nRMSE {p.realised.nrmse:.3f} (r {p.realised.pearson:.2f}); "
                  f"every CV at its slice mean: {p.slice_means_only.nrmse:.3f} (r {p.slice_means_only.pearson:.2f})",
                  fontsize=9)
    top.legend(fontsize=8, loc="lower left")
    bottom.plot(p.x_m, p.u_cfd_m_s, "k-", label="CFD x S")
    bottom.plot(p.x_m, p.u_field_m_s, "b--", label="staggered field")
    bottom.plot(p.x_m, p.u_swarm_m_s, "o-", color="tab:orange", ms=3, label="swarm")
    bottom.set_xlabel("x [m]")
    bottom.set_ylabel("axial velocity, slice mean [m/s]")
    bottom.legend(fontsize=8)
    path = Path(path)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("fields_csv", type=Path, nargs="+",
                    help="a run's fields.csv (fisc-sim run -o DIR writes DIR/fields.csv); several runs of one map "
                         "(other seeds) are averaged CV by CV")
    ap.add_argument("--map", type=Path, default=None,
                    help="the schema-2 map the run flew (default: the embedded default map)")
    ap.add_argument("--plot", type=Path, default=None, metavar="PNG",
                    help="also draw the slice profile (densities with each slice's CV band, axial velocities)")
    a = ap.parse_args(argv)
    map_path = a.map if a.map is not None else default_map_path()
    try:
        profile = density_profile(a.fields_csv, map_path)
    except (OSError, ValueError) as exc:
        print(f"density_profile: {exc}", file=sys.stderr)
        return 2
    runs = ", ".join(f"`{p}`" for p in a.fields_csv)
    print(f"{runs} against `{map_path}`\n")
    print(markdown(profile))
    if a.plot is not None:
        print(f"\nfigure: {plot(profile, a.plot)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
