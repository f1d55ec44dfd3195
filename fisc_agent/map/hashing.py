"""The slot hash h(agent id, CV id): the one integer mix every agent and the simulator share.

``slot`` mode flies fitted vector ``h(i, j) mod N*_j`` (DESIGN.md section 3); the ``kinetic`` mode
draws its deviation directions and interval phases from the same hash.  Pure functions of integers
(Python ints on the onboard scalar path, uint64 numpy arrays vectorised); the simulator's numba twin
(``sim.kernels``) is tested equal to ``slot_mix``.
"""

from __future__ import annotations

import numpy as np

_MASK32 = 0xFFFFFFFF


def slot_mix(a, j):
    """The slot hash's 32-bit integer mix of an agent id ``a`` and a CV id ``j``, both already
    reduced to 32 bits: Python ints (the onboard scalar path) or uint64 numpy arrays (no product
    exceeds 2**64, so both give the same bits).  The one definition of the hash; the simulator's
    numba twin (``sim.kernels``) is tested equal to it."""
    h = ((a * 0x9E3779B1) ^ (j * 0x85EBCA77 + 0x27D4EB2F)) & _MASK32
    h ^= h >> 15
    h = (h * 0x2C1B3C6D) & _MASK32
    h ^= h >> 12
    return h


def slot_hash(agent_id: np.ndarray | int, cv_id: np.ndarray | int) -> np.ndarray:
    """h(agent_id, j) as uint64 (vectorised): identical on every agent and the simulator.

    Agent i in CV j flies fitted vector ``h(i, j) mod N*_j`` (DESIGN.md section 3, ``slot``).
    """
    m = np.uint64(_MASK32)
    return slot_mix(np.asarray(agent_id, dtype=np.uint64) & m, np.asarray(cv_id, dtype=np.uint64) & m)


def slot_hash_int(agent_id: int, cv_id: int) -> int:
    """h(agent_id, j) with Python ints (no numpy call: the single-vehicle hot path)."""
    return slot_mix(int(agent_id) & _MASK32, int(cv_id) & _MASK32)


def slot_index(agent_id: np.ndarray | int, cv_id: np.ndarray | int, n_star: np.ndarray | int) -> np.ndarray:
    """k = h(agent_id, j) mod N*_j as int64: the fitted vector agent ``agent_id`` flies in CV ``cv_id``."""
    return (slot_hash(agent_id, cv_id) % np.asarray(n_star, dtype=np.uint64)).astype(np.int64)
