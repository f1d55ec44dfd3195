"""Honest statistics of a swarm-field estimate (issue 37, item 7): every fidelity figure with its block
bootstrap interval, the axial profile with its intervals, and the samples per CV.

One home for ``fisc-sim run``, ``fisc-sim emulate``, ``fisc-ground replay`` and the monitor: each keeps
its samples per time block (``fisc_ground.fields.time_blocks.BlockAccumulator``) beside its
``FieldRun``, and ``honest_statistics`` turns them into the ``intervals``, ``axial_profile`` and
``samples_per_cv`` blocks of its report.  Pure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fisc_ground.fields.axial_profile import (DEFAULT_SLICE_M, PROFILE_QUANTITIES, AxialProfile, SliceGeometry,
                                              axial_profile, profile_scores, slice_geometry)
from fisc_ground.fields.bootstrap import DEFAULT_LEVEL, DEFAULT_REPLICATES, Interval, block_bootstrap, time_to_width_s
from fisc_ground.fields.field_report import open_fraction
from fisc_ground.fields.metrics import NORMALISATION, compared_mask, normalise, nrmse, pearson
from fisc_ground.fields.swarm_equations import check_cell_volumes

FIGURES = ("nrmse_velocity", "nrmse_pressure", "nrmse_density", "pearson_velocity", "pearson_pressure",
           "pearson_density")
"""The per-CV fidelity figures given intervals (``fisc_ground.fields.metrics``)."""
PROFILE_FIGURES = ("profile_nrmse_density", "profile_pearson_density", "profile_nrmse_pressure",
                   "profile_pearson_pressure")
"""The axial-profile figures given intervals."""


@dataclass(frozen=True)
class StatsInputs:
    """What the statistic needs of a run's map: per-CV targets and geometry (built once per report)."""

    target_u_axial: np.ndarray
    """(n_cv,) CFD axial velocity [m/s]."""
    target_pressure: np.ndarray
    """(n_cv,) CFD gauge pressure [Pa]."""
    target_density: np.ndarray
    """(n_cv,) CFD density (NaN without) [kg/m^3]."""
    cell_volume_m3: float
    """l^3 of the map's CVs [m^3]."""
    drift_dir: np.ndarray
    """(3,) the drift direction the swarm velocity is projected on (+x)."""
    min_samples: int
    """CVs (and slices) with fewer samples are left out."""
    slices: SliceGeometry
    """The axial slices."""


def stats_inputs(cmap, min_samples: int, slice_m: float = DEFAULT_SLICE_M) -> StatsInputs:
    """``StatsInputs`` of a command map."""
    c = np.asarray(cmap["cv_center_m"], dtype=float)
    l = cmap.cell_size_m
    return StatsInputs(
        target_u_axial=np.asarray(cmap["target_velocity_m_s"], dtype=float)[:, 0],
        target_pressure=np.asarray(cmap["target_pressure_gauge_pa"], dtype=float),
        target_density=np.asarray(cmap["target_density_kg_m3"], dtype=float),
        cell_volume_m3=float(check_cell_volumes(l ** 3, c.shape[0])), drift_dir=np.array([1.0, 0.0, 0.0]),
        min_samples=int(min_samples),
        slices=slice_geometry(c, l, open_fraction(cmap), cmap["target_pressure_gauge_pa"],
                              cmap["target_density_kg_m3"], slice_m))


def figures_of_sums(sums: dict[str, np.ndarray], inp: StatsInputs) -> dict[str, float]:
    """The six per-CV fidelity figures and the four profile figures of summed per-CV moments, on the
    definitions of ``FieldRun.fidelity`` (swarm pressure = the dispersion pressure, density = M / (K l^3))."""
    k = max(float(sums["n_time_samples"]), 1.0)
    kr = float(sums["n_ref_samples"])
    mass = np.asarray(sums["mass_kg"], dtype=float)
    samples = np.rint(np.asarray(sums["count"], dtype=float)).astype(np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.asarray(sums["momentum_kg_m_s"], dtype=float) @ inp.drift_dir / np.where(mass > 0, mass, np.nan)
        rho = mass / k / inp.cell_volume_m3
        p = (2.0 / 3.0 * np.asarray(sums["m_dev2_kg_m2_s2"], dtype=float) / kr / inp.cell_volume_m3
             if kr > 0 else np.full(mass.shape, np.nan))
    out: dict[str, float] = {}
    for q, t, s in (("velocity", inp.target_u_axial, u), ("pressure", inp.target_pressure, p),
                    ("density", inp.target_density, rho)):
        m = compared_mask(samples, inp.min_samples, t, s)
        tn, sn = normalise(t[m], NORMALISATION[q]), normalise(s[m], NORMALISATION[q])
        out[f"nrmse_{q}"] = nrmse(sn, tn) if tn is not None and sn is not None else math.nan
        out[f"pearson_{q}"] = pearson(s[m], t[m])
    prof = profile_scores(axial_profile(sums, inp.slices, inp.min_samples))
    out.update({f"profile_{k_}": v for k_, v in prof.items()})
    return out


def samples_per_cv(samples: np.ndarray, min_samples: int) -> dict:
    """min / median / max agent samples per CV over all the map's CVs, and the fraction with fewer than
    ``min_samples`` (left out of the figures)."""
    s = np.asarray(samples, dtype=float)
    if s.size == 0:
        return {"min": None, "median": None, "max": None, "fraction_below_min_samples": None,
                "min_samples": int(min_samples), "n_cv": 0}
    return {"min": int(s.min()), "median": float(np.median(s)), "max": int(s.max()),
            "fraction_below_min_samples": float(np.mean(s < min_samples)), "min_samples": int(min_samples),
            "n_cv": int(s.size)}


@dataclass(frozen=True)
class HonestStatistics:
    """A run's figures with their intervals, its axial profile and its samples per CV."""

    intervals: dict[str, Interval]
    """``FIGURES`` and ``PROFILE_FIGURES`` -> value and bootstrap interval."""
    profile: AxialProfile
    """The axial profile on all samples."""
    samples: dict
    """``samples_per_cv``."""
    elapsed_s: float
    """Time span the samples cover [s] (for the time-to-width estimate)."""
    band: dict[str, tuple[np.ndarray, np.ndarray]] | None = None
    """``density`` / ``pressure`` -> (lo, hi) per slice: the interval of the min-max normalised swarm profile
    (``normalised_profile``), for the figure's band."""

    def axial_profile_dict(self) -> dict:
        """metrics.json ``axial_profile``: per slice arrays and the four scores with their intervals."""
        p = self.profile
        return {"slice_m": float(np.diff(p.x_m).min()) if p.x_m.size > 1 else None,
                "x_m": p.x_m, "samples": p.samples, "compared": p.compared,
                "swarm_density_kg_m3": p.swarm_density_kg_m3, "cfd_density_kg_m3": p.cfd_density_kg_m3,
                "swarm_pressure_pa": p.swarm_pressure_pa, "cfd_pressure_pa": p.cfd_pressure_pa,
                **{k.removeprefix("profile_"): self.intervals[k].as_dict() for k in PROFILE_FIGURES}}

    def intervals_dict(self) -> dict:
        """metrics.json ``intervals``: the per-CV figures with their intervals."""
        return {k: self.intervals[k].as_dict() for k in FIGURES}

    def time_to_width_s(self, figure: str, target_width: float) -> float:
        """Further sampling time [s] until ``figure``'s interval is narrower than ``target_width``
        (``bootstrap.time_to_width_s``)."""
        return time_to_width_s(self.intervals[figure].width, target_width, self.elapsed_s)

    def progress_line(self, figure: str = "profile_pearson_density", target_width: float = 0.1) -> str:
        """``density r 0.62 [0.41, 0.78]; interval < 0.1 wide in ~4 min at the current rate``."""
        iv = self.intervals[figure]
        name = figure.removeprefix("profile_").replace("pearson_", "").replace("nrmse_", "")
        kind = "r" if "pearson" in figure else "nRMSE"
        head = f"{'profile ' if figure.startswith('profile_') else ''}{name} {kind} {iv.text()}"
        t = self.time_to_width_s(figure, target_width)
        if not math.isfinite(t):
            return f"{head}; interval width unknown yet"
        if t == 0.0:
            return f"{head}; interval < {target_width:g} wide"
        return f"{head}; interval < {target_width:g} wide in ~{_duration(t)} at the current rate"


def _duration(t_s: float) -> str:
    if t_s < 90:
        return f"{t_s:.0f} s"
    if t_s < 90 * 60:
        return f"{t_s / 60:.0f} min"
    return f"{t_s / 3600:.1f} h"


def normalised_profile(prof: AxialProfile, quantity: str) -> tuple[np.ndarray, np.ndarray]:
    """(swarm, CFD) profiles of ``quantity`` min-max normalised over the compared slices (NaN elsewhere,
    and everywhere when either is constant)."""
    sw = prof.swarm_density_kg_m3 if quantity == "density" else prof.swarm_pressure_pa
    cfd = prof.cfd_density_kg_m3 if quantity == "density" else prof.cfd_pressure_pa
    use = prof.compared & np.isfinite(sw) & np.isfinite(cfd)
    out_s, out_c = np.full(sw.shape, np.nan), np.full(sw.shape, np.nan)
    a, b = normalise(sw[use], "minmax"), normalise(cfd[use], "minmax")
    if a is not None and b is not None:
        out_s[use], out_c[use] = a, b
    return out_s, out_c


def honest_statistics(block_sums: dict[str, np.ndarray], inp: StatsInputs, elapsed_s: float,
                      n_boot: int = DEFAULT_REPLICATES, seed: int = 0, level: float = DEFAULT_LEVEL) -> HonestStatistics:
    """Bootstrap every figure over the time blocks (``time_blocks.BlockAccumulator.sums``), and the
    normalised profile slice by slice (the figure's band), on the same replicates."""
    ns = inp.slices.x_m.size

    def statistic(s: dict[str, np.ndarray]) -> dict[str, float]:
        out = figures_of_sums(s, inp)
        prof = axial_profile(s, inp.slices, inp.min_samples)
        for q in PROFILE_QUANTITIES:
            out.update({f"slice_{q}_{i}": v for i, v in enumerate(normalised_profile(prof, q)[0].tolist())})
        return out

    bounds = {k: ((-1.0, 1.0) if "pearson" in k else (0.0, math.inf)) for k in FIGURES + PROFILE_FIGURES}
    bounds.update({f"slice_{q}_{i}": (0.0, 1.0) for q in PROFILE_QUANTITIES for i in range(ns)})
    res = block_bootstrap(block_sums, statistic, n_boot, seed, level, bounds=bounds)
    band = {q: (np.array([res[f"slice_{q}_{i}"].lo for i in range(ns)]),
                np.array([res[f"slice_{q}_{i}"].hi for i in range(ns)])) for q in PROFILE_QUANTITIES}
    total = {k: np.asarray(v, dtype=float).sum(axis=0) for k, v in block_sums.items()}
    return HonestStatistics(intervals={k: res[k] for k in FIGURES + PROFILE_FIGURES},
                            profile=axial_profile(total, inp.slices, inp.min_samples),
                            samples=samples_per_cv(np.rint(total["count"]), inp.min_samples),
                            elapsed_s=float(elapsed_s), band=band)
