"""Closest approach and near-misses (fisc_ground.fields.separation_stats) against a brute-force oracle."""

import math

import numpy as np
import pytest

from fisc_ground.fields import separation_stats as ss


@pytest.mark.parametrize("n", [2, 3, 17, 300])
def test_closest_pair_equals_brute_force(n):
    rng = np.random.default_rng(n)
    for trial in range(5):
        pos = rng.uniform(-5, 5, size=(n, 3))
        ids = rng.permutation(10 * n)[:n]
        got, want = ss.closest_pair(ids, pos), ss.brute_force_closest(ids, pos)
        assert got.distance_m == pytest.approx(want.distance_m, rel=1e-12)
        assert {got.id_a, got.id_b} == {want.id_a, want.id_b}
        assert got.id_a < got.id_b


def test_pairs_closer_than_equals_brute_force():
    rng = np.random.default_rng(1)
    pos = rng.uniform(0, 4, size=(200, 3))
    ids = np.arange(200) + 1000
    d = np.linalg.norm(pos[:, None] - pos[None], axis=2)
    i, j = np.nonzero(np.triu(d < 0.5, k=1))
    assert np.array_equal(ss.pairs_closer_than(ids, pos, 0.5), ss.pair_keys(ids[i], ids[j]))


def test_d_min_boundary_is_strict():
    pos = np.array([[0.0, 0, 0], [0.92, 0, 0]])
    ids = np.array([3, 5])
    assert ss.pairs_closer_than(ids, pos, 0.92).size == 0  # equal: not a near-miss
    assert ss.pairs_closer_than(ids, pos, 0.92 + 1e-9).size == 1  # just above d_min's distance
    assert ss.pairs_closer_than(ids, pos, 0.92 - 1e-9).size == 0
    for d_min, misses in ((0.92, 0), (0.92 + 1e-9, 1), (0.92 - 1e-9, 0)):
        tr = ss.ApproachTracker(d_min)
        tr.add(0.0, ids, pos)
        assert tr.result().near_misses == misses
        assert tr.result().distance_m == pytest.approx(0.92)


def test_no_pair_one_agent_zero_agents_and_nan():
    one = ss.closest_pair(np.array([7]), np.zeros((1, 3)))
    assert one.distance_m == math.inf and one.id_a == -1
    zero = ss.closest_pair(np.zeros(0, dtype=int), np.zeros((0, 3)))
    assert zero.distance_m == math.inf
    pos = np.array([[0.0, 0, 0], [np.nan, 0, 0], [0.1, 0, 0], [5.0, 0, 0]])
    got = ss.closest_pair(np.array([1, 2, 3, 4]), pos)
    assert (got.id_a, got.id_b) == (1, 3) and got.distance_m == pytest.approx(0.1)
    nan_only = ss.closest_pair(np.array([1, 2]), np.array([[np.nan] * 3, [0.0, 0, 0]]))
    assert nan_only.distance_m == math.inf
    r = ss.ApproachTracker(0.92).result()
    assert r.as_dict()["closest_approach_m"] is None and r.near_misses == 0


def test_near_miss_counted_once_per_encounter():
    ids = np.array([3, 5, 9])
    far = np.array([[0.0, 0, 0], [2.0, 0, 0], [10.0, 0, 0]])
    near = np.array([[0.0, 0, 0], [0.41, 0, 0], [10.0, 0, 0]])
    tr = ss.ApproachTracker(0.92)
    for k, p in enumerate([far, near, near, near, far, near, far]):  # two encounters of (3, 5)
        tr.add(float(k), ids, p)
    r = tr.result()
    assert r.near_misses == 2
    assert (r.distance_m, r.time_s, r.id_a, r.id_b) == (pytest.approx(0.41), 1.0, 3, 5)
    assert "agents 3 and 5" in r.sentence()
    # a second pair closing while the first stays close is a new encounter
    tr = ss.ApproachTracker(0.92)
    tr.add(0.0, ids, near)
    both = near.copy()
    both[2] = [0.0, 0.5, 0]
    tr.add(1.0, ids, both)
    assert tr.result().near_misses == 1 + 2  # (3,5), then (3,9) and (5,9)


def test_the_largest_telemetry_ids_pair_up():
    big = np.array([2**32 - 2, 2**32 - 3, 5])
    pos = np.array([[0.0, 0, 0], [0.5, 0, 0], [9.0, 0, 0]])
    tr = ss.ApproachTracker(0.92)
    tr.add(0.0, big, pos)
    r = tr.result()
    assert (r.id_a, r.id_b, r.near_misses) == (2**32 - 3, 2**32 - 2, 1)
    assert ss.pairs_closer_than(big, pos, 0.92).size == 1


def test_bad_input_named():
    with pytest.raises(ValueError, match="d_min"):
        ss.ApproachTracker(-1.0)
    with pytest.raises(ValueError, match="ids"):
        ss.closest_pair(np.array([-1, 2]), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        ss.closest_pair(np.array([1, 2]), np.zeros((2, 2)))


def test_common_time_base_interpolates_and_leaves_gaps():
    a = (np.array([0.0, 1.0, 2.0]), np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]]))
    b = (np.array([0.5, 1.5, 5.0]), np.array([[0.0, 1, 0], [0.0, 2, 0], [0.0, 5, 0]]))
    t, pos = ss.common_time_base([a, b], 0.5, max_gap_s=1.0)
    assert t[0] == 0.0 and t[-1] == 5.0
    assert np.allclose(pos[t == 1.0, 0], [[1.0, 0, 0]])
    assert np.allclose(pos[t == 1.0, 1], [[0.0, 1.5, 0]])
    assert np.isnan(pos[t == 0.0, 1]).all()  # before b's first fix
    assert np.isnan(pos[t == 3.0, 1]).all()  # inside b's 3.5 s gap
    assert np.isnan(pos[t == 3.0, 0]).all()  # after a's last fix
    assert np.allclose(pos[t == 5.0, 1], [[0.0, 5, 0]])
    r = ss.track_approach(t, np.array([1, 2]), pos, 0.92)
    want = min(np.linalg.norm(pos[k, 0] - pos[k, 1]) for k in range(t.size)
               if np.isfinite(pos[k]).all())
    assert r.distance_m == pytest.approx(want)


@pytest.mark.parametrize("d_min", [0.0, 0.05, 0.92, 5.0])
def test_tracker_step_equals_brute_force_whether_or_not_pairs_are_close(d_min):
    rng = np.random.default_rng(7)
    tr = ss.ApproachTracker(d_min)
    best = np.inf
    for k in range(6):
        pos = rng.uniform(0, 3, size=(40, 3))
        ids = np.arange(40) * 3
        got, want = tr.add(float(k), ids, pos), ss.brute_force_closest(ids, pos)
        assert got.distance_m == pytest.approx(want.distance_m, rel=1e-12)
        assert (got.id_a, got.id_b) == (want.id_a, want.id_b)
        best = min(best, want.distance_m)
    assert tr.result().distance_m == pytest.approx(best)


@pytest.mark.parametrize("case", ["disjoint", "half", "same", "empty_keys", "empty_set", "beyond_last"])
def test_count_in_equals_isin(case):
    """The near-miss count's membership test (binary search) counts what ``np.isin`` counts."""
    from fisc_ground.fields.separation_stats import _count_in

    rng = np.random.default_rng(4)
    a = np.unique(rng.integers(0, 2**40, 500).astype(np.uint64))
    b = {"disjoint": a + np.uint64(2**41), "half": np.unique(np.concatenate([a[::2], a[:50] + np.uint64(1)])),
         "same": a, "empty_keys": a, "empty_set": a[:0], "beyond_last": a[:10]}[case]
    keys = a[:0] if case == "empty_keys" else a
    assert _count_in(keys, b) == int(np.isin(keys, b, assume_unique=True).sum())
