"""Closest approach between vehicles and near-misses below d_min (pure: positions in, numbers out).

Issue 37, item 6.  One time step: ``closest_pair`` (the smallest pairwise 3-D distance among the
vehicles present, O(N log N) with ``scipy.spatial.cKDTree``) and ``pairs_closer_than`` (every pair
closer than d_min, as encoded pair keys).  Over a run: ``ApproachTracker`` keeps the closest approach
(distance, time and the two ids) and counts **near-misses**: a pair of vehicles that comes closer than
d_min counts once per *encounter*, i.e. when it is closer than d_min at a step and was not at the
previous step it was evaluated at (a pair that stays close over many steps is one near-miss; one
that separates and closes again is two).

Positions that are not finite (no fix, a dropped sample) are ignored, so are the vehicles they
belong to at that step.  Vehicle ids must be distinct at one step, integers in 0 .. 2^32 - 1 (telemetry's u32).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from typing import Any

import numpy as np

_ID_LIMIT = 1 << 32


def _kdtree(pos: np.ndarray) -> Any:
    """``scipy.spatial.cKDTree`` of ``pos``, imported here: the monitor imports this module, and
    ``fisc-ground``'s parser must load without scipy to name the missing extra."""
    from scipy.spatial import cKDTree

    return cKDTree(pos)


@dataclass(frozen=True)
class ClosestPair:
    """The closest two vehicles at one time step (``distance_m`` inf and ids -1 with fewer than two)."""

    distance_m: float
    """Their centre-to-centre distance [m]."""
    id_a: int
    """The smaller of the two vehicle ids (-1: none)."""
    id_b: int
    """The larger of the two vehicle ids (-1: none)."""


@dataclass(frozen=True)
class ClosestApproach:
    """The closest approach over a run and its near-misses."""

    distance_m: float
    """Smallest distance between two vehicles over all evaluated steps [m] (inf: never two present)."""
    time_s: float
    """When it happened [s] (NaN: never)."""
    id_a: int
    """The smaller vehicle id of that pair (-1: none)."""
    id_b: int
    """The larger vehicle id of that pair (-1: none)."""
    near_misses: int
    """Encounters closer than ``d_min_m`` (each pair counted once per encounter)."""
    d_min_m: float
    """The spacing the near-misses are counted against [m]."""
    steps: int
    """Time steps evaluated."""

    def as_dict(self) -> dict:
        """JSON-ready dict (inf / NaN as None; the contract keys ``closest_approach_m``, ``near_misses``,
        ``d_min_m``)."""
        d = self.distance_m if math.isfinite(self.distance_m) else None
        t = self.time_s if math.isfinite(self.time_s) else None
        return {"closest_approach_m": d, "closest_approach_time_s": t,
                "closest_approach_ids": [self.id_a, self.id_b] if d is not None else None,
                "near_misses": int(self.near_misses), "d_min_m": float(self.d_min_m),
                "separation_steps": int(self.steps)}

    def sentence(self) -> str:
        """One line for reports: ``closest approach 0.41 m (agents 3 and 5 at t = 12.3 s); 2 near-misses < d_min 0.92 m``."""
        if not math.isfinite(self.distance_m):
            return f"closest approach: never two vehicles present ({self.steps} steps); d_min {self.d_min_m:.2f} m"
        return (f"closest approach {self.distance_m:.2f} m (agents {self.id_a} and {self.id_b} at t = {self.time_s:.1f} s); "
                f"{self.near_misses} near-misses < d_min {self.d_min_m:.2f} m over {self.steps} steps")


def _finite(ids: np.ndarray, pos_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pos = np.asarray(pos_m, dtype=float)
    ids = np.asarray(ids, dtype=np.int64)
    if pos.ndim != 2 or pos.shape[1] != 3 or ids.shape != (pos.shape[0],):
        raise ValueError(f"positions must be (n, 3) with one id each, got {pos.shape} and ids {ids.shape}")
    ok = np.isfinite(pos).all(axis=1)
    ids, pos = ids[ok], pos[ok]
    if ids.size and (ids.min() < 0 or ids.max() >= _ID_LIMIT):
        raise ValueError(f"vehicle ids must lie in 0 .. {_ID_LIMIT - 1}")
    return ids, pos


def _nearest(ids: np.ndarray, pos: np.ndarray, tree: Any) -> ClosestPair:
    dist, nn = tree.query(pos, k=2)
    i = int(np.argmin(dist[:, 1]))
    a, b = int(ids[i]), int(ids[nn[i, 1]])
    return ClosestPair(float(dist[i, 1]), min(a, b), max(a, b))


def closest_pair(ids: np.ndarray, pos_m: np.ndarray) -> ClosestPair:
    """The closest two vehicles among ``pos_m`` (n, 3) with ``ids`` (n,); non-finite rows ignored."""
    ids, pos = _finite(ids, pos_m)
    if ids.size < 2:
        return ClosestPair(math.inf, -1, -1)
    return _nearest(ids, pos, _kdtree(pos))


def pair_keys(id_a: np.ndarray, id_b: np.ndarray, distinct: bool = False) -> np.ndarray:
    """Sorted unique uint64 keys ``min << 32 | max`` of vehicle-id pairs (order within a pair ignored);
    ``distinct``: the pairs are known to be distinct (a sort instead of ``np.unique``)."""
    a, b = np.asarray(id_a, dtype=np.int64), np.asarray(id_b, dtype=np.int64)
    keys = (np.minimum(a, b).astype(np.uint64) << np.uint64(32)) | np.maximum(a, b).astype(np.uint64)
    if distinct:
        keys.sort()
        return keys
    return np.unique(keys)


def _close_pairs(ids: np.ndarray, pos: np.ndarray, tree: Any, d_min_m: float) -> tuple[np.ndarray, ClosestPair]:
    """Keys of the pairs strictly closer than ``d_min_m`` and the closest of them (distance inf without)."""
    none = ClosestPair(math.inf, -1, -1)
    if ids.size < 2 or d_min_m == 0:
        return np.zeros(0, dtype=np.uint64), none
    pairs = tree.query_pairs(d_min_m, output_type="ndarray")
    if not pairs.size:
        return np.zeros(0, dtype=np.uint64), none
    d2 = np.sum((pos[pairs[:, 0]] - pos[pairs[:, 1]]) ** 2, axis=1)
    keep = d2 < d_min_m * d_min_m  # strictly closer (query_pairs includes the distance itself)
    pairs, d2 = pairs[keep], d2[keep]
    if not pairs.size:
        return np.zeros(0, dtype=np.uint64), none
    i = int(np.argmin(d2))
    a, b = int(ids[pairs[i, 0]]), int(ids[pairs[i, 1]])
    return pair_keys(ids[pairs[:, 0]], ids[pairs[:, 1]], distinct=True), \
        ClosestPair(float(np.sqrt(d2[i])), min(a, b), max(a, b))


def _close_keys(ids: np.ndarray, pos: np.ndarray, tree: Any, d_min_m: float) -> np.ndarray:
    return _close_pairs(ids, pos, tree, d_min_m)[0]


def pairs_closer_than(ids: np.ndarray, pos_m: np.ndarray, d_min_m: float) -> np.ndarray:
    """Keys (``pair_keys``) of every pair strictly closer than ``d_min_m``; non-finite rows ignored."""
    if not d_min_m >= 0:
        raise ValueError(f"d_min must be >= 0 m, is {d_min_m!r}")
    ids, pos = _finite(ids, pos_m)
    if ids.size < 2:
        return np.zeros(0, dtype=np.uint64)
    return _close_keys(ids, pos, _kdtree(pos), d_min_m)


def brute_force_closest(ids: np.ndarray, pos_m: np.ndarray) -> ClosestPair:
    """O(N^2) oracle of ``closest_pair`` (tests and tiny fleets)."""
    ids, pos = _finite(ids, pos_m)
    if ids.size < 2:
        return ClosestPair(math.inf, -1, -1)
    d = np.linalg.norm(pos[:, None, :] - pos[None, :, :], axis=2)
    d[np.diag_indices(ids.size)] = np.inf
    i, j = np.unravel_index(int(np.argmin(d)), d.shape)
    a, b = int(ids[i]), int(ids[j])
    return ClosestPair(float(d[i, j]), min(a, b), max(a, b))


def _count_in(keys: np.ndarray, sorted_keys: np.ndarray) -> int:
    """How many of ``keys`` are in ``sorted_keys`` (sorted, unique): ``np.isin(...).sum()`` by binary search."""
    if not (keys.size and sorted_keys.size):
        return 0
    i = np.searchsorted(sorted_keys, keys)
    i[i == sorted_keys.size] = 0
    return int(np.count_nonzero(sorted_keys[i] == keys))


class ApproachTracker:
    """Closest approach and near-miss encounters over a sequence of time steps (``add`` one step at a time,
    in time order).  State: the best pair so far and the set of pairs closer than d_min at the last step."""

    def __init__(self, d_min_m: float, close_pairs: Callable | None = None) -> None:
        """``close_pairs``: an optional faster lister of the pairs closer than d_min, ``(ids, pos, d_min_m) ->
        (keys, closest) | None`` with the finite rows; it must give what ``_close_pairs`` gives (the sorted
        keys of the pairs strictly closer, the closest of them; ``sim.close_pairs.list_close_pairs``);
        None from it, or no lister: the KD-tree."""
        if not (math.isfinite(d_min_m) and d_min_m >= 0):
            raise ValueError(f"d_min must be a finite number >= 0 m, is {d_min_m!r}")
        self.d_min_m = float(d_min_m)
        self._lister = close_pairs
        self._best = ClosestPair(math.inf, -1, -1)
        self._best_t = math.nan
        self._close = np.zeros(0, dtype=np.uint64)
        self.near_misses = 0
        self.steps = 0

    def add(self, t_s: float, ids: np.ndarray, pos_m: np.ndarray) -> ClosestPair:
        """Evaluate one time step; returns that step's closest pair."""
        ids, pos = _finite(ids, pos_m)
        self.steps += 1
        if ids.size < 2:
            self._close = np.zeros(0, dtype=np.uint64)
            return ClosestPair(math.inf, -1, -1)
        listed = None if self._lister is None else self._lister(ids, pos, self.d_min_m)
        tree = None
        if listed is None:
            tree = _kdtree(pos)
            listed = _close_pairs(ids, pos, tree, self.d_min_m)
        close, step = listed  # the closest pair, when closer than d_min
        if not close.size:
            step = _nearest(ids, pos, _kdtree(pos) if tree is None else tree)
        if step.distance_m < self._best.distance_m:
            self._best, self._best_t = step, float(t_s)
        self.near_misses += int(close.size - _count_in(close, self._close))
        self._close = close
        return step

    def result(self) -> ClosestApproach:
        """The closest approach so far."""
        b = self._best
        return ClosestApproach(b.distance_m, self._best_t, b.id_a, b.id_b, self.near_misses, self.d_min_m, self.steps)


def track_approach(t_s: np.ndarray, ids: np.ndarray, pos_m: np.ndarray, d_min_m: float) -> ClosestApproach:
    """Closest approach of a fleet sampled on a common time base: ``t_s`` (K,), ``ids`` (N,) and
    ``pos_m`` (K, N, 3) with NaN where a vehicle is absent."""
    pos = np.asarray(pos_m, dtype=float)
    t = np.asarray(t_s, dtype=float)
    if pos.ndim != 3 or pos.shape[0] != t.shape[0] or pos.shape[2] != 3:
        raise ValueError(f"positions must be (K, N, 3) for K = {t.shape[0]} times, got {pos.shape}")
    tracker = ApproachTracker(d_min_m)
    for k in range(t.shape[0]):
        tracker.add(float(t[k]), ids, pos[k])
    return tracker.result()


def common_time_base(tracks: list[tuple[np.ndarray, np.ndarray]], period_s: float,
                     max_gap_s: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Positions of several vehicles on one time base: ``tracks`` is a list of ``(time_s (n_i,),
    pos_m (n_i, 3))`` on a shared clock; returns ``(t (K,), pos (K, N, 3))`` on a grid of ``period_s``
    over the union of their spans, linearly interpolated; NaN outside a vehicle's own span and inside
    gaps between its samples longer than ``max_gap_s`` (no fix there: not interpolated)."""
    if not (period_s > 0 and max_gap_s > 0):
        raise ValueError(f"period and max gap must be > 0 s, are {period_s!r} and {max_gap_s!r}")
    spans = [(float(np.nanmin(t)), float(np.nanmax(t))) for t, _ in tracks if np.isfinite(t).any()]
    if not spans:
        return np.zeros(0), np.zeros((0, len(tracks), 3))
    lo, hi = min(s[0] for s in spans), max(s[1] for s in spans)
    grid = lo + period_s * np.arange(int(math.floor((hi - lo) / period_s + 1e-9)) + 1)
    out = np.full((grid.size, len(tracks), 3), np.nan)
    for j, (t, p) in enumerate(tracks):
        t, p = np.asarray(t, dtype=float), np.asarray(p, dtype=float)
        ok = np.isfinite(t) & np.isfinite(p).all(axis=1)
        t, p = t[ok], p[ok]
        if t.size == 0:
            continue
        order = np.argsort(t, kind="stable")
        t, p = t[order], p[order]
        k = np.searchsorted(t, grid, side="right")
        inside = (grid >= t[0]) & (grid <= t[-1])
        # the samples around each grid time must not be further apart than the gap limit
        k_hi = np.clip(k, 0, t.size - 1)
        k_lo = np.clip(k - 1, 0, t.size - 1)
        gap_ok = (t[k_hi] - t[k_lo]) <= max_gap_s + 1e-9
        use = inside & (gap_ok | (t[k_lo] == grid))
        for c in range(3):
            out[use, j, c] = np.interp(grid[use], t, p[:, c])
    return grid, out
