"""The numba kernel of ``sim.close_pairs``: every pair of agents strictly closer than d_min, by a cell grid.

Imports numba: reach it only through ``sim.close_pairs.close_pairs_lister`` (None without numba).
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def close_pair_keys(pos, ids, by_id, d_min_m, max_cells):
    """``(keys, best d^2, best key, ok)``: the sorted keys ``min(id) << 32 | max(id)`` of the pairs strictly
    closer than ``d_min_m`` (> 0) among ``pos`` (n >= 1, 3, finite) with ``ids`` (n,) distinct (``by_id``:
    their order, ``np.argsort(ids)``; sorted outside, numba's sort costs seconds to compile), and the
    closest of them (smallest ``(dx^2 + dy^2) + dz^2``, numpy's ``np.sum(d ** 2, axis=1)`` order; ties: the
    smallest key); ``ok`` False (nothing listed) when the agents' box needs more than ``max_cells`` cells.

    The grid's cells are a hair larger than d_min (by 1e-9 of it), so two points closer than d_min are in
    the same or adjacent cells whatever the rounding of their cell coordinates.  Agents are visited in
    increasing id, each cell lists its agents in increasing id (so an agent's partners of larger id are the
    tail of each neighbouring cell's list), and its partners are sorted as they are found: the keys come out
    sorted, without a sort of all of them."""
    n = pos.shape[0]
    empty = np.zeros(0, dtype=np.uint64)
    lo = np.empty(3)
    dims = np.empty(3, dtype=np.int64)
    inv_cell = 1.0 / (d_min_m * (1.0 + 1e-9))
    total = 1
    for k in range(3):
        a = pos[0, k]
        b = pos[0, k]
        for i in range(1, n):
            a = min(a, pos[i, k])
            b = max(b, pos[i, k])
        lo[k] = a
        dims[k] = np.int64(math.floor((b - a) * inv_cell)) + 1
        total *= dims[k]
        if total > max_cells:
            return empty, math.inf, np.uint64(0), False
    nx, ny, nz = dims[0], dims[1], dims[2]
    cell = np.empty(n, dtype=np.int64)
    start = np.zeros(total + 1, dtype=np.int64)
    for i in range(n):
        c = 0
        for k in range(3):
            f = np.int64(math.floor((pos[i, k] - lo[k]) * inv_cell))
            f = min(max(f, 0), dims[k] - 1)
            c = c * dims[k] + f
        cell[i] = c
        start[c + 1] += 1
    for q in range(total):
        start[q + 1] += start[q]
    order = np.empty(n, dtype=np.int64)  # the agents cell by cell, each cell's in increasing id
    fill_at = np.empty(total, dtype=np.int64)
    for q in range(total):
        fill_at[q] = start[q]
    for t in range(n):
        i = by_id[t]
        order[fill_at[cell[i]]] = i
        fill_at[cell[i]] += 1
    d2_max = d_min_m * d_min_m
    keys = np.empty(max(16, 8 * n), dtype=np.uint64)
    count = 0
    best = math.inf
    best_key = np.uint64(0)
    partners = np.empty(n, dtype=np.int64)
    later = np.empty(total, dtype=np.int64)  # per cell: its first agent of an id larger than the agent visited
    for q in range(total):
        later[q] = start[q]
    for t in range(n):
        i = by_id[t]
        a = ids[i]
        c = cell[i]
        later[c] += 1  # the agent visited is its cell's next in id order
        cx = c // (ny * nz)
        cy = (c // nz) % ny
        cz = c % nz
        m = 0
        for ax in range(max(cx - 1, 0), min(cx + 2, nx)):
            for ay in range(max(cy - 1, 0), min(cy + 2, ny)):
                for az in range(max(cz - 1, 0), min(cz + 2, nz)):
                    q = (ax * ny + ay) * nz + az
                    for s in range(later[q], start[q + 1]):
                        j = order[s]
                        b = ids[j]
                        d0 = pos[i, 0] - pos[j, 0]
                        d1 = pos[i, 1] - pos[j, 1]
                        d2 = pos[i, 2] - pos[j, 2]
                        r2 = (d0 * d0 + d1 * d1) + d2 * d2
                        if not r2 < d2_max:
                            continue
                        key = (np.uint64(a) << np.uint64(32)) | np.uint64(b)
                        if r2 < best or (r2 == best and key < best_key):
                            best = r2
                            best_key = key
                        u = m  # insertion: the partners in increasing id
                        while u > 0 and partners[u - 1] > b:
                            partners[u] = partners[u - 1]
                            u -= 1
                        partners[u] = b
                        m += 1
        if count + m > keys.shape[0]:
            grown = np.empty(max(2 * keys.shape[0], count + m), dtype=np.uint64)
            for u in range(count):  # loops, not slices: their shape checks cost seconds of compile
                grown[u] = keys[u]
            keys = grown
        for u in range(m):
            keys[count] = (np.uint64(a) << np.uint64(32)) | np.uint64(partners[u])
            count += 1
    out = np.empty(count, dtype=np.uint64)
    for u in range(count):
        out[u] = keys[u]
    return out, best, best_key, True
