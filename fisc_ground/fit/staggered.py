"""Continuity-consistent staggered (MAC-grid) command field on the CV staircase.

The map's CVs are the occupied cells of a regular grid.  This module gives every cell face
that touches a CV one *normal* velocity (a staggered, face-centred field as in the pressure
projection of incompressible solvers) such that the discrete divergence of ``rho_d u`` is zero
in every CV, ``rho_d`` being a *designed swarm density* per CV:

* faces between two CVs carry the flux ``rho_f u_f l^2`` (``rho_f`` the mean of the two CVs'
  designed densities);
* faces between a CV and a cell without one carry nothing (the staircase wall), except
* the inlet faces (lower x face of the first grid slice), which carry the CFD inflow, and
* the outlet faces (upper x face of the last slice), whose flux is free.

The face velocities come in two steps (``project``).  First every x plane's CV-CV faces keep the
CFD flux pattern ``rho_f u*_f`` (``u*`` the CFD velocity averaged onto the faces) scaled by one
factor per plane, so that every plane carries the inflow Q of the closed duct (the even spread is
the least-squares choice for a plane's total).  Then one weighted least-squares projection over
all CV-CV faces: the fluxes ``q`` closest to ``q*`` in ``sum_f w_f (q_f - q*_f)^2`` with zero net
outflow in every CV.  The Lagrange condition gives ``q = q* - W^-1 D^T lam`` and one sparse
symmetric positive definite solve ``(D W^-1 D^T) lam = D q* + b`` (``b`` the fixed inlet and outlet
fluxes): a Poisson equation for the "pressure" ``lam`` on the CV graph.  Axial faces weigh
``axial_weight`` (default 100: the planes keep their CFD pattern and the staircase's steps are
balanced by sideways flow within the slice); ``weight_exponent`` > 0 would make corrections cheaper
in the wall cubes (measured worse, default 0 = plain L2).

Inside a cube an agent interpolates each component linearly between the cube's two faces
(``fisc_agent.map.lookup.CommandField``, mode ``staggered``), so the field is continuous across
faces in its normal component and tracers keep the designed density.

Ground side only; the agent reads the resulting arrays from the map.  scipy.sparse (the ``ground``
extra) is imported by ``project`` alone, so the settings and their defaults load without it (the
``fisc-ground`` parser shows them in ``--help``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from fisc_agent.map.lookup import cube_mean_u_axial_m_s

#: Candidates of the automatic blend beta of the designed density (``design_density``), lowest first: the
#: lowest whose static field keeps the velocity nRMSE within ``STATIC_VELOCITY_LIMIT`` is used
#: (``build_staggered``).  0.5 is the middle of the blend; a duct whose static field misses the limit there
#: gets more (the long duct of benchmarks/duct_family.py 0.6, its double throat 0.75): higher beta moves the
#: design towards the staircase's continuity pattern, buying velocity fidelity with density correlation
#: (docs/studies/fidelity.md, "Ducts not seen when the defaults were chosen").
AUTO_CONTINUITY_WEIGHTS = (0.5, 0.6, 0.75, 1.0)
#: Largest velocity nRMSE of the static field at amplitude k = 1 for which the automatic beta may stay at
#: its lowest candidate.  Flown, a swarm scores 0.6-0.75 of its static field's figure (the long duct: 0.077
#: flown of 0.103 static), so 0.10 keeps a flown map within 1.5x of the issue's velocity aim (0.075).
STATIC_VELOCITY_LIMIT = 0.10
#: Default exponent p of the face weights w_f = max(open_fraction, floor)^p.
DEFAULT_WEIGHT_EXPONENT = 0.0
#: Default ratio of the weights of axial to lateral face corrections (see ``project``).
DEFAULT_AXIAL_WEIGHT = 100.0
#: Smallest open fraction used in the weights (keeps W invertible).
WEIGHT_FLOOR = 0.02
#: Factor k on the designed density's amplitude used when none is given (see ``design_density``; 1 =
#: the staircase's own contrast).  A lagging swarm realises about 0.9 of the designed slice contrast and
#: scatters in the wall cubes, so the design asks for more: the largest of these whose static field keeps
#: the velocity nRMSE within ``STATIC_VELOCITY_BUDGET`` (1 regardless).  1.1 improved the density
#: figures on the ducts that can afford it at a velocity cost of about 0.002 on the tunnel
#: (docs/studies/fidelity.md, "Velocity against density"); more contrast buys more correlation with more
#: velocity error.
AUTO_DENSITY_AMPLITUDES = (1.1, 1.05, 1.0)
#: Largest velocity nRMSE of the static field (``static_velocity_nrmse``) for which the automatic
#: amplitude may exceed 1.  Flown, a swarm scores 0.55-0.8 of its static field's figure; a duct whose
#: static field already misses this at k = 1 (the long duct of benchmarks/duct_family.py: 0.103) keeps 1.
STATIC_VELOCITY_BUDGET = 0.08


@dataclass(frozen=True)
class StaggeredConfig:
    """How the designed density and the projection weights are chosen (recorded in maps)."""

    continuity_weight: float | None = None
    """beta of ``design_density``: 0 = the CFD's density pattern, 1 = the density at which the CFD
    velocity is continuity-consistent on the staircase; in between trades density fidelity for
    velocity fidelity.  None (the default) chooses it (``AUTO_CONTINUITY_WEIGHTS`` within
    ``velocity_limit``, ``build_staggered``)."""
    weight_exponent: float = DEFAULT_WEIGHT_EXPONENT
    """p in the face weights w_f = max(min(open_lo, open_hi), floor)^p: how strongly the projection
    keeps the CFD velocity in fully open CVs and corrects it in the wall cubes (0 = plain L2)."""
    axial_weight: float = DEFAULT_AXIAL_WEIGHT
    """Weight of axial relative to lateral face corrections in the projection: below 1 the axial
    fluxes of neighbouring slices absorb part of a staircase step's residual, so the sideways flow
    it needs spreads over about sqrt(1 / axial_weight) slices instead of one.  Large values (the
    default) keep each plane's CFD flux pattern: spreading cost more velocity fidelity (static field
    0.128 at 1/9 against 0.070) than it gained in density."""
    density_amplitude: float | None = None
    """k of ``design_density``: the designed density's contrast is k times the staircase's own (1 is
    the contrast continuity allows at the CFD velocity); None (the default) chooses it
    (``AUTO_DENSITY_AMPLITUDES`` within ``velocity_budget``, ``build_staggered``).  Above
    1 the swarm's density pattern stands further above its sampling noise and wall-cube scatter, at
    the cost of velocity fidelity: by continuity, n u A is the same through every slice, so a deeper
    density dip makes the swarm faster than the CFD there (docs/studies/fidelity.md, "Velocity against
    density")."""
    velocity_budget: float = STATIC_VELOCITY_BUDGET
    """With ``density_amplitude`` None: the largest static velocity nRMSE (``static_velocity_nrmse``)
    an amplitude above 1 may cost."""
    velocity_limit: float = STATIC_VELOCITY_LIMIT
    """With ``continuity_weight`` None: the largest static velocity nRMSE at k = 1 (or at the given
    ``density_amplitude``) the lowest automatic beta may leave; above it beta is raised."""

    def __post_init__(self) -> None:
        if not (self.axial_weight > 0 and np.isfinite(self.axial_weight)):
            raise ValueError(f"StaggeredConfig.axial_weight must be finite and > 0, got {self.axial_weight!r}")
        if self.continuity_weight is not None and not (0.0 <= self.continuity_weight <= 1.0):
            raise ValueError(f"StaggeredConfig.continuity_weight must lie in [0, 1], got {self.continuity_weight!r}")
        if not (self.weight_exponent >= 0 and np.isfinite(self.weight_exponent)):
            raise ValueError(f"StaggeredConfig.weight_exponent must be finite and >= 0, got {self.weight_exponent!r}")
        k = self.density_amplitude
        if k is not None and not (k > 0 and np.isfinite(k)):
            raise ValueError(f"StaggeredConfig.density_amplitude must be finite and > 0 (None: automatic), "
                             f"got {k!r}")
        for name in ("velocity_budget", "velocity_limit"):
            v = getattr(self, name)
            if not (v > 0 and np.isfinite(v)):
                raise ValueError(f"StaggeredConfig.{name} must be finite and > 0, got {v!r}")


@dataclass(frozen=True)
class StaggeredField:
    """Face-normal velocities of the staircase (unscaled, in the reference's units) and the density."""

    face_u_x_m_s: np.ndarray
    """(nx + 1, ny, nz) normal velocity on the x faces [m/s]; face (i, j, k) is the lower x face of
    cell (i, j, k).  0 on walls and on faces that touch no CV."""
    face_u_y_m_s: np.ndarray
    """(nx, ny + 1, nz) normal velocity on the y faces [m/s]."""
    face_u_z_m_s: np.ndarray
    """(nx, ny, nz + 1) normal velocity on the z faces [m/s]."""
    design_density: np.ndarray
    """(n_cv,) designed relative swarm density rho_d (mean over CVs 1) [-]."""
    max_divergence: float
    """Largest |net outflow| of rho_d u over a CV after the projection, relative to the inflow [-]."""
    density_amplitude: float | None = None
    """k the designed density was built with (``build_staggered``: the chosen one when the config left
    it open; None from ``project`` alone, which is given a density)."""
    continuity_weight: float | None = None
    """beta the designed density was built with (``build_staggered``: the chosen one when the config
    left it open; None from ``project`` alone)."""
    static_velocity_nrmse: float | None = None
    """``static_velocity_nrmse`` of this field against the CFD [-] (``build_staggered``; None from
    ``project`` alone)."""


def _min_max(f: np.ndarray) -> np.ndarray:
    span = float(np.ptp(f))
    return (f - f.min()) / span if span > 0 else np.ones_like(f)


def cfd_pattern(target_density: np.ndarray, target_pressure: np.ndarray) -> np.ndarray:
    """(n_cv,) min-max normalised CFD density, or pressure where the reference has no (finite,
    non-constant) density: the pattern the swarm density is compared with."""
    f = np.asarray(target_density, dtype=float)
    if not np.all(np.isfinite(f)) or np.ptp(f) <= 1e-12 * max(float(np.max(np.abs(f))), 1e-300):
        f = np.asarray(target_pressure, dtype=float)
    if not np.all(np.isfinite(f)):
        j = int(np.flatnonzero(~np.isfinite(f))[0])
        raise ValueError(f"CV {j}: CFD density and pressure are not finite")
    return _min_max(f)


def slice_flux_area(grid_cv: np.ndarray, target_velocity_m_s: np.ndarray) -> np.ndarray:
    """(n_cv,) s_j: the axial CFD velocity summed over the CV's x slice, relative to the inlet slice.

    A swarm flying the CFD velocity in every cube of a slice carries s times the inlet's number
    flux at equal density (the staircase holds more cube area than the CFD's open flow area,
    more so in some slices than others), so continuity at the CFD velocity needs n ~ 1 / s."""
    g = np.asarray(grid_cv, dtype=np.int64)
    u = np.asarray(target_velocity_m_s, dtype=float)[:, 0]
    ids = g.reshape(g.shape[0], -1)
    per_slice = np.array([u[row[row >= 0]].sum() for row in ids])
    if not per_slice[0] > 0:
        raise ValueError("the inlet (first x slice) carries no inflow: the CFD velocity there is not along +x")
    sl = np.empty(u.size)
    for i, row in enumerate(ids):
        sl[row[row >= 0]] = per_slice[i] / per_slice[0]
    if not np.all(sl > 0):
        raise ValueError("an x slice carries no net CFD flow; cannot design a swarm density for it")
    return sl


def staircase_contrast(grid_cv: np.ndarray, target_velocity_m_s: np.ndarray) -> float:
    """A = 1 - min(1/s) / max(1/s) (``slice_flux_area``): the density contrast continuity gives a swarm
    flying the CFD velocity on the staircase."""
    return _contrast(1.0 / slice_flux_area(grid_cv, target_velocity_m_s))


def _contrast(inv_s: np.ndarray) -> float:
    return 1.0 - float(inv_s.min() / inv_s.max())


def design_density(grid_cv: np.ndarray, target_velocity_m_s: np.ndarray, target_density: np.ndarray,
                   target_pressure: np.ndarray, continuity_weight: float, density_amplitude: float) -> np.ndarray:
    """Designed swarm density rho_d (mean 1) per CV.

    rho_d = 1 - k A (1 - f), f = (1 - beta) f_cfd + beta f_cont: a blend of the CFD's density pattern
    ``f_cfd`` (``cfd_pattern``) and the pattern ``f_cont`` = min-max of 1 / s (``slice_flux_area``)
    that continuity forces on a swarm flying exactly the CFD velocity.  The amplitude A = 1 -
    min(1/s) / max(1/s) is the staircase's own contrast, so beta = 1 and k = 1 give the density at
    which the CFD velocity is continuity-consistent, beta = 0 the CFD's density pattern at that
    amplitude (the swarm then trades velocity fidelity for it); k (``density_amplitude``) scales the
    contrast, again at the cost of velocity fidelity.  Nothing here is fitted to a particular duct.
    ValueError if k A >= 1 (the densest-to-thinnest ratio would not be finite and positive).
    """
    f_cfd = cfd_pattern(target_density, target_pressure)
    inv_s = 1.0 / slice_flux_area(grid_cv, target_velocity_m_s)
    contrast = _contrast(inv_s)
    amp = density_amplitude * contrast
    if not amp < 1.0:
        raise ValueError(f"density_amplitude {density_amplitude:g} times the staircase's contrast {contrast:.3f} "
                         f"is >= 1, so the designed density would reach 0; use a density_amplitude below "
                         f"{1.0 / contrast:.3g}")
    f = (1.0 - continuity_weight) * f_cfd + continuity_weight * _min_max(inv_s)
    rho = 1.0 - amp * (1.0 - f)
    return rho / rho.mean()


def _padded(grid_cv: np.ndarray) -> np.ndarray:
    g = np.full(tuple(s + 2 for s in grid_cv.shape), -1, dtype=np.int64)
    g[1:-1, 1:-1, 1:-1] = grid_cv
    return g


def _faces(pad: np.ndarray, shape_cells: tuple[int, int, int], axis: int):
    """Face grid index (m, 3), lower and upper cell id (-1: none) of every face normal to ``axis``."""
    shape = list(shape_cells)
    shape[axis] += 1
    idx = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), axis=-1).reshape(-1, 3)
    hi = pad[idx[:, 0] + 1, idx[:, 1] + 1, idx[:, 2] + 1]
    lo_idx = idx.copy()
    lo_idx[:, axis] -= 1
    lo = pad[lo_idx[:, 0] + 1, lo_idx[:, 1] + 1, lo_idx[:, 2] + 1]
    return tuple(shape), idx, lo, hi


def project(grid_cv: np.ndarray, target_velocity_m_s: np.ndarray, density: np.ndarray,
            open_fraction: np.ndarray, weight_exponent: float = DEFAULT_WEIGHT_EXPONENT,
            axial_weight: float = DEFAULT_AXIAL_WEIGHT) -> StaggeredField:
    """The projection of the module docstring, in two parts that together make ``D q = 0``.

    1. Axial faces: the flux through every x plane of the grid must equal the inflow Q (a closed
       duct).  Each plane's CV-CV faces keep the CFD pattern ``rho_f u*_f`` scaled by one factor
       per plane (``Q / sum_plane rho_f u*_f``): the correction is spread evenly over the plane,
       which is the least-squares choice for a plane's total.
    2. Lateral (y, z) faces: the axial fluxes leave a residual in each CV (the staircase narrows
       or widens, so flow must move sideways); the lateral fluxes closest to ``rho_f u*_f`` in
       ``sum w_f (q_f - rho_f u*_f)^2`` that absorb it come from one sparse Poisson solve
       ``(D W^-1 D^T) lam = D q* - r`` on the graph of lateral faces (block diagonal: one block
       per axial slice).

    ``grid_cv`` (nx, ny, nz) CV ids (-1: no CV); ``target_velocity_m_s`` (n_cv, 3) CFD velocity per CV;
    ``density`` (n_cv,) designed density (> 0); ``open_fraction`` (n_cv,) in (0, 1] (lateral weights).
    """
    import scipy.sparse as sp
    import scipy.sparse.csgraph as csgraph
    import scipy.sparse.linalg as spla

    g = np.asarray(grid_cv, dtype=np.int64)
    u = np.asarray(target_velocity_m_s, dtype=float)
    n_cv = int(u.shape[0])
    rho = np.asarray(density, dtype=float)
    if u.shape != (n_cv, 3) or rho.shape != (n_cv,):
        raise ValueError(f"target_velocity_m_s must be (n_cv, 3) and density (n_cv,), got {u.shape} and {rho.shape}")
    if not np.all(np.isfinite(u)):
        raise ValueError(f"CV {int(np.flatnonzero(~np.all(np.isfinite(u), axis=1))[0])}: target velocity not finite")
    if not np.all(rho > 0):
        raise ValueError("designed density must be > 0 in every CV")
    w_cv = np.maximum(np.clip(np.asarray(open_fraction, dtype=float), 0.0, 1.0), WEIGHT_FLOOR) ** weight_exponent
    pad = _padded(g)
    nx = g.shape[0]

    def face_values(lo, hi, per_cv):
        a, b = per_cv[np.maximum(lo, 0)], per_cv[np.maximum(hi, 0)]
        return np.where((lo >= 0) & (hi >= 0), 0.5 * (a + b), np.where(lo >= 0, a, b))

    # ---- 1. axial faces
    shape_x, idx_x, lo_x, hi_x = _faces(pad, g.shape, 0)
    inlet = (idx_x[:, 0] == 0) & (hi_x >= 0)
    open_x = ((lo_x >= 0) & (hi_x >= 0)) | ((idx_x[:, 0] == nx) & (lo_x >= 0)) | inlet
    rho_x = face_values(lo_x, hi_x, rho)
    q_x = np.where(open_x, rho_x * face_values(lo_x, hi_x, u[:, 0]), 0.0)
    q_in = float(q_x[inlet].sum())
    if not q_in > 0:
        raise ValueError("the inlet (first x slice) carries no inflow: the CFD velocity there is not along +x")
    for i in range(1, nx + 1):
        m = open_x & (idx_x[:, 0] == i)
        total = float(q_x[m].sum())
        if not total > 0:
            raise ValueError(f"x plane {i}: the CFD carries no net flow through it; cannot build a staggered field")
        q_x[m] *= q_in / total
    # ---- 2. one weighted least-squares projection over the CV-CV faces of all three axes
    both_x = (lo_x >= 0) & (hi_x >= 0)
    fixed = open_x & ~both_x                      # inlet and outlet faces keep the plane-scaled flux
    r = np.zeros(n_cv)                            # net outflow of each CV through its fixed faces
    np.add.at(r, lo_x[fixed & (lo_x >= 0)], q_x[fixed & (lo_x >= 0)])
    np.add.at(r, hi_x[fixed & (hi_x >= 0)], -q_x[fixed & (hi_x >= 0)])
    faces = []
    rows, cols, vals, q_star, w_face, rho_face = [], [], [], [], [], []
    n_unknown = 0
    for a in (0, 1, 2):
        shape, idx, lo, hi = (shape_x, idx_x, lo_x, hi_x) if a == 0 else _faces(pad, g.shape, a)
        k = np.flatnonzero((lo >= 0) & (hi >= 0))
        ids = np.arange(n_unknown, n_unknown + k.size)
        rows += [lo[k], hi[k]]
        cols += [ids, ids]
        vals += [np.ones(k.size), -np.ones(k.size)]
        rf = 0.5 * (rho[lo[k]] + rho[hi[k]])
        q_star.append(q_x[k] if a == 0 else rf * 0.5 * (u[lo[k], a] + u[hi[k], a]))
        w_face.append(np.minimum(w_cv[lo[k]], w_cv[hi[k]]) * (axial_weight if a == 0 else 1.0))
        rho_face.append(rf)
        faces.append((shape, k, ids))
        n_unknown += k.size
    q_star = np.concatenate(q_star)
    w_face = np.concatenate(w_face)
    rho_face = np.concatenate(rho_face)
    D = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n_cv, n_unknown))
    winv = 1.0 / w_face
    L = (D @ sp.diags(winv) @ D.T).tocsr()
    rhs = D @ q_star + r
    # each connected block is a pure Neumann problem: pin one CV per block (consistent: the fixed
    # inlet and outlet fluxes balance, and a block without them has no net source)
    n_comp, labels = csgraph.connected_components(L, directed=False)
    first = np.unique(labels, return_index=True)[1]
    pin = np.zeros(n_cv)
    pin[first] = np.maximum(L.diagonal()[first], 1.0)
    lam = spla.spsolve((L + sp.diags(pin)).tocsc(), rhs)
    q = q_star - winv * (D.T @ lam)
    div = D @ q + r
    u_face = q / rho_face

    out = []
    for a, (shape, k, ids) in enumerate(faces):
        arr = np.zeros(int(np.prod(shape)))
        if a == 0:
            arr[fixed] = q_x[fixed] / rho_x[fixed]
        arr[k] = u_face[ids]
        out.append(arr.reshape(shape))
    return StaggeredField(face_u_x_m_s=out[0], face_u_y_m_s=out[1], face_u_z_m_s=out[2], design_density=rho,
                          max_divergence=float(np.max(np.abs(div))) / q_in)


def static_velocity_nrmse(grid_cv: np.ndarray, face_u_x_m_s: np.ndarray, target_velocity_m_s: np.ndarray) -> float:
    """The DESIGN.md section 4 velocity nRMSE of the field itself, no vehicle: each CV's cube-mean
    axial velocity (``fisc_agent.map.lookup.cube_mean_u_axial_m_s``, the rule agents fly) over its
    maximum against the CFD's axial velocity over its maximum."""
    u = cube_mean_u_axial_m_s(grid_cv, face_u_x_m_s)
    t = np.asarray(target_velocity_m_s, dtype=float)[:, 0]
    return float(np.sqrt(np.mean((u / u.max() - t / t.max()) ** 2)))


def build_staggered(grid_cv: np.ndarray, target_velocity_m_s: np.ndarray, target_density: np.ndarray,
                    target_pressure: np.ndarray, open_fraction: np.ndarray,
                    config: StaggeredConfig = StaggeredConfig()) -> StaggeredField:
    """Designed density (``design_density``) then the projection (``project``).

    Without a ``continuity_weight``, beta is the lowest of ``AUTO_CONTINUITY_WEIGHTS`` whose field at
    k = 1 (or at the given ``density_amplitude``) keeps ``static_velocity_nrmse`` within
    ``config.velocity_limit`` (the last if none does).  Then, without a ``density_amplitude``, k is the
    largest of ``AUTO_DENSITY_AMPLITUDES`` whose field keeps it within ``config.velocity_budget`` (1 if
    none does; amplitudes with k A >= 1 are skipped)."""
    built: dict[tuple[float, float], tuple[StaggeredField, float]] = {}

    def field(beta: float, k: float) -> tuple[StaggeredField, float]:
        if (beta, k) not in built:
            rho = design_density(grid_cv, target_velocity_m_s, target_density, target_pressure, beta, k)
            st = project(grid_cv, target_velocity_m_s, rho, open_fraction, config.weight_exponent, config.axial_weight)
            built[beta, k] = st, static_velocity_nrmse(grid_cv, st.face_u_x_m_s, target_velocity_m_s)
        return built[beta, k]

    betas = AUTO_CONTINUITY_WEIGHTS if config.continuity_weight is None else (config.continuity_weight,)
    k_check = 1.0 if config.density_amplitude is None else config.density_amplitude
    for beta in betas:
        if len(betas) == 1 or field(beta, k_check)[1] <= config.velocity_limit:
            break
    if config.density_amplitude is not None:
        ks: tuple[float, ...] = (config.density_amplitude,)
    else:
        contrast = staircase_contrast(grid_cv, target_velocity_m_s)
        ks = tuple(k for k in AUTO_DENSITY_AMPLITUDES if k == 1.0 or k * contrast < 1.0)
    for k in ks:
        st, static = field(beta, k)
        if static <= config.velocity_budget:
            break
    return replace(st, density_amplitude=float(k), continuity_weight=float(beta), static_velocity_nrmse=static)
