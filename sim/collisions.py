"""Optional collision layer (paper section "Collision Detection & Response"), vectorised.

Detection: two agents collide when they are closer than ``2 r``.  Candidate pairs come from a
spatial hash of cubic cells of edge ``2 r``: agents are sorted by cell key and each agent is
compared only with the agents of its own cell and of the 13 "forward" neighbour cells (the
other 13 are covered by symmetry), located through a counting sort of dense cell numbers —
no per-agent Python and no O(N^2) comparison.  Only *approaching* pairs (relative velocity
along the separation < 0) get a response, so one encounter is not answered every step.

Classification by the velocity directions e_i, e_j (cosine c = e_i . e_j):
* one-way (c >= ``overtake_cos``): both fly the same way and one overtakes the other;
* mutual head-on (c <= -``head_on_cos``);
* mutual perpendicular (otherwise).

Response: a speed-only momentum exchange; directions are kept.
* one-way: the faster loses and the slower gains ``exchange (s_f - s_s) / 2`` (equal masses:
  ``exchange = 1`` is the perfectly inelastic exchange, both leave at the mean speed);
* mutual: both lose the same fraction of speed, ``head_on_loss`` or the larger
  ``perpendicular_loss``.
An agent in several pairs at once gets the *mean* of its pairs' speed changes (a multi-body
contact resolved once per step; summing would let a dense cluster drive every speed to 0 in
one step and lock it into a permanent jam).  Speeds are clipped to ``[0, v_max]``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

#: Forward half of the 26 neighbour offsets (lexicographically positive).
_FORWARD = np.array([(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)
                     if (dx, dy, dz) > (0, 0, 0)], dtype=np.int64)

ONE_WAY, HEAD_ON, PERPENDICULAR = 0, 1, 2
CLASS_NAMES = ("one_way", "head_on", "perpendicular")


@dataclass(frozen=True)
class CollisionParams:
    """Parameters of the collision layer (the paper gives no numbers; documented defaults)."""

    radius_m: float = 0.1
    """Agent radius r [m]; a collision is two agents closer than 2 r."""
    v_max_m_s: float = 7.5
    """Upper bound of the speeds after a response [m/s]."""
    overtake_cos: float = 0.5
    """Directions with cosine >= this are a one-way (overtaking) encounter (within 60 deg)."""
    head_on_cos: float = 0.5
    """Directions with cosine <= -this are mutual head-on; between, mutual perpendicular."""
    exchange: float = 0.5
    """One-way: fraction of the speed difference exchanged (1: both leave at the mean speed)."""
    head_on_loss: float = 0.1
    """Mutual head-on: fraction of speed each agent loses."""
    perpendicular_loss: float = 0.2
    """Mutual perpendicular: fraction of speed each agent loses (larger than head-on, as in the paper)."""

    def __post_init__(self) -> None:
        if not self.radius_m > 0:
            raise ValueError(f"CollisionParams.radius_m must be > 0, got {self.radius_m!r}")
        if not self.v_max_m_s > 0:
            raise ValueError(f"CollisionParams.v_max_m_s must be > 0, got {self.v_max_m_s!r}")
        for name in ("exchange", "head_on_loss", "perpendicular_loss"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"CollisionParams.{name} must be in [0, 1], got {getattr(self, name)!r}")


@dataclass
class CollisionStats:
    """Running counts of the collision layer."""

    contacts: int = 0
    """Pairs found closer than 2 r (approaching or not), summed over steps."""
    one_way: int = 0
    """Approaching pairs answered as one-way (overtaking)."""
    head_on: int = 0
    """Approaching pairs answered as mutual head-on."""
    perpendicular: int = 0
    """Approaching pairs answered as mutual perpendicular."""

    def as_dict(self) -> dict:
        """Collision counts by type."""
        return {"contacts": self.contacts, "one_way": self.one_way, "head_on": self.head_on,
                "perpendicular": self.perpendicular}


@functools.lru_cache(maxsize=1)
def _numba_pairs():
    """numba kernel: close pairs from the dense cell table (same pairs as the numpy path); None without numba."""
    try:
        import numba
    except ImportError:
        return None

    @numba.njit(cache=True, nogil=True)
    def scan(pos, order, skey, starts, counts, deltas, h2, out_i, out_j):
        n = order.shape[0]
        m = 0
        for r in range(n):
            a = order[r]
            for q in range(deltas.shape[0]):
                c = skey[r] + deltas[q]
                lo = starts[c]
                hi = lo + counts[c]
                if deltas[q] == 0 and lo < r + 1:
                    lo = r + 1
                for t in range(lo, hi):
                    b = order[t]
                    d0 = pos[b, 0] - pos[a, 0]
                    d1 = pos[b, 1] - pos[a, 1]
                    d2 = pos[b, 2] - pos[a, 2]
                    if d0 * d0 + d1 * d1 + d2 * d2 < h2:
                        if m < out_i.shape[0]:
                            out_i[m] = min(a, b)
                            out_j[m] = max(a, b)
                        m += 1
        return m

    return scan


def close_pairs(pos_m: np.ndarray, radius_m: float, max_cells_per_agent: int = 64,
                backend: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """All pairs (i < j as index arrays) of points closer than ``2 radius_m`` (spatial hash).

    Cells of edge 2r over the points' bounding box (plus a one-cell border) are numbered
    densely; a counting sort gives each cell's start and count, so the own cell and the 13
    forward neighbour cells of every agent are found with plain gathers (no search).  When the
    box would need more than ``max_cells_per_agent`` cells per agent (widely scattered points)
    the cell keys are looked up with ``searchsorted`` on the sorted keys instead.
    ``backend``: "auto" uses a numba scan of the dense table when numba is importable,
    "numpy" the vectorised expansion (same pairs, possibly in another order).
    """
    pos = np.asarray(pos_m, dtype=float)
    n = pos.shape[0]
    e = np.empty(0, dtype=np.int64)
    if n < 2:
        return e, e
    h = 2.0 * radius_m
    cells = np.floor((pos - pos.min(axis=0)) / h).astype(np.int64) + 1
    dims = cells.max(axis=0) + 2
    n_cells = int(np.prod(dims))
    key = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    order = np.argsort(key, kind="stable")
    skey = key[order]
    dense = n_cells <= max_cells_per_agent * n + 4096
    if dense:
        counts = np.bincount(key, minlength=n_cells)
        starts = np.cumsum(counts) - counts
        scan = _numba_pairs() if backend == "auto" else None
        if scan is not None:
            deltas = np.array([(o[0] * dims[1] + o[1]) * dims[2] + o[2]
                               for o in [np.zeros(3, dtype=np.int64), *_FORWARD]], dtype=np.int64)
            pos_c = np.ascontiguousarray(pos)
            cap = 4 * n + 1024
            i, j = np.empty(cap, dtype=np.int64), np.empty(cap, dtype=np.int64)
            m = scan(pos_c, order, skey, starts, counts, deltas, h * h, i, j)
            if m > cap:  # denser than expected: rerun with room for every pair
                i, j = np.empty(m, dtype=np.int64), np.empty(m, dtype=np.int64)
                scan(pos_c, order, skey, starts, counts, deltas, h * h, i, j)
            return i[:m], j[:m]
    rank = np.arange(n)
    pi, pj = [], []
    for off in [np.zeros(3, dtype=np.int64), *_FORWARD]:
        delta = (off[0] * dims[1] + off[1]) * dims[2] + off[2]
        nb = skey + delta
        if dense:
            lo = starts[nb]
            hi = lo + counts[nb]
        else:
            lo = np.searchsorted(skey, nb, "left")
            hi = np.searchsorted(skey, nb, "right")
        if delta == 0:
            lo = np.maximum(lo, rank + 1)  # same cell: each pair once
        cnt = np.maximum(hi - lo, 0)
        total = int(cnt.sum())
        if not total:
            continue
        a = np.repeat(rank, cnt)
        start = np.repeat(lo - np.cumsum(cnt) + cnt, cnt)
        b = start + np.arange(total)
        pi.append(order[a])
        pj.append(order[b])
    if not pi:
        return e, e
    i, j = np.concatenate(pi), np.concatenate(pj)
    d = pos[j] - pos[i]
    close = np.einsum("ij,ij->i", d, d) < h * h
    i, j = i[close], j[close]
    swap = i > j
    i[swap], j[swap] = j[swap], i[swap]
    return i, j


def classify(vel_i: np.ndarray, vel_j: np.ndarray, params: CollisionParams) -> np.ndarray:
    """(m,) class of each pair: ONE_WAY, HEAD_ON or PERPENDICULAR (by velocity alignment)."""
    si = np.linalg.norm(vel_i, axis=1)
    sj = np.linalg.norm(vel_j, axis=1)
    c = np.einsum("ij,ij->i", vel_i, vel_j) / np.maximum(si * sj, 1e-12)
    c = np.where((si > 1e-9) & (sj > 1e-9), c, 0.0)  # a hovering agent: a perpendicular encounter
    out = np.full(c.shape, PERPENDICULAR, dtype=np.int64)
    out[c >= params.overtake_cos] = ONE_WAY
    out[c <= -params.head_on_cos] = HEAD_ON
    return out


def speed_response(speed_i: np.ndarray, speed_j: np.ndarray, kind: np.ndarray,
                   params: CollisionParams) -> tuple[np.ndarray, np.ndarray]:
    """Speed changes (d_i, d_j) of each pair for its class (before clipping)."""
    diff = speed_j - speed_i
    d_i = np.where(kind == ONE_WAY, 0.5 * params.exchange * diff, 0.0)
    d_j = -d_i
    loss = np.where(kind == HEAD_ON, params.head_on_loss, params.perpendicular_loss)
    mutual = kind != ONE_WAY
    d_i = np.where(mutual, -loss * speed_i, d_i)
    d_j = np.where(mutual, -loss * speed_j, d_j)
    return d_i, d_j


@dataclass
class CollisionModel:
    """The collision layer as the swarm core calls it: ``apply(pos, vel)`` each step."""

    params: CollisionParams = field(default_factory=CollisionParams)
    cell_size_m: float = 0.5
    """CV edge of the map (informational; the hash uses cells of 2 r)."""
    stats: CollisionStats = field(default_factory=CollisionStats)

    def apply(self, pos_m: np.ndarray, vel: np.ndarray) -> None:
        """Detect collisions among ``pos_m`` (n, 3) and adjust the speeds of ``vel`` (n, 3) in place."""
        i, j = close_pairs(pos_m, self.params.radius_m)
        self.stats.contacts += int(i.size)
        if not i.size:
            return
        d = pos_m[j] - pos_m[i]
        approaching = np.einsum("ij,ij->i", vel[j] - vel[i], d) < 0.0
        i, j = i[approaching], j[approaching]
        if not i.size:
            return
        vi, vj = vel[i], vel[j]
        kind = classify(vi, vj, self.params)
        counts = np.bincount(kind, minlength=3)
        self.stats.one_way += int(counts[ONE_WAY])
        self.stats.head_on += int(counts[HEAD_ON])
        self.stats.perpendicular += int(counts[PERPENDICULAR])
        si, sj = np.linalg.norm(vi, axis=1), np.linalg.norm(vj, axis=1)
        d_i, d_j = speed_response(si, sj, kind, self.params)
        n = vel.shape[0]
        delta = np.bincount(i, weights=d_i, minlength=n) + np.bincount(j, weights=d_j, minlength=n)
        pairs = np.bincount(i, minlength=n) + np.bincount(j, minlength=n)
        hit = np.flatnonzero(pairs)
        delta = delta[hit] / pairs[hit]
        speed = np.linalg.norm(vel[hit], axis=1)
        new = np.clip(speed + delta, 0.0, self.params.v_max_m_s)
        vel[hit] *= (new / np.maximum(speed, 1e-12))[:, None]
