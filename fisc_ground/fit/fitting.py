"""The paper's velocity fitting ("Velocity-Fitting" section), vectorised across CVs and candidates.

For every control volume j and every candidate agent count N in [N_min, N_max] the fit looks
for N velocity vectors v_1..v_N whose mean is the CV's target velocity (eq. velocity_constraint)
and whose velocity dispersion gives the CV's target swarm pressure (eq. pressure_constraint),
by minimising the paper's objective (eq. iterative_objective)::

    L(N) = || v_target - mean(v) ||^2 + alpha * | P_target - (2 m / (3 dV)) sum_i ||v_i - vbar||^2 |

with a Newton-type iteration that uses the Jacobian, started from the perturbed target
(eq. initialisation ``v^(0) = v_target + sigma xi``, ``sigma^2 = P_target 3 dV / (2 m N)``) and
stopped when the update norm ``||dv^(k)|| < eps`` (eps = 1e-6). N* = argmin_N L(N).

Newton step.  The residual vector is ``r = [vbar - v_target (3 comps), sqrt(alpha) (P(v) - P_t)]``
(4 equations, 3N unknowns: under-determined).  The step is the minimum-norm Newton step
``dv = -J^T (J J^T + mu I)^-1 r`` (mu = 1e-12 of the largest diagonal entry, only to keep the
system regular when the dispersion is zero), which converges quadratically.  ``J J^T`` is a
4x4 "arrow" matrix ``[[I/N, b], [b^T, q]]`` (``b = 2 c sqrt(alpha) sum_i d_i / N``,
``q = 4 alpha c^2 sum_i ||d_i||^2``, ``d_i = v_i - vbar``, ``c = 2m / (3 dV)``); it is solved
exactly in closed form (Schur complement on the scalar corner), batched over all CVs and
candidates, which equals ``np.linalg.solve`` on the same matrices (tested) at a fraction of the
cost.  Geometrically the step corrects the mean exactly and scales the deviations by
``(1 + P_t / P) / 2``, i.e. it is Newton's square-root iteration on the rms deviation; the
iteration therefore converges to ``v_target + d0 sqrt(P_t / P(v0))`` (tested).

Layout: CVs are processed in chunks (bounded memory); inside a chunk each candidate N is one
slot-major array ``(N, 3, n_chunk)``, so every operation is a contiguous vectorised pass over
all CVs of the chunk and no padding is computed.  Systems drop out of the working set as they
converge.  There is no Python loop over CVs; the loops are over chunks, the candidates and the
Newton iterations.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

#: CVs per random-number block: the initial perturbation of a CV depends only on (seed, its block),
#: so results do not depend on the processing chunk size.
NOISE_BLOCK_CVS = 1024
#: Default number of CVs processed together (bounds the memory: about 0.1 GB of float64 per array).
DEFAULT_CHUNK_CVS = 32 * NOISE_BLOCK_CVS
#: Relative Levenberg-Marquardt regularisation of J J^T (only matters when the dispersion is zero).
_DAMPING = 1e-12


@dataclass(frozen=True)
class FitResult:
    """Velocity-fitting result for n CVs (unscaled velocities, reference frame)."""

    velocities_m_s: np.ndarray
    """(n, n_max, 3) fitted vectors v_{s,d,j,k} of the chosen N*; NaN for slots k >= N*_j [m/s]."""
    n_star: np.ndarray
    """(n,) int32 chosen agent count N*_j (argmin of the loss, tie-break: largest N)."""
    loss: np.ndarray
    """(n,) final objective (eq. iterative_objective) of the chosen candidate."""
    mean_velocity_m_s: np.ndarray
    """(n, 3) mean of the N* fitted vectors [m/s] (eq. velocity_constraint's right-hand side)."""
    pressure: np.ndarray
    """(n,) achieved swarm pressure (eq. pressure_constraint: deviations from the target velocity)."""
    iterations: np.ndarray
    """(n,) int32 Newton iterations used by the chosen candidate."""
    converged: np.ndarray
    """(n,) bool: the chosen candidate's update norm fell below ``tol`` within ``max_iter``."""
    seconds: float
    """Wall time spent in the fitting itself (``time.perf_counter``), input checks excluded [s]."""
    candidate_loss: np.ndarray
    """(n, n_max - n_min + 1) final loss of every candidate N = n_min..n_max."""

    @property
    def n_cv(self) -> int:
        """Number of CVs."""
        return int(self.n_star.shape[0])


def pressure_coefficient(agent_mass_kg: float, cell_volume_m3: np.ndarray | float) -> np.ndarray:
    """``c = 2 m / (3 dV)``, the factor of eq. pressure_constraint (and eq. swarm_pressure)."""
    return 2.0 * np.asarray(agent_mass_kg, dtype=np.float64) / (
        3.0 * np.asarray(cell_volume_m3, dtype=np.float64)
    )


def swarm_pressure(
    velocities_m_s: np.ndarray,
    agent_mass_kg: float,
    cell_volume_m3: np.ndarray | float,
    reference_velocity_m_s: np.ndarray | None = None,
) -> np.ndarray:
    """Swarm pressure of a CV's velocity vectors, eq. pressure_constraint.

    ``P = (2 m / (3 dV)) sum_i ||v_i - v_ref||^2`` for ``velocities_m_s`` of shape (..., N, 3);
    NaN rows count as absent agents.  ``v_ref`` is ``reference_velocity_m_s`` (..., 3) — the
    target velocity in eq. pressure_constraint — or, when None, the mean of the present vectors
    (the form used inside eq. iterative_objective and eq. internal_pressure).  At a converged
    fit the mean equals the target, so both give the same value.  ``cell_volume_m3`` broadcasts
    against the leading dimensions.
    """
    v = np.asarray(velocities_m_s, dtype=np.float64)
    present = np.all(np.isfinite(v), axis=-1)
    if reference_velocity_m_s is None:
        count = present.sum(axis=-1)
        ref = np.where(present[..., None], v, 0.0).sum(axis=-2) / np.maximum(count, 1)[..., None]
    else:
        ref = np.asarray(reference_velocity_m_s, dtype=np.float64)
    dev = np.where(present[..., None], v - ref[..., None, :], 0.0)
    return pressure_coefficient(agent_mass_kg, cell_volume_m3) * np.einsum("...kx,...kx->...", dev, dev)


def objective(
    velocities_m_s: np.ndarray,
    target_velocity_m_s: np.ndarray,
    pressure_target: np.ndarray,
    agent_mass_kg: float,
    cell_volume_m3: np.ndarray | float,
    alpha: float = 1.0,
) -> np.ndarray:
    """The paper's loss, eq. iterative_objective, for vectors (..., N, 3) (NaN rows = absent).

    ``L = ||v_target - vbar||^2 + alpha |P_target - (2m/(3 dV)) sum_i ||v_i - vbar||^2|``.
    """
    v = np.asarray(velocities_m_s, dtype=np.float64)
    present = np.all(np.isfinite(v), axis=-1)
    count = np.maximum(present.sum(axis=-1), 1)
    vbar = np.where(present[..., None], v, 0.0).sum(axis=-2) / count[..., None]
    p = swarm_pressure(v, agent_mass_kg, cell_volume_m3, None)
    dmean = np.asarray(target_velocity_m_s, dtype=np.float64) - vbar
    return np.einsum("...x,...x->...", dmean, dmean) + alpha * np.abs(pressure_target - p)


def initial_dispersion(
    pressure_target: np.ndarray,
    cell_volume_m3: np.ndarray | float,
    agent_mass_kg: float,
    n_agents: np.ndarray | int,
) -> np.ndarray:
    """sigma of the perturbed initialisation: ``sigma^2 = P_target 3 dV / (2 m N)`` (paper).

    It is also the rms deviation magnitude ``sqrt(mean_i ||v_i - v_target||^2)`` that a fit with
    N agents must realise to meet the pressure target (eq. pressure_constraint).
    """
    return np.sqrt(
        np.asarray(pressure_target, dtype=np.float64)
        * 3.0
        * np.asarray(cell_volume_m3, dtype=np.float64)
        / (2.0 * agent_mass_kg * np.asarray(n_agents, dtype=np.float64))
    )


def select_n_star(candidate_loss: np.ndarray, candidate_n: np.ndarray, tie_tol: float) -> np.ndarray:
    """Index of the chosen candidate per CV: ``N* = argmin L(N)`` with a deterministic tie-break.

    Every N >= 2 can meet both targets exactly, so several candidates usually end at a loss of
    round-off size.  Candidates whose loss is within ``tie_tol`` of the CV's minimum are tied,
    and among them the **largest N** wins: the per-agent rms deviation needed for the pressure
    falls as ``1 / sqrt(N)`` (``sigma_N^2 = P 3 dV / (2 m N)``), so more slots mean smaller
    velocity deviations per agent (lower peak commanded speeds, so a larger speed scale S), and
    in ``slot`` command mode a CV whose agents occupy only some of the slots misses the target
    mean by less.  ``candidate_n`` must be increasing.  Returns (n,) int64 indices.
    """
    loss = np.asarray(candidate_loss, dtype=np.float64)
    best = np.min(loss, axis=1, keepdims=True)
    tied = loss <= best + tie_tol
    n_cand = loss.shape[1]
    # last True along the (increasing-N) candidate axis
    return n_cand - 1 - np.argmax(tied[:, ::-1], axis=1)


def initial_guess(
    target_velocity_m_s: np.ndarray,
    pressure_target: np.ndarray,
    cell_volume_m3: np.ndarray,
    agent_mass_kg: float,
    candidate_n: np.ndarray,
    n_max: int,
    seed: int,
    first_cv: int = 0,
) -> list[np.ndarray]:
    """Perturbed initialisation ``v^(0) = v_target + sigma_N xi``, ``xi ~ N(0, I)`` (paper).

    Returns one array per candidate N, in the slot-major layout of the solver: shape
    (N, 3, n), element [i, x, j] = component x of agent i's start velocity in CV j.
    Per CV one set of n_max standard-normal vectors is drawn and candidate N uses its first N
    (every candidate's start is still ``v_target + sigma_N xi`` with ``xi ~ N(0, I)``).
    The noise of CV ``first_cv + j`` comes from ``np.random.default_rng([seed, block])`` with
    ``block = (first_cv + j) // NOISE_BLOCK_CVS``, so a CV's start does not depend on how the
    CVs are chunked.  ``cell_volume_m3`` is an (n,) array.
    """
    vt = np.asarray(target_velocity_m_s, dtype=np.float64)
    n = vt.shape[0]
    xi = np.empty((n_max, 3, n))
    b0 = first_cv // NOISE_BLOCK_CVS
    b1 = -(-(first_cv + n) // NOISE_BLOCK_CVS)
    for block in range(b0, b1):
        lo = block * NOISE_BLOCK_CVS
        noise = np.random.default_rng([seed, block]).standard_normal((n_max, 3, NOISE_BLOCK_CVS))
        s = max(lo, first_cv)
        e = min(lo + NOISE_BLOCK_CVS, first_cv + n)
        xi[:, :, s - first_cv : e - first_cv] = noise[:, :, s - lo : e - lo]
    starts = []
    for n_agents in np.asarray(candidate_n):
        sigma = initial_dispersion(pressure_target, cell_volume_m3, agent_mass_kg, n_agents)
        starts.append(xi[:n_agents] * sigma + vt.T)
    return starts


def arrow_solve(
    inv_n: np.ndarray, b: np.ndarray, q: np.ndarray, r_v: np.ndarray, r_p: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Solve the batched 4x4 system ``[[inv_n I3, b], [b^T, q]] [y_v; y_p] = [r_v; r_p]`` exactly.

    Shapes: ``inv_n``, ``q``, ``r_p`` (...,); ``b``, ``r_v`` (3, ...) (component axis first).
    Schur complement on the scalar corner; this is ``(J J^T + mu I) y = r`` of the Newton step.
    """
    y_p = (r_p - np.einsum("x...,x...->...", b, r_v) / inv_n) / (
        q - np.einsum("x...,x...->...", b, b) / inv_n
    )
    y_v = (r_v - b * y_p) / inv_n
    return y_v, y_p


def _newton(
    v: np.ndarray,
    vt: np.ndarray,
    pt: np.ndarray,
    c: np.ndarray,
    alpha: float,
    tol: float,
    max_iter: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Minimum-norm Newton iteration for one candidate N on v (N, 3, B), in place.

    ``vt`` (3, B), ``pt`` and ``c`` (B,).  Converged systems drop out of the working set.
    Returns v, iterations (B,) int32, converged (B,) bool.
    """
    n_agents, _, bsz = v.shape
    inv_n = 1.0 / n_agents
    sqa = float(np.sqrt(alpha))
    iterations = np.zeros(bsz, dtype=np.int32)
    converged = np.zeros(bsz, dtype=bool)
    idx = np.arange(bsz)
    w, vt_w, pt_w, c_w = v, vt, pt, c
    for _ in range(max_iter):
        vbar = w.sum(axis=0) * inv_n  # (3, b)
        d = w - vbar  # deviations d_i (N, 3, b)
        s = np.einsum("kxb,kxb->b", d, d)
        g = 2.0 * sqa * c_w  # d r_p / d v_i = g d_i
        r_v = vbar - vt_w
        r_p = sqa * (c_w * s - pt_w)
        b = (g * inv_n) * d.sum(axis=0)
        q = g * g * s
        mu = _DAMPING * np.maximum(inv_n, q)
        y_v, y_p = arrow_solve(inv_n + mu, b, q + mu, r_v, r_p)
        # dv_i = -J_i^T y = -(y_v / N + g d_i y_p)
        d *= g * y_p
        d += y_v * inv_n
        w -= d
        step = np.sqrt(np.einsum("kxb,kxb->b", d, d))
        iterations[idx] += 1
        done = step < tol
        if done.any():
            converged[idx[done]] = True
            if w is not v:
                v[:, :, idx[done]] = w[:, :, done]
            keep = ~done
            if not keep.any():
                w = None
                break
            w, vt_w, pt_w, c_w, idx = w[:, :, keep], vt_w[:, keep], pt_w[keep], c_w[keep], idx[keep]
    if w is not None and w is not v:
        v[:, :, idx] = w
    return v, iterations, converged


def _validate(vt, pt, vol, agent_mass_kg, n_min, n_max, alpha, tol, max_iter):
    if vt.ndim != 2 or vt.shape[1] != 3:
        raise ValueError(f"target_velocity_m_s must be an (n, 3) array, got shape {vt.shape}")
    n = vt.shape[0]
    if pt.shape != (n,):
        raise ValueError(f"pressure_target must have shape ({n},), got {pt.shape}")
    if vol.shape != (n,):
        raise ValueError(f"cell_volume_m3 must be a scalar or an ({n},) array, got shape {vol.shape}")
    if not (np.isfinite(agent_mass_kg) and agent_mass_kg > 0):
        raise ValueError(f"agent_mass_kg must be positive and finite, got {agent_mass_kg!r}")
    if not (1 <= n_min <= n_max):
        raise ValueError(f"need 1 <= n_min <= n_max, got n_min={n_min}, n_max={n_max}")
    if not (np.isfinite(alpha) and alpha > 0):
        raise ValueError(f"alpha must be positive and finite, got {alpha!r}")
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be positive and finite, got {tol!r}")
    if max_iter < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter!r}")
    bad_v = ~np.all(np.isfinite(vt), axis=1)
    if bad_v.any():
        j = int(np.flatnonzero(bad_v)[0])
        raise ValueError(f"CV {j}: target velocity is not finite: {vt[j].tolist()}")
    if not np.all(np.isfinite(pt)):
        j = int(np.flatnonzero(~np.isfinite(pt))[0])
        raise ValueError(f"CV {j}: pressure target is not finite: {float(pt[j])!r}")
    if np.any(pt < 0):
        j = int(np.flatnonzero(pt < 0)[0])
        raise ValueError(
            f"CV {j}: pressure target {float(pt[j])!r} is negative, which no set of velocities can "
            "realise (the swarm pressure of eq. pressure_constraint is >= 0); map CFD pressure "
            "with fisc_ground.fit.scaling.swarm_pressure_target first"
        )
    bad_vol = ~(np.isfinite(vol) & (vol > 0))
    if bad_vol.any():
        j = int(np.flatnonzero(bad_vol)[0])
        raise ValueError(f"CV {j}: cell volume {float(vol[j])!r} is not positive and finite")


def fit_velocities(
    target_velocity_m_s: np.ndarray,
    pressure_target: np.ndarray,
    cell_volume_m3: np.ndarray | float,
    agent_mass_kg: float = 1.0,
    n_min: int = 2,
    n_max: int = 10,
    alpha: float = 1.0,
    tol: float = 1e-6,
    max_iter: int = 50,
    seed: int = 0,
    chunk_cvs: int = DEFAULT_CHUNK_CVS,
) -> FitResult:
    """Fit N*_j velocity vectors per CV to the target velocity and swarm pressure (paper's fit).

    ``target_velocity_m_s`` (n, 3) are the CV mean CFD velocities; ``pressure_target`` (n,) the
    *swarm* pressure targets (>= 0, e.g. ``kappa (P_cfd - min P_cfd)``); ``cell_volume_m3`` the
    CV volume dV (scalar or (n,)); ``agent_mass_kg`` m.  For N = n_min..n_max the minimum-norm
    Newton iteration (module docstring) runs from the seeded perturbed start until
    ``||dv|| < tol`` or ``max_iter``; N* is chosen by ``select_n_star`` (least loss, ties within
    ``tol`` -> largest N).  ``chunk_cvs`` CVs are processed at a time (rounded up to a multiple
    of ``NOISE_BLOCK_CVS``; the result does not depend on it).

    Raises ValueError naming the CV index for non-finite targets, negative pressure targets or
    non-positive volumes, and for invalid parameters.
    """
    vt = np.asarray(target_velocity_m_s, dtype=np.float64)
    pt = np.asarray(pressure_target, dtype=np.float64)
    n = vt.shape[0] if vt.ndim >= 1 else 0
    vol = np.asarray(cell_volume_m3, dtype=np.float64)
    if vol.ndim == 0:
        vol = np.full(n, float(vol))
    n_min, n_max, max_iter = int(n_min), int(n_max), int(max_iter)
    _validate(vt, pt, vol, agent_mass_kg, n_min, n_max, alpha, tol, max_iter)

    t0 = time.perf_counter()
    cand = np.arange(n_min, n_max + 1)
    n_cand = cand.size
    c_all = pressure_coefficient(agent_mass_kg, vol)

    velocities = np.full((n, n_max, 3), np.nan)
    n_star = np.zeros(n, dtype=np.int32)
    loss = np.zeros(n)
    iterations = np.zeros(n, dtype=np.int32)
    converged = np.zeros(n, dtype=bool)
    cand_loss = np.zeros((n, n_cand))

    chunk = max(1, -(-int(chunk_cvs) // NOISE_BLOCK_CVS)) * NOISE_BLOCK_CVS
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        vt_c, pt_c, c_c = vt[s:e].T.copy(), pt[s:e], c_all[s:e]
        starts = initial_guess(vt[s:e], pt_c, vol[s:e], agent_mass_kg, cand, n_max, seed, first_cv=s)
        sols, its, convs = [], [], []
        lc = np.empty((e - s, n_cand))
        for ci, v in enumerate(starts):
            v, it_c, conv_c = _newton(v, vt_c, pt_c, c_c, alpha, tol, max_iter)
            # final loss, eq. iterative_objective
            vbar = v.mean(axis=0)
            dev = v - vbar
            p_obj = c_c * np.einsum("kxb,kxb->b", dev, dev)
            dm = vt_c - vbar
            lc[:, ci] = np.einsum("xb,xb->b", dm, dm) + alpha * np.abs(pt_c - p_obj)
            sols.append(v)
            its.append(it_c)
            convs.append(conv_c)
        pick = select_n_star(lc, cand, tol)
        for ci, v in enumerate(sols):
            rows = np.flatnonzero(pick == ci)
            if rows.size == 0:
                continue
            velocities[s + rows, : cand[ci]] = v[:, :, rows].transpose(2, 0, 1)
            iterations[s + rows] = its[ci][rows]
            converged[s + rows] = convs[ci][rows]
        n_star[s:e] = cand[pick]
        loss[s:e] = lc[np.arange(e - s), pick]
        cand_loss[s:e] = lc

    mean_v = np.nanmean(velocities, axis=1) if n else np.zeros((0, 3))
    pressure = swarm_pressure(velocities, agent_mass_kg, vol, vt)
    seconds = time.perf_counter() - t0
    return FitResult(
        velocities_m_s=velocities,
        n_star=n_star,
        loss=loss,
        mean_velocity_m_s=mean_v,
        pressure=pressure,
        iterations=iterations,
        converged=converged,
        seconds=seconds,
        candidate_loss=cand_loss,
    )


def fit_rmse(
    result: FitResult, target_velocity_m_s: np.ndarray, pressure_target: np.ndarray
) -> tuple[float, float]:
    """Validation residuals of a fit (paper: RMSE over the valid CVs).

    ``velocity_rmse = sqrt(mean_j ||vbar_j - v_target,j||^2)`` and
    ``pressure_rmse = sqrt(mean_j (P_j - P_target,j)^2)`` over the valid CVs, i.e. those whose
    chosen candidate converged and whose fitted mean and pressure are finite.  NaN when no CV is
    valid.
    """
    vt = np.asarray(target_velocity_m_s, dtype=np.float64)
    pt = np.asarray(pressure_target, dtype=np.float64)
    valid = (
        result.converged
        & np.all(np.isfinite(result.mean_velocity_m_s), axis=1)
        & np.isfinite(result.pressure)
    )
    if not valid.any():
        return float("nan"), float("nan")
    dv = result.mean_velocity_m_s[valid] - vt[valid]
    dp = result.pressure[valid] - pt[valid]
    return float(np.sqrt(np.mean(np.sum(dv * dv, axis=1)))), float(np.sqrt(np.mean(dp * dp)))


def fit_cv_reference(
    target_velocity_m_s: np.ndarray,
    pressure_target: float,
    cell_volume_m3: float,
    agent_mass_kg: float = 1.0,
    n_min: int = 2,
    n_max: int = 10,
    alpha: float = 1.0,
    tol: float = 1e-6,
    seed: int = 0,
) -> tuple[np.ndarray, int, float, np.ndarray]:
    """Plain single-CV reference fit (test oracle and benchmark baseline), one CV at a time.

    For each candidate N: ``scipy.optimize.least_squares`` (trust-region reflective, analytic
    Jacobian) on the same residual vector as ``fit_velocities`` from the paper's perturbed start
    (``np.random.default_rng(seed)``); then the paper's loss per candidate and the same N*
    selection.  Returns ``(velocities (N*, 3), N*, loss, candidate_loss (n_cand,))``.
    """
    from scipy.optimize import least_squares

    vt = np.asarray(target_velocity_m_s, dtype=np.float64).reshape(3)
    c = float(pressure_coefficient(agent_mass_kg, cell_volume_m3))
    sqa = float(np.sqrt(alpha))
    rng = np.random.default_rng(seed)
    cand = np.arange(n_min, n_max + 1)
    sols, losses = [], []
    for n_agents in cand:
        sigma = float(initial_dispersion(pressure_target, cell_volume_m3, agent_mass_kg, n_agents))
        x0 = (vt + sigma * rng.standard_normal((n_agents, 3))).ravel()

        def residual(x, n_agents=n_agents):
            v = x.reshape(n_agents, 3)
            vbar = v.mean(axis=0)
            d = v - vbar
            return np.concatenate([vbar - vt, [sqa * (c * np.sum(d * d) - pressure_target)]])

        def jacobian(x, n_agents=n_agents):
            v = x.reshape(n_agents, 3)
            d = v - v.mean(axis=0)
            jac = np.zeros((4, 3 * n_agents))
            for i in range(n_agents):
                jac[0:3, 3 * i : 3 * i + 3] = np.eye(3) / n_agents
                jac[3, 3 * i : 3 * i + 3] = 2.0 * sqa * c * d[i]
            return jac

        sol = least_squares(residual, x0, jac=jacobian, method="trf", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        v = sol.x.reshape(n_agents, 3)
        sols.append(v)
        losses.append(float(objective(v, vt, pressure_target, agent_mass_kg, cell_volume_m3, alpha)))
    cand_loss = np.asarray(losses)
    pick = int(select_n_star(cand_loss[None, :], cand, tol)[0])
    return sols[pick], int(cand[pick]), float(cand_loss[pick]), cand_loss
