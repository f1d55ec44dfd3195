"""Collision layer: spatial-hash detection and the classification/response on hand cases."""

import numpy as np
import pytest

from sim.collisions import (HEAD_ON, ONE_WAY, PERPENDICULAR, CollisionModel, CollisionParams, classify,
                            close_pairs)


def test_close_pairs_equals_brute_force():
    rng = np.random.default_rng(1)
    p = rng.random((1500, 3)) * 2.0
    i, j = close_pairs(p, 0.1)
    d = np.linalg.norm(p[:, None] - p[None], axis=2)
    bi, bj = np.nonzero(np.triu(d < 0.2, 1))
    assert set(zip(i.tolist(), j.tolist())) == set(zip(bi.tolist(), bj.tolist()))
    assert np.all(i < j)


def test_close_pairs_across_cell_boundaries_and_negative_coordinates():
    p = np.array([[-0.01, 0.0, 0.0], [0.01, 0.0, 0.0], [5.0, 5.0, 5.0]])
    i, j = close_pairs(p, 0.1)
    assert list(zip(i, j)) == [(0, 1)]


P = CollisionParams()


@pytest.mark.parametrize("vi, vj, kind", [
    ([2.0, 0, 0], [1.0, 0, 0], ONE_WAY),         # overtaking, same direction
    ([1.0, 0.2, 0], [1.0, -0.2, 0], ONE_WAY),    # nearly parallel
    ([1.0, 0, 0], [-1.0, 0, 0], HEAD_ON),        # head-on
    ([1.0, 0, 0], [-1.0, 0.3, 0], HEAD_ON),
    ([1.0, 0, 0], [0, 1.0, 0], PERPENDICULAR),   # crossing at right angles
    ([1.0, 0, 0], [0, 0, 0], PERPENDICULAR),     # into a hovering agent
])
def test_classification_hand_cases(vi, vj, kind):
    assert classify(np.array([vi], float), np.array([vj], float), P)[0] == kind


def _collide(pi, pj, vi, vj, params=P):
    pos = np.array([pi, pj], float)
    vel = np.array([vi, vj], float)
    m = CollisionModel(params)
    m.apply(pos, vel)
    return vel, m.stats


def test_one_way_faster_slows_slower_speeds_up_directions_kept():
    vel, st = _collide([0, 0, 0], [0.1, 0, 0], [2.0, 0, 0], [1.0, 0, 0])  # i behind j, faster
    assert st.one_way == 1
    assert vel[0, 0] == pytest.approx(2.0 - 0.25) and vel[1, 0] == pytest.approx(1.0 + 0.25)
    assert np.allclose(vel[:, 1:], 0)


def test_mutual_loses_symmetrically_more_when_perpendicular():
    vel, st = _collide([0, 0, 0], [0.1, 0, 0], [1.0, 0, 0], [-1.0, 0, 0])
    assert st.head_on == 1
    np.testing.assert_allclose(vel, [[0.9, 0, 0], [-0.9, 0, 0]])
    vel, st = _collide([0, 0, 0], [0.1, -0.1, 0], [1.0, 0, 0], [0, 1.0, 0])
    assert st.perpendicular == 1
    np.testing.assert_allclose(np.linalg.norm(vel, axis=1), [0.8, 0.8])
    np.testing.assert_allclose(vel[0] / np.linalg.norm(vel[0]), [1, 0, 0])


def test_receding_or_distant_pairs_are_left_alone():
    vel, st = _collide([0, 0, 0], [0.1, 0, 0], [-1.0, 0, 0], [1.0, 0, 0])  # moving apart
    np.testing.assert_allclose(vel, [[-1, 0, 0], [1, 0, 0]])
    assert st.contacts == 1 and st.head_on == 0
    vel, st = _collide([0, 0, 0], [0.5, 0, 0], [1.0, 0, 0], [-1.0, 0, 0])  # farther than 2r
    assert st.contacts == 0


def test_speeds_are_clipped_to_v_max():
    params = CollisionParams(v_max_m_s=1.1, exchange=1.0)
    vel, _ = _collide([0, 0, 0], [0.1, 0, 0], [0.5, 0, 0], [3.0, 0, 0])  # j ahead is faster -> not approaching
    vel, _ = _collide([0.1, 0, 0], [0, 0, 0], [0.5, 0, 0], [3.0, 0, 0], params)  # j behind, faster
    assert np.all(np.linalg.norm(vel, axis=1) <= 1.1 + 1e-12)


def test_agent_in_several_pairs_gets_the_mean_change_not_the_sum():
    # agent 0 meets two head-on agents at once: it loses 10 %, not 20 %
    pos = np.array([[0.0, 0, 0], [0.1, 0.05, 0], [0.1, -0.05, 0]])
    vel = np.array([[1.0, 0, 0], [-1.0, 0, 0], [-1.0, 0, 0]])
    m = CollisionModel(P)
    m.apply(pos, vel)
    assert m.stats.head_on == 2
    assert np.linalg.norm(vel[0]) == pytest.approx(0.9)


def test_close_pairs_sparse_fallback_equals_dense():
    rng = np.random.default_rng(4)
    p = np.concatenate([rng.random((300, 3)), [[4.0, 4.0, 4.0], [4.05, 4.0, 4.0]]])
    dense = close_pairs(p, 0.1, max_cells_per_agent=10**4)
    sparse = close_pairs(p, 0.1, max_cells_per_agent=0)
    assert set(zip(*map(list, dense))) == set(zip(*map(list, sparse)))
    assert (300, 301) in set(zip(*map(list, dense)))


def test_close_pairs_numba_and_numpy_paths_agree():
    rng = np.random.default_rng(9)
    p = rng.random((2000, 3)) * 2.0
    a = close_pairs(p, 0.1, backend="auto")
    b = close_pairs(p, 0.1, backend="numpy")
    assert len(a[0]) == len(b[0]) > 0
    assert set(zip(*map(list, a))) == set(zip(*map(list, b)))


def test_close_pairs_dense_cluster_beyond_the_first_buffer():
    p = np.random.default_rng(2).random((200, 3)) * 0.05  # every pair is close: 19900 > 4 n + 1024
    i, j = close_pairs(p, 0.1)
    assert len(i) == 200 * 199 // 2
