"""The pairs of agents closer than d_min at one evaluation of the closest approach, by a numba cell grid.

``fisc_ground.fields.separation_stats.ApproachTracker`` lists them with a KD-tree
(``separation_stats._close_pairs``, the reference); ``simulate`` hands its tracker ``close_pairs_lister()``,
which lists the same pairs (strictly closer than d_min, distances as the reference computes them) and the
same closest pair in a fraction of the time: at 10^3 agents in the tunnel, ~10^4 pairs are closer than d_min
and the KD-tree's pair listing cost most of an evaluation.  tests/sim/test_close_pairs.py compares both.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from fisc_ground.fields.separation_stats import ClosestPair

#: Largest grid (cells) the lister builds: ``MAX_CELLS_PER_AGENT`` per agent plus ``MAX_CELLS_BASE`` (beyond it,
#: agents spread thinly over a large box, it declines and the KD-tree lists them).
MAX_CELLS_PER_AGENT = 64
MAX_CELLS_BASE = 1 << 16


def close_pairs_lister() -> Callable | None:
    """``list_close_pairs`` when numba is installed, else None (the tracker's KD-tree)."""
    try:
        from sim import close_pairs_jit  # noqa: F401
    except ModuleNotFoundError as exc:
        if exc.name != "numba":
            raise
        return None
    return list_close_pairs


def list_close_pairs(ids: np.ndarray, pos: np.ndarray, d_min_m: float) -> tuple[np.ndarray, ClosestPair] | None:
    """Sorted keys (``separation_stats.pair_keys``) of the pairs of ``pos`` (n, 3, finite; ``ids`` (n,)
    distinct, 0 .. 2^32 - 1) strictly closer than ``d_min_m``, and the closest of them (distance inf and
    ids -1 without any; of equally close pairs, the one of the smallest key); None when the agents' box
    is too large for the grid (``MAX_CELLS_PER_AGENT``, ``MAX_CELLS_BASE``): the caller lists them otherwise."""
    none = ClosestPair(math.inf, -1, -1)
    n = ids.shape[0]
    if n < 2 or d_min_m == 0:
        return np.zeros(0, dtype=np.uint64), none
    from sim.close_pairs_jit import close_pair_keys

    ids = np.ascontiguousarray(ids, dtype=np.int64)
    keys, best, key, ok = close_pair_keys(np.ascontiguousarray(pos, dtype=np.float64), ids, np.argsort(ids),
                                          float(d_min_m), MAX_CELLS_PER_AGENT * n + MAX_CELLS_BASE)
    if not ok:
        return None
    if not keys.size:
        return keys, none
    return keys, ClosestPair(float(math.sqrt(best)), int(key >> np.uint64(32)), int(key & np.uint64(0xFFFFFFFF)))
