"""The paper's test scenarios (section "Test Scenarios"), seeded and reproducible.

* Case 1, tunnel seeding (:func:`seed_positions`): N*_j agents in every CV whose centre lies at
  ``x <= x_axial``, uniformly at random inside the CV; they start flying their command.
* Case 2, reservoir (:class:`Reservoir`): agents enter through the inlet (the CVs of the first
  slice) at the paper's source rate (eq. source_rate)

      N_batch / dt_source  ~=  N*_entry |v_s,entry| / l

  applied *per inlet CV* j with that CV's N*_j and entry command ``v_s,entry = S v_{s,d,j}``
  (the velocity the agents fly there); the inlet's total rate is the sum over the slice.
  This is the number flux that keeps N*_j agents in a cube of edge l moving at |v|:
  n |v| l^2 = (N*/l^3) |v| l^2.  Fractional agents carry over from batch to batch (a
  deterministic accumulator), so over a time T the inlet injects sum_j rate_j T agents to
  within one agent per inlet CV.  Each batch is spread uniformly over the inlet CV's upstream
  face in (y, z) and over the distance ``|v_x| dt_source`` (capped at l) in x, i.e. where a
  continuous inflow would have put those agents during the interval.

  Mode ``kinetic`` (``Reservoir(..., kinetic_persistence_s=T)``): every agent flies the field plus
  a persistent deviation of rms sigma_j along a direction d it keeps for T.  A gas streaming out
  of a reservoir crosses the inlet face with a *flux*-weighted velocity distribution: a direction
  class d enters at a rate proportional to its axial speed (u + sigma d_x)+, so that inside the
  duct every class has the same density.  ``Reservoir.admit`` applies that weight to each batch
  (thinning: an agent is admitted with probability (u + sigma d_x)+ / (u + sigma), d_x its own
  deviation at entry, uniform on [-1, 1]) and the rate is divided by the mean admission
  probability E = a / (1 + a) for a = u / sigma >= 1, (1 + a) / 4 below, so the expected inflow
  stays eq. source_rate.  Without it, slow classes (d_x near -u / sigma) entered as often as fast
  ones and piled up in the first slices (1.2x the designed density).

Population scale (``--agents N``): both scenarios take a ``population_scale`` that multiplies
N* (seeding, with largest-remainder rounding so the total is exactly N) or the source rate
(reservoir).  ``scale_for_agents`` gives the scale that makes the seeded total, or the
reservoir's nominal population sum_j N*_j, equal to N.
"""

from __future__ import annotations

import numpy as np

from fisc_agent.map.lookup import CommandField
from sim.kernels import jit_kernels
from sim.kinetic_step import BatchAdmission, deviation_x


def seeded_cvs(field: CommandField, x_axial_m: float = np.inf) -> np.ndarray:
    """CV ids seeded in Case 1: centre x <= ``x_axial_m`` and N*_j > 0."""
    return np.flatnonzero((field.centers_m[:, 0] <= x_axial_m) & (np.asarray(field.n_star) > 0))


def apportion(weights: np.ndarray, total: int) -> np.ndarray:
    """Integer counts proportional to ``weights`` that sum exactly to ``total`` (largest remainder)."""
    w = np.asarray(weights, dtype=float)
    if total < 0:
        raise ValueError(f"total must be >= 0, got {total}")
    if w.size == 0 or w.sum() <= 0:
        if total:
            raise ValueError("cannot apportion agents over zero weights")
        return np.zeros(w.size, dtype=np.int64)
    exact = w * (total / w.sum())
    base = np.floor(exact).astype(np.int64)
    rest = total - int(base.sum())
    if rest:
        order = np.argsort(-(exact - base), kind="stable")
        base[order[:rest]] += 1
    return base


def seed_counts(field: CommandField, x_axial_m: float = np.inf, n_agents: int | None = None) -> np.ndarray:
    """(n_cv,) agents per CV for Case 1: N*_j in the seeded CVs (0 elsewhere), or N*
    proportionally rescaled to a total of ``n_agents``."""
    counts = np.zeros(field.n_cv, dtype=np.int64)
    cvs = seeded_cvs(field, x_axial_m)
    n_star = np.asarray(field.n_star, dtype=np.int64)[cvs]
    counts[cvs] = n_star if n_agents is None else apportion(n_star, int(n_agents))
    return counts


def seed_positions(field: CommandField, rng: np.random.Generator, x_axial_m: float = np.inf,
                   n_agents: int | None = None) -> np.ndarray:
    """Case 1 (tunnel seeding): (N, 3) positions, ``seed_counts`` agents uniform in each CV."""
    counts = seed_counts(field, x_axial_m, n_agents)
    cv = np.repeat(np.arange(field.n_cv), counts)
    lo = field.centers_m[cv] - 0.5 * field.cell_size_m
    return lo + rng.random((cv.size, 3)) * field.cell_size_m


def inlet_cvs(field: CommandField) -> np.ndarray:
    """CV ids of the first slice (smallest grid x index present): the inlet."""
    ix = np.floor((field.centers_m[:, 0] - field.origin_m[0]) / field.cell_size_m + 1e-9).astype(np.int64)
    return np.flatnonzero(ix == ix.min())


def source_rate(n_star_entry: np.ndarray, v_entry_m_s: np.ndarray, cell_size_m: float) -> np.ndarray:
    """Eq. source_rate: N_batch / dt_source = N*_entry |v_s,entry| / l  [agents/s], per inlet CV.

    ``n_star_entry`` (m,), ``v_entry_m_s`` (m, 3) the (scaled) entry commands, ``cell_size_m`` l.
    """
    return np.asarray(n_star_entry, dtype=float) * np.linalg.norm(v_entry_m_s, axis=1) / float(cell_size_m)


def kinetic_admission(u_m_s: np.ndarray, spread_m_s: np.ndarray, d_x: np.ndarray) -> np.ndarray:
    """Admission probability (u + sigma d_x)+ / (u + sigma) of an agent entering with axial field
    speed u, deviation rms sigma and deviation direction x component d_x (module docstring)."""
    u = np.abs(np.asarray(u_m_s, dtype=float))
    sg = np.asarray(spread_m_s, dtype=float)
    return np.clip((u + sg * np.asarray(d_x, dtype=float)) / np.maximum(u + sg, 1e-12), 0.0, 1.0)


def kinetic_admission_mean(u_m_s: np.ndarray, spread_m_s: np.ndarray) -> np.ndarray:
    """Mean of ``kinetic_admission`` over d_x uniform on [-1, 1]: a / (1 + a) for a = u / sigma >= 1,
    (1 + a) / 4 below (1 for sigma = 0)."""
    u = np.abs(np.asarray(u_m_s, dtype=float))
    sg = np.asarray(spread_m_s, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = np.where(u >= sg, u / (u + sg), (u + sg) / (4.0 * sg))
    if not np.all(mean > 0):
        raise ValueError("an inlet CV has no axial entry speed and no deviation: no agent would be admitted")
    return mean


def scale_for_agents(field: CommandField, n_agents: int | None, x_axial_m: float = np.inf) -> float:
    """Population scale that makes sum_j N*_j (over the seeded CVs) equal ``n_agents`` (1 if None)."""
    if n_agents is None:
        return 1.0
    total = float(np.asarray(field.n_star)[seeded_cvs(field, x_axial_m)].sum())
    if total <= 0:
        raise ValueError("the map has no CV with N* > 0")
    return float(n_agents) / total


def is_due(next_t_s: float, t_s: float) -> bool:
    """Whether ``periods_due(next_t_s, t_s, period)`` counts an event (1e-9 s early counts)."""
    return next_t_s <= t_s + 1e-9


def periods_due(next_t_s: float, t_s: float, period_s: float) -> tuple[int, float]:
    """How many events of a clock ticking every ``period_s``, next due at ``next_t_s``, are due by
    ``t_s`` (1e-9 s early counts), and when the one after them is due."""
    k = 0
    while is_due(next_t_s, t_s):
        next_t_s += period_s
        k += 1
    return k, next_t_s


class Reservoir:
    """Case 2: batches of agents through the inlet at eq. source_rate (see module docstring)."""

    def __init__(self, field: CommandField, interval_s: float = 0.05, population_scale: float = 1.0,
                 kinetic_persistence_s: float | None = None) -> None:
        if not interval_s > 0:
            raise ValueError(f"reservoir interval_s must be > 0, got {interval_s!r}")
        if not population_scale >= 0:
            raise ValueError(f"population_scale must be >= 0, got {population_scale!r}")
        if kinetic_persistence_s is not None and not (kinetic_persistence_s > 0 and np.isfinite(kinetic_persistence_s)):
            raise ValueError(f"kinetic_persistence_s must be finite and > 0, got {kinetic_persistence_s!r}")
        if kinetic_persistence_s is not None and field.spread_m_s is None:
            raise ValueError("a kinetic reservoir needs a field with the fitted spread (CommandField.from_map)")
        self.kinetic_persistence_s = kinetic_persistence_s
        self.field = field
        self.interval_s = float(interval_s)
        self.cvs = inlet_cvs(field)
        self.entry_cmd_m_s = np.asarray(field.mean_cmd_m_s)[self.cvs]
        self.rate_per_cv = population_scale * source_rate(np.asarray(field.n_star)[self.cvs],
                                                          self.entry_cmd_m_s, field.cell_size_m)
        #: candidates per second and inlet CV: the rate divided by the mean admission (kinetic)
        self._candidate_rate_per_cv = self.rate_per_cv
        if kinetic_persistence_s is not None:
            self._candidate_rate_per_cv = self.rate_per_cv / kinetic_admission_mean(
                self.entry_cmd_m_s[:, 0], np.asarray(field.spread_m_s)[self.cvs])
        self._entry_u_m_s = np.asarray(field.mean_cmd_m_s)[:, 0]
        self._spread_m_s = None if field.spread_m_s is None else np.asarray(field.spread_m_s)
        self._carry = np.zeros(self.cvs.size)
        self._next_t = 0.0
        self._admission = None  # numba: sim.kinetic_step.BatchAdmission of this reservoir (made at its first batch)

    @property
    def rate_per_s(self) -> float:
        """Total nominal inflow (sum over the inlet slice) [agents/s]."""
        return float(self.rate_per_cv.sum())

    def batch(self, rng: np.random.Generator) -> np.ndarray:
        """Positions (k, 3) of one batch (one interval's worth of inflow; a kinetic reservoir's
        candidates, see ``admit``)."""
        return self._batch(rng)[0]

    def entering(self, rng: np.random.Generator, first_id: int, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """One batch after admission: positions (k, 3) and ids (``batch`` then ``admit``; a kinetic reservoir
        with numba: both in one pass, ``sim.kinetic_step.BatchAdmission``, the same draws and bits)."""
        if self.kinetic_persistence_s is not None and jit_kernels() is not None:
            counts = self._counts()
            k = int(counts.sum())
            u = rng.random((k, 3))
            r = rng.random(k) if k else np.zeros(0)
            if self._admission is None:
                self._admission = BatchAdmission(self.cvs, self.field, self.entry_cmd_m_s[:, 0], self.interval_s,
                                                 self._entry_u_m_s, self._spread_m_s)
            return self._admission(counts, u, r, first_id, float(t_s) / self.kinetic_persistence_s)
        pos, cv = self._batch(rng)
        return self.admit(pos, first_id, t_s, rng, cv)

    def _counts(self) -> np.ndarray:
        """Candidates of the next batch per inlet CV (the accumulators advanced by one interval)."""
        self._carry += self._candidate_rate_per_cv * self.interval_s
        counts = np.floor(self._carry).astype(np.int64)
        self._carry -= counts
        return counts

    def _batch(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        counts = self._counts()
        cv = np.repeat(self.cvs, counts)
        l = self.field.cell_size_m
        lo = self.field.centers_m[cv] - 0.5 * l
        u = rng.random((cv.size, 3))
        depth = np.minimum(np.abs(np.repeat(self.entry_cmd_m_s[:, 0], counts)) * self.interval_s, l)
        pos = lo + u * l
        pos[:, 0] = lo[:, 0] + u[:, 0] * depth
        return pos, cv

    def admit(self, pos_m: np.ndarray, first_id: int, t_s: float, rng: np.random.Generator,
              cv_ids: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The agents of a batch that enter, and their ids: candidate k gets id ``first_id + k``;
        all enter unless the reservoir is kinetic, which admits each with probability
        ``kinetic_admission`` of its own deviation at ``t_s`` (ids of the others are skipped).
        ``cv_ids``: the candidates' CVs if known (else looked up)."""
        pos = np.asarray(pos_m, dtype=float).reshape(-1, 3)
        ids = np.arange(first_id, first_id + pos.shape[0], dtype=np.int64)
        if self.kinetic_persistence_s is None or pos.shape[0] == 0:
            return pos, ids
        cv = self.field.cv_of(pos) if cv_ids is None else np.asarray(cv_ids, dtype=np.int64)
        j = np.maximum(cv, 0)
        d_x = deviation_x(ids, t_s, self.kinetic_persistence_s)  # numba when installed, same bits
        p = kinetic_admission(self._entry_u_m_s[j], self._spread_m_s[j], d_x)
        keep = rng.random(pos.shape[0]) < np.where(cv >= 0, p, 1.0)
        return pos[keep], ids[keep]

    def due(self, t_s: float) -> int:
        """Number of batches due by time ``t_s`` (advances the internal clock)."""
        k, self._next_t = periods_due(self._next_t, t_s, self.interval_s)
        return k

    def is_due(self, t_s: float) -> bool:
        """Whether ``due(t_s)`` would be > 0 (the clock left as it is)."""
        return is_due(self._next_t, t_s)


class StaggeredInlet:
    """Case 2 with the agents' own admission (``fisc-sim run --staggered-admission``): one agent every
    ``period_s`` (the map's ``admission_period_s``, the windows ``fisc-agent --entry-stagger auto`` flies),
    the first at t = 0, each at a uniformly random point of the inlet slice's upstream face (a random
    inlet CV, uniform on its face), instead of the eq. source_rate batches of ``Reservoir`` (which at a
    small population fill every inlet CV's accumulator at nearly the same time and inject slabs).
    Every agent enters (no kinetic flux weighting: real agents are not thinned)."""

    def __init__(self, field: CommandField, period_s: float) -> None:
        if not (np.isfinite(period_s) and period_s > 0):
            raise ValueError(f"staggered admission: period_s must be finite and > 0, got {period_s!r}")
        self.field = field
        self.period_s = float(period_s)
        self.cvs = inlet_cvs(field)
        self._next_t = 0.0

    @property
    def rate_per_s(self) -> float:
        """Admissions per second [agents/s]."""
        return 1.0 / self.period_s

    def due(self, t_s: float) -> int:
        """Number of admissions due by time ``t_s`` (advances the internal clock)."""
        k, self._next_t = periods_due(self._next_t, t_s, self.period_s)
        return k

    def is_due(self, t_s: float) -> bool:
        """Whether ``due(t_s)`` would be > 0 (the clock left as it is)."""
        return is_due(self._next_t, t_s)

    def entering(self, rng: np.random.Generator, first_id: int, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """One agent: its position (1, 3) on the inlet face and its id ``first_id`` (``t_s`` unused: the
        same call as ``Reservoir.entering``)."""
        l = self.field.cell_size_m
        lo = self.field.centers_m[self.cvs[rng.integers(self.cvs.size)]] - 0.5 * l
        pos = lo + rng.random(3) * l
        pos[0] = lo[0]
        return pos.reshape(1, 3), np.array([first_id], dtype=np.int64)


def synthetic_tunnel_map(nx: int = 12, radius_cells: float = 2.0, cell_size_m: float = 0.5,
                         speed_m_s: float = 1.0, n_star: int = 3, spread_m_s: float = 0.2,
                         scale: float = 1.0):
    """A small analytic command map for tests and demos (no CFD, no fitting).

    A straight tunnel along x of ``nx`` slices; a CV wherever the cell centre lies within
    ``radius_cells`` cells of the axis (y = z = 0 on cell faces).  Target velocity
    (``speed_m_s``, 0, 0) with a mild linear acceleration (x 1 -> 1.5 along the tunnel), N* =
    ``n_star`` everywhere, fitted vectors = target +/- ``spread_m_s`` along y (mean = target),
    gauge pressure from Bernoulli, density constant with a tiny Bernoulli dip.
    """
    from fisc_agent.map.codec import decode_map
    from fisc_agent.map.codec import encode_map

    l = float(cell_size_m)
    r = int(np.ceil(radius_cells))
    shape = (nx, 2 * r, 2 * r)
    origin = np.array([0.0, -r * l, -r * l])
    idx = np.stack(np.meshgrid(*(np.arange(s) for s in shape), indexing="ij"), axis=-1).reshape(-1, 3)
    centres = origin + (idx + 0.5) * l
    keep = np.hypot(centres[:, 1], centres[:, 2]) <= radius_cells * l
    idx, centres = idx[keep], centres[keep]
    n = idx.shape[0]
    grid = np.full(shape, -1, dtype=np.int32)
    grid[idx[:, 0], idx[:, 1], idx[:, 2]] = np.arange(n)
    u = speed_m_s * (1.0 + 0.5 * centres[:, 0] / (nx * l))
    tv = np.zeros((n, 3))
    tv[:, 0] = u
    nmax = max(n_star, 2)
    fv = np.full((n, nmax, 3), np.nan)
    for k in range(n_star):
        fv[:, k] = tv
        fv[:, k, 1] += spread_m_s * (1 if k % 2 == 0 else -1) * (0 if (n_star % 2 and k == n_star - 1) else 1)
    p = 0.5 * 1.2 * (speed_m_s ** 2 - u ** 2)
    rho = 1.2 * (1.0 + p / 1e5)
    arrays = {
        "cv_center_m": centres, "cv_index": idx.astype(np.int32), "grid_cv": grid,
        "n_star": np.full(n, n_star, dtype=np.int32), "fit_velocity_m_s": fv,
        "fit_mean_velocity_m_s": np.nanmean(fv[:, :n_star], axis=1), "fit_pressure": p - p.min(),
        "fit_loss": np.zeros(n), "target_velocity_m_s": tv, "target_pressure_gauge_pa": p,
        "target_density_kg_m3": rho, "swarm_pressure_target": p - p.min(), "node_count": np.ones(n, dtype=np.int32),
    }
    meta = {"map_version": 1, "n_cv": int(n),
            "grid": {"origin_m": [float(v) for v in origin], "cell_size_m": l, "shape": list(shape)},
            "n_range": [2, nmax], "scale": float(scale), "kappa": 1.0, "agent_mass_kg": 1.0,
            "max_speed_m_s": 5.0, "provenance": {"reference": {"name": "synthetic_tunnel"}}}
    return decode_map(encode_map(meta, arrays), source="synthetic_tunnel_map")
