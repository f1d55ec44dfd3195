"""The numba cell-grid lister of the pairs closer than d_min (``sim.close_pairs``) gives what the KD-tree
reference of ``fisc_ground.fields.separation_stats`` gives: the same pair keys, the same closest distance,
and through ``ApproachTracker`` the same closest approach and near-miss counts."""

import math

import numpy as np
import pytest

import fisc_ground.fields.separation_stats as ss
from sim.close_pairs import MAX_CELLS_BASE, MAX_CELLS_PER_AGENT, close_pairs_lister, list_close_pairs

import numba  # noqa: F401  (a dependency of sim: missing means broken, not skipped)


def _reference(ids, pos, d_min):
    """The KD-tree listing (``separation_stats._close_pairs``): keys and closest pair."""
    if ids.size < 2:
        return np.zeros(0, dtype=np.uint64), ss.ClosestPair(math.inf, -1, -1)
    return ss._close_pairs(ids, pos, ss._kdtree(pos), d_min)


def _same(ids, pos, d_min):
    listed = list_close_pairs(ids, pos, d_min)
    if listed is None:  # declined: only for a box of more cells than the grid's limit
        cells = np.prod(np.floor(np.ptp(pos, axis=0) / (d_min * (1 + 1e-9))) + 1)
        assert cells > MAX_CELLS_PER_AGENT * ids.size + MAX_CELLS_BASE
        return None
    keys, best = listed
    ref_keys, ref_best = _reference(ids, pos, d_min)
    np.testing.assert_array_equal(keys, ref_keys)
    assert keys.dtype == np.uint64
    assert best.distance_m == ref_best.distance_m  # bit for bit (inf when none)
    if ref_keys.size:  # the pair: one of the pairs at that distance (the reference's on no tie)
        d = {(int(k >> np.uint64(32)), int(k & np.uint64(0xFFFFFFFF))) for k in keys}
        assert (best.id_a, best.id_b) in d
    return keys, best


def test_lister_is_there_with_numba():
    assert close_pairs_lister() is list_close_pairs


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("n", [0, 1, 2, 3, 50, 400])
def test_random_clouds_equal_the_kdtree(seed, n):
    rng = np.random.default_rng(seed)
    box = rng.uniform(0.5, 8.0, 3)
    pos = rng.random((n, 3)) * box - rng.uniform(-5, 5, 3)
    ids = rng.permutation(10 * n + 5)[:n].astype(np.int64)
    for d_min in (0.05, 0.3, 0.92, 2.5):
        _same(ids, pos, d_min)


def test_pairs_at_exactly_d_min_are_not_close():
    # on a lattice of spacing d: neighbours at exactly d (not counted), diagonals further
    d = 0.5
    g = np.arange(5) * d
    pos = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    ids = np.arange(pos.shape[0], dtype=np.int64)
    keys, best = _same(ids, pos, d)
    assert keys.size == 0 and best.distance_m == math.inf
    keys, _ = _same(ids, pos, math.nextafter(d, math.inf))  # a hair more: every lattice neighbour
    assert keys.size == 3 * 4 * 25


def test_all_agents_in_one_cell_and_duplicates():
    rng = np.random.default_rng(7)
    pos = 3.0 + 0.01 * rng.random((60, 3))
    pos[5] = pos[6]  # two at the same point: distance 0
    ids = np.arange(100, 160, dtype=np.int64)
    keys, best = _same(ids, pos, 0.92)
    assert keys.size == 60 * 59 // 2 and best.distance_m == 0.0 and (best.id_a, best.id_b) == (105, 106)


def test_d_min_zero_and_large_ids():
    rng = np.random.default_rng(3)
    pos = rng.random((30, 3))
    ids = (np.arange(30, dtype=np.int64) * 97 + (1 << 32) - 30 * 97 - 1)
    keys, _ = list_close_pairs(ids, pos, 0.0)
    assert keys.size == 0
    _same(ids, pos, 0.4)


def test_a_box_too_large_for_the_grid_is_declined():
    pos = np.array([[0.0, 0.0, 0.0], [1e6, 1e6, 1e6], [0.1, 0.0, 0.0]])
    assert list_close_pairs(np.arange(3, dtype=np.int64), pos, 0.5) is None
    tr = ss.ApproachTracker(0.5, list_close_pairs)  # the tracker then lists them with the KD-tree
    step = tr.add(0.0, np.arange(3), pos)
    assert (step.id_a, step.id_b) == (0, 2) and tr.near_misses == 1


def test_tracker_with_the_lister_equals_the_kdtree_tracker():
    rng = np.random.default_rng(11)
    n = 300
    pos = rng.random((n, 3)) * [12.0, 3.0, 3.0]
    vel = rng.normal(0, 0.3, (n, 3))
    a, b = ss.ApproachTracker(0.92), ss.ApproachTracker(0.92, list_close_pairs)
    for k in range(12):
        live = rng.random(n) < 0.9  # vehicles come and go; a NaN row is ignored
        p = pos.copy()
        p[3] = np.nan
        ids = np.flatnonzero(live)
        a.add(0.5 * k, ids, p[live])
        b.add(0.5 * k, ids, p[live])
        pos += vel * 0.5
    assert a.result() == b.result()
    c, e = ss.ApproachTracker(0.01), ss.ApproachTracker(0.01, list_close_pairs)  # no pair that close
    for tr in (c, e):
        tr.add(0.0, np.arange(n), pos)
    assert c.result() == e.result() and c.near_misses == 0
