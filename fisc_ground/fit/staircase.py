"""The designed staircase: which of the covered cubes of each axial slice become CVs.

A swarm that flies the CFD's axial velocity u through a slice of N cubes carries the number flux
n u N l^2, and by continuity that flux is the same in every slice.  The CFD's flow passes through the
*open* area of the slice only, but the swarm spreads over whole cubes, so the swarm's density follows
the slice's cube area: n ~ 1 / sum_cubes(u).  With every covered cube a CV (DESIGN.md section 2's
rule), that pattern is an accident of how the grid cuts the wall (docs/studies/density_study.md, "A trimmed
staircase"): it correlates 0.74 with the CFD's density on the tunnel and -0.21 on a mild duct.

Cubes that lie only partly inside the duct are the free choice.  Keeping a slice's m most covered cubes
(most reference nodes; at least as many as the slice's open area fills, at most every covered one) sets
its flux area s(m) = sum of the kept cubes' mean axial CFD velocity.  ``designed_staircase`` picks m per
slice so that 1 / s follows the CFD's slice density pattern f (min-max over the slices) with contrast C:

    s_i proportional to 1 / (1 - C (1 - f_i))      (least squares in log s over the slices)

so the swarm's continuity pattern at the CFD velocity *is* the CFD's density pattern, at a contrast that
stands above the flight's scatter.  Slices are chosen from the inlet on, and a cube whose upstream
neighbour is not kept (a step outwards, fed only through its sides) is eligible only if it is at least
``DEFAULT_MIN_STEP_OPEN`` open: barely open side-fed cubes are where a lagging swarm thins most.  A kept
cube with neither axial neighbour kept (``axial_pockets``) is dropped.  The designed density (``fisc_ground.fit.staggered``) then needs little
velocity to reach it.  A per-slice minimum node count in effect, as DESIGN.md section 2 allows; the
paper's schema-1 maps keep every covered cube.

Pure numpy: per-cell arrays in, a keep mask out (``fisc_ground.fit.partition`` calls it).
"""

from __future__ import annotations

import numpy as np

#: Default contrast C of the designed staircase (``FitConfig.staircase_contrast``).  Chosen from 0.3 / 0.4 /
#: 0.5 on seven ducts (the tunnel, its RANS solution, duct_b and four fresh analytic ducts): 0.4 meets the
#: tunnel's aims and keeps every other duct within 1.5x of them (the double throat's pressure only since
#: ``axial_pockets``; docs/staircase.md, "The designed staircase"); 0.5 raises the density correlation further but costs
#: the mild duct's and the double throat's pressure, and the tunnel's density nRMSE.
DEFAULT_STAIRCASE_CONTRAST = 0.4
#: Default smallest open fraction of a cube that steps the staircase outwards (``designed_staircase``).  On
#: the tunnel such cubes held 0.48-0.65 of their slice's density below a quarter open; with the rule the
#: density nRMSE fell from 0.238-0.261 to 0.217-0.255 (seeds 0-3).  Neutral on four other ducts, it cost the
#: short throat 0.04 of density nRMSE (docs/studies/density_study.md, "The designed staircase").
DEFAULT_MIN_STEP_OPEN = 0.25
#: Scale factors tried for the proportionality constant of s (log-spaced over this range around the median
#: slice's full flux area, in this many steps).
_SCALE_RANGE = (0.2, 5.0)
_SCALE_STEPS = 400


def slice_pattern(value_sum: np.ndarray, node_count: np.ndarray) -> np.ndarray | None:
    """(nx,) min-max normalised slice mean of a node field, from per-cell sums and counts (nx, m); None
    when the slices' means are all equal (a straight pipe: no pattern to follow).

    ValueError when a slice has no node."""
    n = np.asarray(node_count, dtype=float).sum(axis=1)
    if not np.all(n > 0):
        raise ValueError(f"x slice {int(np.flatnonzero(~(n > 0))[0])} holds no reference node")
    mean = np.asarray(value_sum, dtype=float).sum(axis=1) / n
    span = float(np.ptp(mean))
    if not span > 1e-12 * max(float(np.max(np.abs(mean))), 1e-300):
        return None
    return (mean - mean.min()) / span


def designed_staircase(node_count: np.ndarray, u_axial_m_s: np.ndarray, pattern: np.ndarray,
                       contrast: float = DEFAULT_STAIRCASE_CONTRAST,
                       min_step_open: float = DEFAULT_MIN_STEP_OPEN) -> np.ndarray:
    """(nx, m) keep mask: per x slice the m_i most covered cubes, m_i chosen as the module docstring says.

    ``node_count`` (nx, m) reference nodes per cell (0: not covered), the cells of a slice along the second
    axis; ``u_axial_m_s`` (nx, m) their mean axial CFD velocity; ``pattern`` (nx,) the slice density pattern
    in [0, 1] (``slice_pattern``); ``contrast`` C in (0, 1).  A cube whose upstream neighbour is not kept
    (a step outwards, fed only through its sides) may be kept only if its open fraction (node count over
    the slice's fullest cube) is at least ``min_step_open``.  m_i lies between the slice's open area in
    cubes (the sum of the open fractions, rounded, at least 1) and its number of eligible cubes; ties in
    node count keep the cells' order.  ValueError on bad shapes or values, or when no slice choice
    carries a positive CFD flux."""
    c = np.asarray(node_count, dtype=float)
    u = np.asarray(u_axial_m_s, dtype=float)
    f = np.asarray(pattern, dtype=float)
    if c.ndim != 2 or u.shape != c.shape or f.shape != (c.shape[0],):
        raise ValueError(f"node_count and u_axial_m_s must be equal (nx, m) arrays and pattern (nx,), "
                         f"got {c.shape}, {u.shape} and {f.shape}")
    if not 0.0 < contrast < 1.0:
        raise ValueError(f"staircase contrast must lie in (0, 1), got {contrast!r}")
    if not 0.0 <= min_step_open <= 1.0:
        raise ValueError(f"min_step_open must lie in [0, 1], got {min_step_open!r}")
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(f))):
        raise ValueError("u_axial_m_s and pattern must be finite")
    covered = c > 0
    if not np.all(covered.any(axis=1)):
        raise ValueError(f"x slice {int(np.flatnonzero(~covered.any(axis=1))[0])} has no covered cube")
    open_fraction = c / c.max(axis=1, keepdims=True)
    log_want = -np.log(1.0 - contrast * (1.0 - f))
    ref = float(np.median(np.where(covered, u, 0.0).sum(axis=1)))
    if not ref > 0:
        raise ValueError("the reference's slices carry no net CFD flow along +x; cannot design a staircase")
    best_err, best_keep = np.inf, None
    slices: dict = {}  # the candidates of a slice depend on its upstream slice's choice, not on the scale
    for scale in np.geomspace(*_SCALE_RANGE, _SCALE_STEPS) * ref:
        keep, err = _select(c, u, open_fraction, log_want + np.log(scale), min_step_open, slices)
        if err < best_err:
            best_err, best_keep = err, keep
    if best_keep is None:
        raise ValueError("no choice of cubes carries a positive CFD flux through every x slice; "
                         "cannot design a staircase")
    return best_keep & ~axial_pockets(best_keep)


def axial_pockets(keep: np.ndarray) -> np.ndarray:
    """(nx, m) the kept cubes with neither their upstream nor their downstream neighbour kept, inside the
    inlet and outlet slices: pockets the flow cannot pass through.  The projected field carries no axial
    flux there, so agents that wander in (the ``kinetic`` deviations) linger and pile up: on the double
    throat of ``benchmarks/duct_family.py`` one such cube held 1.4 x the density and 3.2 x the median
    pressure of the swarm, and set the top of the pressure's min-max range (docs/simulation.md).
    ``designed_staircase`` drops them (removing one changes no other cube's neighbours)."""
    k = np.asarray(keep, dtype=bool)
    up = np.ones_like(k)
    down = np.ones_like(k)
    up[1:] = k[:-1]
    down[:-1] = k[1:]
    return k & ~up & ~down


def _candidates(c_i: np.ndarray, u_i: np.ndarray, open_i: np.ndarray, upstream: np.ndarray,
                min_step_open: float) -> tuple[np.ndarray, list[float | None]]:
    """A slice's eligible cubes, most covered first, and for each count m of them kept the log of their
    flux area s(m) (None where m is below the slice's open area or s(m) <= 0: not a choice)."""
    eligible = (c_i > 0) & (upstream | (open_i >= min_step_open))
    order = np.argsort(-np.where(eligible, c_i, -1.0), kind="stable")[:int(eligible.sum())]
    s = np.cumsum(u_i[order])
    m = np.arange(1, s.size + 1)
    m_min = min(max(int(np.rint(open_i.sum())), 1), s.size)
    ok = (m >= m_min) & (s > 0)
    logs = np.log(np.where(s > 0, s, 1.0))
    return order, [float(v) if k else None for v, k in zip(logs, ok)]


def _select(c: np.ndarray, u: np.ndarray, open_fraction: np.ndarray, log_target: np.ndarray,
            min_step_open: float, slices: dict) -> tuple[np.ndarray, float]:
    """Slice by slice from the inlet: the m most covered eligible cubes whose log flux area is nearest
    ``log_target``; the keep mask and the summed squared error (inf if a slice has no positive choice).
    ``slices``: ``_candidates`` by slice and upstream choice, shared by the calls of one staircase (each
    scale tried meets the same few); the error of a choice is (log s - log_target)^2 as one float64 each."""
    keep = np.zeros(c.shape, dtype=bool)
    upstream = np.ones(c.shape[1], dtype=bool)
    err = 0.0
    for i in range(c.shape[0]):
        key = (i, upstream.tobytes())
        if key not in slices:
            slices[key] = _candidates(c[i], u[i], open_fraction[i], upstream, min_step_open)
        order, logs = slices[key]
        target = float(log_target[i])
        j, best = -1, np.inf
        for k, log_s in enumerate(logs):  # the first of the smallest, as np.argmin
            if log_s is not None and (log_s - target) * (log_s - target) < best:
                j, best = k, (log_s - target) * (log_s - target)
        if j < 0:
            return keep, np.inf
        err += best
        keep[i, order[:j + 1]] = True
        upstream = keep[i]
    return keep, err
