"""Where each agent is: O(1) control-volume assignment on a padded copy of the map's grid
(eq. cv_assignment), the return policy's nearest-CV table, and the fused numba kernel that
assigns and gathers the command in one pass (``sim.swarm`` steps with them)."""

from __future__ import annotations


import numpy as np

from fisc_agent.map.lookup import CommandField
from sim.kernels import jit_kernels


def fused_lookup_kernel():
    """Fused numba kernel: padded-grid CV lookup + command gather (mean or slot); None without numba.

    Same arithmetic as the numpy path (``CVLookup.__call__`` then the table gathers, and
    ``fisc_agent.map.hashing.slot_hash`` for the slot index); tested equal to it.
    """
    jk = jit_kernels()
    return None if jk is None else jk.fused_lookup


class CVLookup:
    """O(1) CV assignment on a padded grid (eq. cv_assignment for points inside occupied cells).

    Identical to ``CommandField.cv_of`` (floor of (x - origin) / l, half-open cells, -1 outside
    the map's CVs) but on a copy of ``grid_cv`` with a border of ``margin`` (>= 1) cells, so that
    one clip replaces the bounds test, with reusable scratch buffers (no big temporaries per
    step).  The same padded grid holds, for every cell without a CV, the CV the return policy
    steers towards (``nearest``): the nearest (centre to cell centre) within ``margin`` cells that
    is not stagnant, else the nearest stagnant one, -1 if none; the O(1) table of the return
    policy, computed once with ``CommandField.return_cv_within``.
    """

    def __init__(self, field: CommandField, margin: int = 2) -> None:
        g = np.asarray(field.grid_cv)
        m = max(int(margin), 1)
        nx, ny, nz = g.shape
        shape = (nx + 2 * m, ny + 2 * m, nz + 2 * m)
        pad = np.full(shape, -1, dtype=np.int64)
        pad[m:-m, m:-m, m:-m] = g
        self._flat = pad.ravel()
        l = float(field.cell_size_m)
        idx = np.stack(np.unravel_index(np.arange(pad.size), shape), axis=1)
        near = pad.ravel().copy()
        empty = np.flatnonzero(near < 0)
        if empty.size and margin > 0:
            centres = np.asarray(field.origin_m) + (idx[empty] - m + 0.5) * l
            near[empty] = field.return_cv_within(centres, int(margin))
        near[empty[near[empty] < 0]] = -1
        # the outermost ring stands for "everything further out": never steered back
        border = np.any((idx == 0) | (idx == np.asarray(shape) - 1), axis=1)
        near[border & (pad.ravel() < 0)] = -1
        self._near = near
        self._origin = np.asarray(field.origin_m, dtype=float) - m * l
        self._inv_l = 1.0 / l
        self._hi = np.asarray(shape, dtype=np.float64) - 1.0
        self._strides = np.array([shape[1] * shape[2], shape[2], 1], dtype=np.int64)
        self._buf = np.empty((0, 3))
        self._ibuf = np.empty((0, 3), dtype=np.int64)
        self._last = np.empty(0, dtype=np.int64)

    def __call__(self, points_m: np.ndarray) -> np.ndarray:
        """(n,) int64 CV id of each (n, 3) point, -1 where the cell has no CV."""
        n = points_m.shape[0]
        if self._buf.shape[0] < n:
            self._buf = np.empty((max(n, 2 * self._buf.shape[0]), 3))
            self._ibuf = np.empty_like(self._buf, dtype=np.int64)
        f, i = self._buf[:n], self._ibuf[:n]
        np.subtract(points_m, self._origin, out=f)
        f *= self._inv_l
        np.floor(f, out=f)
        np.clip(f, 0.0, self._hi, out=f)
        i[...] = f
        self._last = i @ self._strides
        return self._flat[self._last]

    def nearest_of_last(self, index: np.ndarray) -> np.ndarray:
        """Return-table CV of the points ``index`` of the last call (their own CV if they have
        one, else the nearest within the margin, else -1)."""
        return self._near[self._last[index]]

    def nearest(self, points_m: np.ndarray) -> np.ndarray:
        """Return-table CV of each (m, 3) point (see ``nearest_of_last``)."""
        f = np.floor((np.asarray(points_m, dtype=float) - self._origin) * self._inv_l)
        i = np.clip(f, 0.0, self._hi).astype(np.int64)
        return self._near[i @ self._strides]
