"""Optional collision layer (paper section "Collision Detection & Response"), vectorised.

Detection: two agents collide when they are closer than ``2 r``.  Candidate pairs come from a
spatial hash of cubic cells of edge ``2 r``: agents are sorted by cell key and each agent is
compared only with the agents of its own cell and of the 13 "forward" neighbour cells (the
other 13 are covered by symmetry), located with ``searchsorted`` on the sorted keys — no
per-agent Python and no O(N^2) comparison.  Only *approaching* pairs (relative velocity
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
Speed changes of several pairs of one agent add up; speeds are clipped to ``[0, v_max]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Forward half of the 26 neighbour offsets (lexicographically positive).
_FORWARD = np.array([(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)
                     if (dx, dy, dz) > (0, 0, 0)], dtype=np.int64)
_KEY_BITS = 20
_KEY_OFF = 1 << (_KEY_BITS - 1)

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
        return {"contacts": self.contacts, "one_way": self.one_way, "head_on": self.head_on,
                "perpendicular": self.perpendicular}


def close_pairs(pos_m: np.ndarray, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """All pairs (i < j as index arrays) of points closer than ``2 radius_m`` (spatial hash)."""
    pos = np.asarray(pos_m, dtype=float)
    n = pos.shape[0]
    if n < 2:
        e = np.empty(0, dtype=np.int64)
        return e, e
    h = 2.0 * radius_m
    cells = np.floor(pos / h).astype(np.int64) + _KEY_OFF
    m = np.int64(1 << _KEY_BITS)
    key = (cells[:, 0] * m + cells[:, 1]) * m + cells[:, 2]
    order = np.argsort(key, kind="stable")
    skey = key[order]
    rank = np.arange(n)
    pi, pj = [], []
    for off in [np.zeros(3, dtype=np.int64), *_FORWARD]:
        delta = (off[0] * m + off[1]) * m + off[2]
        lo = np.searchsorted(skey, skey + delta, "left")
        hi = np.searchsorted(skey, skey + delta, "right")
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
        e = np.empty(0, dtype=np.int64)
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
        hit = np.flatnonzero(delta)
        speed = np.linalg.norm(vel[hit], axis=1)
        new = np.clip(speed + delta[hit], 0.0, self.params.v_max_m_s)
        vel[hit] *= (new / np.maximum(speed, 1e-12))[:, None]
