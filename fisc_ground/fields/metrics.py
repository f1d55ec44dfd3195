"""Fidelity metrics: how closely a swarm field reproduces the CFD target (DESIGN.md section 4).

All comparisons are over the CVs that hold at least ``min_samples`` agent samples in the
averaging window and finite values in both fields of the quantity compared:

* velocity: u_hat = u_axial / max(u_axial), for the swarm and the CFD target separately;
  nRMSE_u = sqrt(mean((u_hat_swarm - u_hat_cfd)^2)).
* pressure and density: min-max normalisation f_hat = (f - min f) / (max f - min f) of each
  field, then the same nRMSE.  Invariant to S, kappa and the mass scale.
* centreline: per axial slice (CVs sharing an x centre), the mean over the slice's CVs nearest
  the axis (smallest |(y, z)| of the CV centre: for the grid with the axis on cell faces, the
  4 CVs around the axis) of the *raw* field; each centreline profile is then normalised the
  same way (by its max for velocity, min-max for pressure and density) and the largest
  absolute deviation between swarm and CFD profiles is reported.
* Pearson correlation of the raw fields per quantity (affine-invariant, so no normalisation).

A normalisation is *degenerate* when it is undefined: max(u) <= 0 for velocity, or a
(numerically) constant field for min-max (range <= 1e-12 of the field's magnitude).  Metrics
that need it are NaN and the reason is listed in ``FidelityMetrics.degenerate``.  A nearly
but not exactly constant field (the CFD density varies by ~7e-4 relative) is *not*
degenerate: min-max normalisation magnifies its trend, which is the point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

QUANTITIES = ("velocity", "pressure", "density")
NORMALISATION = {"velocity": "max", "pressure": "minmax", "density": "minmax"}
DEFAULT_MIN_SAMPLES = 10
"""Default number of agent samples a CV needs in the averaging window to be compared."""
_RANGE_RTOL = 1e-12


@dataclass(frozen=True)
class FidelityMetrics:
    """Swarm-vs-CFD fidelity (DESIGN.md section 4); NaN where undefined (see ``degenerate``)."""

    nrmse_velocity: float
    """RMS of u_hat_swarm - u_hat_cfd over compared CVs (u_hat = u_axial / max u_axial)."""
    nrmse_pressure: float
    """RMS difference of the min-max normalised pressures."""
    nrmse_density: float
    """RMS difference of the min-max normalised densities."""
    centreline_max_dev_velocity: float
    """Largest |difference| of the max-normalised centreline velocity profiles."""
    centreline_max_dev_pressure: float
    """Largest |difference| of the min-max normalised centreline pressure profiles."""
    centreline_max_dev_density: float
    """Largest |difference| of the min-max normalised centreline density profiles."""
    pearson_velocity: float
    """Pearson correlation of swarm and CFD axial velocity over compared CVs."""
    pearson_pressure: float
    """Pearson correlation of swarm and CFD pressure over compared CVs."""
    pearson_density: float
    """Pearson correlation of swarm and CFD density over compared CVs."""
    n_cv_compared: int
    """CVs with >= ``min_samples`` agent samples and finite swarm and target velocity (pressure and
    density compare on the subset of these where their own values are finite)."""
    n_centreline_slices: int
    """Axial slices that contributed to the centreline comparison."""
    min_samples: int
    """The sample threshold used."""
    degenerate: tuple[str, ...] = ()
    """Human-readable reasons for NaN metrics (constant field, no density in the reference...)."""

    def as_dict(self) -> dict:
        """Plain dict (floats, ints and a list of strings) for reports and JSON."""
        out = {
            name: float(getattr(self, name)) for name in (
                "nrmse_velocity", "nrmse_pressure", "nrmse_density",
                "centreline_max_dev_velocity", "centreline_max_dev_pressure", "centreline_max_dev_density",
                "pearson_velocity", "pearson_pressure", "pearson_density")
        }
        out.update(n_cv_compared=int(self.n_cv_compared), n_centreline_slices=int(self.n_centreline_slices),
                   min_samples=int(self.min_samples), degenerate=list(self.degenerate))
        return out


@dataclass(frozen=True)
class CentrelineProfiles:
    """Normalised centreline profiles of target (CFD) and swarm fields (paper fig. 10)."""

    x_m: np.ndarray
    """(n_slices,) axial position of each slice's CV centres [m], increasing."""
    target: dict[str, np.ndarray]
    """quantity -> (n_slices,) normalised CFD profile (NaN where the slice had no compared CV)."""
    swarm: dict[str, np.ndarray]
    """quantity -> (n_slices,) normalised swarm profile."""
    degenerate: tuple[str, ...] = ()
    """Reasons for all-NaN profiles."""


# --------------------------------------------------------------------------------------------
# Normalisations and scores


def normalise_by_max(values: np.ndarray) -> np.ndarray | None:
    """f / max(f) (the paper's velocity normalisation); None when max(f) <= 0 or there is no value."""
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return None
    top = np.nanmax(v) if np.isfinite(v).any() else np.nan
    if not top > 0.0:
        return None
    return v / top


def normalise_min_max(values: np.ndarray) -> np.ndarray | None:
    """(f - min f) / (max f - min f); None for an empty or (numerically) constant field."""
    v = np.asarray(values, dtype=float)
    if v.size == 0 or not np.isfinite(v).any():
        return None
    lo, hi = np.nanmin(v), np.nanmax(v)
    scale = max(abs(lo), abs(hi))
    if not hi - lo > _RANGE_RTOL * scale:  # also catches hi == lo == 0
        return None
    return (v - lo) / (hi - lo)


def normalise(values: np.ndarray, kind: str) -> np.ndarray | None:
    """Normalise by ``kind`` ``"max"`` or ``"minmax"``; None where undefined."""
    if kind == "max":
        return normalise_by_max(values)
    if kind == "minmax":
        return normalise_min_max(values)
    raise ValueError(f"unknown normalisation {kind!r} (use 'max' or 'minmax')")


def nrmse(a_hat: np.ndarray, b_hat: np.ndarray) -> float:
    """sqrt(mean((a_hat - b_hat)^2)) of two normalised fields; NaN when empty."""
    d = np.asarray(a_hat, dtype=float) - np.asarray(b_hat, dtype=float)
    return float(np.sqrt(np.mean(d * d))) if d.size else float("nan")


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation coefficient; NaN with fewer than 2 values or a constant input."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if a.size < 2:
        return float("nan")
    da, db = a - a.mean(), b - b.mean()
    den = np.sqrt(np.sum(da * da) * np.sum(db * db))
    if not den > 0.0:
        return float("nan")
    return float(np.clip(np.sum(da * db) / den, -1.0, 1.0))


# --------------------------------------------------------------------------------------------
# Masks and centreline geometry


def compared_mask(samples: np.ndarray, min_samples: int, *fields: np.ndarray) -> np.ndarray:
    """CVs with ``samples >= min_samples`` and finite values in every given field."""
    mask = np.asarray(samples) >= int(min_samples)
    for f in fields:
        mask &= np.isfinite(np.asarray(f, dtype=float))
    return mask


def centreline_selection(centers_m: np.ndarray, rel_tol: float = 1e-6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per axial slice, the CVs nearest the axis.

    Slices are CVs with the same centre x (gaps <= ``rel_tol`` of the x extent are merged).  In each
    slice the CVs whose radial distance sqrt(y^2 + z^2) equals the slice minimum (within
    ``rel_tol`` of the largest radius) are selected.  Returns ``(slice_x (n_slices,),
    slice_of_cv (n_cv,), on_centreline (n_cv,) bool)``.
    """
    c = np.asarray(centers_m, dtype=float)
    if c.ndim != 2 or c.shape[1] != 3:
        raise ValueError(f"centers_m must be (n_cv, 3), got shape {c.shape}")
    if c.shape[0] == 0:
        return np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool)
    x = c[:, 0]
    tol_x = rel_tol * max(float(np.ptp(x)), 1.0)
    order = np.argsort(x, kind="stable")
    ids_sorted = np.concatenate([[0], np.cumsum(np.diff(x[order]) > tol_x)])
    slice_of = np.empty(x.size, dtype=np.int64)
    slice_of[order] = ids_sorted
    first = order[np.concatenate([[0], np.flatnonzero(np.diff(ids_sorted)) + 1])]
    r = np.hypot(c[:, 1], c[:, 2])
    r_min = np.full(first.size, np.inf)
    np.minimum.at(r_min, slice_of, r)
    tol = rel_tol * max(float(r.max()), 1.0)
    on_axis = r <= r_min[slice_of] + tol
    return x[first], slice_of, on_axis


def _centreline_means(values: np.ndarray, slice_of: np.ndarray, use: np.ndarray, n_slices: int) -> np.ndarray:
    w = use.astype(float)
    vals = np.where(use, values, 0.0)
    s = np.bincount(slice_of, weights=vals, minlength=n_slices)
    n = np.bincount(slice_of, weights=w, minlength=n_slices)
    return np.where(n > 0, s / np.where(n > 0, n, 1.0), np.nan)


def centreline_profiles(centers_m: np.ndarray, target_u_axial: np.ndarray, target_pressure: np.ndarray,
                        target_density: np.ndarray | None, swarm_u_axial: np.ndarray,
                        swarm_pressure: np.ndarray, swarm_density: np.ndarray, samples: np.ndarray,
                        min_samples: int = DEFAULT_MIN_SAMPLES) -> CentrelineProfiles:
    """Normalised centreline profiles (paper fig. 10) of CFD target and swarm.

    Per slice, the mean of the raw field over the near-axis CVs that are compared (enough
    samples, finite values); then each profile is normalised (max for velocity, min-max for
    pressure and density) over the slices present in *both* profiles.  Slices without a
    compared near-axis CV are NaN.
    """
    slice_x, slice_of, on_axis = centreline_selection(centers_m)
    n_slices = slice_x.size
    pairs = _field_pairs(target_u_axial, target_pressure, target_density, swarm_u_axial, swarm_pressure,
                         swarm_density, np.asarray(centers_m).shape[0])
    target, swarm, degenerate = {}, {}, []
    for q, (t, s) in pairs.items():
        use = on_axis & compared_mask(samples, min_samples, t, s)
        tp = _centreline_means(t, slice_of, use, n_slices)
        sp = _centreline_means(s, slice_of, use, n_slices)
        both = np.isfinite(tp) & np.isfinite(sp)
        t_hat, s_hat = np.full(n_slices, np.nan), np.full(n_slices, np.nan)
        tn, sn = normalise(tp[both], NORMALISATION[q]), normalise(sp[both], NORMALISATION[q])
        if not both.any():
            degenerate.append(f"centreline {q}: no slice has a compared near-axis CV")
        elif tn is None or sn is None:
            which = "target" if tn is None else "swarm"
            degenerate.append(f"centreline {q}: {which} profile cannot be {_NORM_TEXT[q]}")
        else:
            t_hat[both], s_hat[both] = tn, sn
        target[q], swarm[q] = t_hat, s_hat
    order = np.argsort(slice_x)
    return CentrelineProfiles(x_m=slice_x[order], target={k: v[order] for k, v in target.items()},
                              swarm={k: v[order] for k, v in swarm.items()}, degenerate=tuple(degenerate))


_NORM_TEXT = {"velocity": "normalised by its max (max <= 0)",
              "pressure": "min-max normalised (constant field)",
              "density": "min-max normalised (constant field)"}


def _field_pairs(target_u, target_p, target_rho, swarm_u, swarm_p, swarm_rho, n_cv: int) -> dict:
    out = {}
    for q, t, s in (("velocity", target_u, swarm_u), ("pressure", target_p, swarm_p),
                    ("density", target_rho, swarm_rho)):
        t = np.full(n_cv, np.nan) if t is None else np.asarray(t, dtype=float)
        s = np.asarray(s, dtype=float)
        if t.shape != (n_cv,) or s.shape != (n_cv,):
            raise ValueError(f"{q}: target and swarm fields must be ({n_cv},), got {t.shape} and {s.shape}")
        out[q] = (t, s)
    return out


# --------------------------------------------------------------------------------------------


def fidelity_metrics(centers_m: np.ndarray, target_u_axial: np.ndarray, target_pressure: np.ndarray,
                     target_density: np.ndarray | None, swarm_u_axial: np.ndarray,
                     swarm_pressure: np.ndarray, swarm_density: np.ndarray, samples: np.ndarray,
                     min_samples: int = DEFAULT_MIN_SAMPLES) -> FidelityMetrics:
    """DESIGN.md section 4 metrics of a swarm field against the CFD target, per CV arrays (n_cv,).

    ``target_density`` may be None or NaN (reference without density): density metrics are
    then NaN and flagged.  ``samples``: agent samples per CV in the averaging window.
    """
    centers = np.asarray(centers_m, dtype=float)
    n_cv = centers.shape[0]
    samples = np.asarray(samples)
    if samples.shape != (n_cv,):
        raise ValueError(f"samples must be ({n_cv},), got {samples.shape}")
    pairs = _field_pairs(target_u_axial, target_pressure, target_density, swarm_u_axial, swarm_pressure,
                         swarm_density, n_cv)
    scores: dict[str, float] = {}
    degenerate: list[str] = []
    for q, (t, s) in pairs.items():
        mask = compared_mask(samples, min_samples, t, s)
        if not mask.any():
            reason = "reference has no density" if q == "density" and not np.isfinite(t).any() \
                else "no CV has enough samples"
            degenerate.append(f"{q}: {reason}")
            scores[f"nrmse_{q}"] = scores[f"pearson_{q}"] = float("nan")
            continue
        tn, sn = normalise(t[mask], NORMALISATION[q]), normalise(s[mask], NORMALISATION[q])
        if tn is None or sn is None:
            degenerate.append(f"{q}: {'target' if tn is None else 'swarm'} field cannot be {_NORM_TEXT[q]}")
            scores[f"nrmse_{q}"] = float("nan")
        else:
            scores[f"nrmse_{q}"] = nrmse(sn, tn)
        scores[f"pearson_{q}"] = pearson(s[mask], t[mask])
    prof = centreline_profiles(centers, *(pairs[q][0] for q in QUANTITIES), *(pairs[q][1] for q in QUANTITIES),
                               samples, min_samples)
    degenerate.extend(prof.degenerate)
    for q in QUANTITIES:
        d = np.abs(prof.swarm[q] - prof.target[q])
        scores[f"centreline_max_dev_{q}"] = float(np.nanmax(d)) if np.isfinite(d).any() else float("nan")
    n_slices = int(np.isfinite(prof.target["velocity"]).sum())
    n_compared = int(compared_mask(samples, min_samples, *pairs["velocity"]).sum())
    return FidelityMetrics(**scores, n_cv_compared=n_compared, n_centreline_slices=n_slices,
                           min_samples=int(min_samples), degenerate=tuple(degenerate))
