"""The axial profile (issue 37, item 7): density and pressure per axial slice of the tunnel, against the
CFD's volume-weighted slice means.  It pools every CV of a slice, so it needs far fewer samples than the
per-CV figures (a small fleet fills few CVs often, but every slice it crosses).

Per slice of ``slice_m`` (0.5 m) along x, over the time samples K of an average:

* **density** = time-averaged agent mass in the slice / the slice's volume as the map gives it to the
  swarm (its CVs: n_cv(slice) l^3), ``sum_j M_j / (K n l^3)`` [kg/m^3];
* **pressure** from the slice's velocity spread: ``2 / (3 V) <sum_i m ||v_i - U_slice||^2>``, U_slice
  the slice's mass-weighted mean velocity over the window (eq. internal_pressure on the slice) [Pa];
* the CFD's slice means weight each CV's target by the CFD's volume in it (l^3 ``cv_open_fraction``).

Scores as ``fisc_ground.fields.metrics`` scores the per-CV fields: nRMSE of the min-max normalised
profiles and Pearson r of the raw ones, over the slices with at least ``min_samples`` agent samples.
Pure: per-CV sums in (``fisc_ground.fields.time_blocks.SUM_NAMES``), arrays and numbers out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fisc_ground.fields.metrics import normalise_min_max, nrmse, pearson

DEFAULT_SLICE_M = 0.5
"""Slice length along the axis [m]."""
PROFILE_QUANTITIES = ("density", "pressure")


@dataclass(frozen=True)
class SliceGeometry:
    """Which slice each CV belongs to and the slices' volumes and CFD means."""

    x_m: np.ndarray
    """(n_slices,) centre of each slice along x [m]."""
    slice_of_cv: np.ndarray
    """(n_cv,) slice index of each CV."""
    volume_m3: np.ndarray
    """(n_slices,) the slice's volume as the map gives it to the swarm: its CVs' l^3 [m^3]."""
    cfd_density_kg_m3: np.ndarray
    """(n_slices,) CFD density, volume-weighted over the slice's CVs (NaN without density)."""
    cfd_pressure_pa: np.ndarray
    """(n_slices,) CFD gauge pressure, volume-weighted over the slice's CVs [Pa]."""


def slice_geometry(centers_m: np.ndarray, cell_size_m: float, open_fraction: np.ndarray,
                   target_pressure_pa: np.ndarray, target_density_kg_m3: np.ndarray | None,
                   slice_m: float = DEFAULT_SLICE_M) -> SliceGeometry:
    """Slices of ``slice_m`` from the upstream face of the first CV; only slices holding a CV centre."""
    c = np.asarray(centers_m, dtype=float)
    if c.ndim != 2 or c.shape[1] != 3 or c.shape[0] == 0:
        raise ValueError(f"centers_m must be a non-empty (n_cv, 3) array, got shape {c.shape}")
    if not (math.isfinite(slice_m) and slice_m > 0):
        raise ValueError(f"slice length must be a finite number > 0 m, is {slice_m!r}")
    n = c.shape[0]
    x0 = float(c[:, 0].min()) - 0.5 * cell_size_m
    raw = np.floor((c[:, 0] - x0) / slice_m + 1e-9).astype(np.int64)
    present, slice_of = np.unique(raw, return_inverse=True)
    ns = present.size
    vol = np.bincount(slice_of, minlength=ns) * cell_size_m ** 3
    w = np.asarray(open_fraction, dtype=float).reshape(n) * cell_size_m ** 3

    def mean(v):
        v = np.full(n, np.nan) if v is None else np.asarray(v, dtype=float).reshape(n)
        ok = np.isfinite(v) & (w > 0)
        s = np.bincount(slice_of, weights=np.where(ok, v * w, 0.0), minlength=ns)
        ww = np.bincount(slice_of, weights=np.where(ok, w, 0.0), minlength=ns)
        return np.where(ww > 0, s / np.where(ww > 0, ww, 1.0), np.nan)

    return SliceGeometry(x_m=x0 + (present + 0.5) * slice_m, slice_of_cv=slice_of, volume_m3=vol,
                         cfd_density_kg_m3=mean(target_density_kg_m3), cfd_pressure_pa=mean(target_pressure_pa))


@dataclass(frozen=True)
class AxialProfile:
    """The swarm's axial profile beside the CFD's."""

    x_m: np.ndarray
    """(n_slices,) slice centres [m]."""
    samples: np.ndarray
    """(n_slices,) agent samples in the slice over the window."""
    swarm_density_kg_m3: np.ndarray
    """(n_slices,) swarm density (NaN without samples)."""
    swarm_pressure_pa: np.ndarray
    """(n_slices,) swarm pressure from the slice's velocity spread (NaN without samples)."""
    cfd_density_kg_m3: np.ndarray
    """(n_slices,) CFD density, volume-weighted slice mean."""
    cfd_pressure_pa: np.ndarray
    """(n_slices,) CFD pressure, volume-weighted slice mean."""
    compared: np.ndarray
    """(n_slices,) bool: the slice has >= min_samples samples and finite values."""


def axial_profile(sums: dict[str, np.ndarray], geom: SliceGeometry, min_samples: int) -> AxialProfile:
    """The profile of per-CV sums (``time_blocks.SUM_NAMES``, summed over the window's time samples)."""
    ns = geom.x_m.size
    s = geom.slice_of_cv
    k = max(float(sums["n_time_samples"]), 1.0)
    count = np.bincount(s, weights=np.asarray(sums["count"], dtype=float), minlength=ns)
    mass = np.bincount(s, weights=np.asarray(sums["mass_kg"], dtype=float), minlength=ns)
    mom = np.stack([np.bincount(s, weights=np.asarray(sums["momentum_kg_m_s"], dtype=float)[:, c], minlength=ns)
                    for c in range(3)], axis=1)
    mv2 = np.bincount(s, weights=np.asarray(sums["m_v2_kg_m2_s2"], dtype=float), minlength=ns)
    has = mass > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = np.where(has, mass / (k * geom.volume_m3), np.nan)
        spread = np.where(has, mv2 - np.einsum("ij,ij->i", mom, mom) / np.where(has, mass, 1.0), np.nan)
        p = 2.0 / 3.0 * np.maximum(spread, 0.0) / (k * geom.volume_m3)
    samples = np.rint(count).astype(np.int64)
    compared = (samples >= int(min_samples)) & np.isfinite(rho) & np.isfinite(geom.cfd_pressure_pa)
    return AxialProfile(x_m=geom.x_m, samples=samples, swarm_density_kg_m3=rho, swarm_pressure_pa=p,
                        cfd_density_kg_m3=geom.cfd_density_kg_m3, cfd_pressure_pa=geom.cfd_pressure_pa,
                        compared=compared)


def profile_scores(prof: AxialProfile) -> dict[str, float]:
    """``nrmse_density``, ``pearson_density``, ``nrmse_pressure``, ``pearson_pressure`` of the profile
    (NaN where undefined: fewer than 2 compared slices, a constant profile, no CFD density)."""
    out: dict[str, float] = {}
    for q, sw, cfd in (("density", prof.swarm_density_kg_m3, prof.cfd_density_kg_m3),
                       ("pressure", prof.swarm_pressure_pa, prof.cfd_pressure_pa)):
        use = prof.compared & np.isfinite(cfd) & np.isfinite(sw)
        a, b = sw[use], cfd[use]
        an, bn = normalise_min_max(a), normalise_min_max(b)
        out[f"nrmse_{q}"] = nrmse(an, bn) if an is not None and bn is not None and a.size >= 2 else math.nan
        out[f"pearson_{q}"] = pearson(a, b)
    return out
