"""Case 1 seeding and Case 2 reservoir: counts, rates, reproducibility."""

import numpy as np
import pytest

from fisc_agent.map.lookup import CommandField
from sim.scenarios import (Reservoir, apportion, inlet_cvs, scale_for_agents, seed_counts, seed_positions,
                           source_rate, synthetic_tunnel_map)
from sim.swarm import Swarm


@pytest.fixture(scope="module")
def field():
    return CommandField.from_map(synthetic_tunnel_map(nx=8, n_star=4))


def test_seed_counts_per_cv_equal_n_star(field):
    pos = seed_positions(field, np.random.default_rng(0))
    counts = np.bincount(field.cv_of(pos), minlength=field.n_cv)
    np.testing.assert_array_equal(counts, field.n_star)


def test_seed_respects_x_axial(field):
    pos = seed_positions(field, np.random.default_rng(0), x_axial_m=1.0)
    cv = field.cv_of(pos)
    seeded = np.unique(cv)
    assert np.all(field.centers_m[seeded, 0] <= 1.0)
    assert len(pos) == int(field.n_star[field.centers_m[:, 0] <= 1.0].sum())


def test_seed_with_agents_total_is_exact_and_proportional(field):
    pos = seed_positions(field, np.random.default_rng(0), n_agents=500)
    assert len(pos) == 500
    counts = seed_counts(field, n_agents=500)
    assert counts.sum() == 500 and np.ptp(counts) <= 1  # uniform N* -> (nearly) equal shares


def test_apportion_largest_remainder():
    np.testing.assert_array_equal(apportion(np.array([1, 1, 2]), 5), [1, 1, 3])
    assert apportion(np.array([3.0, 7.0]), 0).sum() == 0


def test_seed_is_reproducible(field):
    a = seed_positions(field, np.random.default_rng(42))
    b = seed_positions(field, np.random.default_rng(42))
    np.testing.assert_array_equal(a, b)


def test_source_rate_equation():
    # N* |v| / l: 4 agents at 1.5 m/s through a 0.5 m cube -> 12 agents/s
    assert source_rate(np.array([4]), np.array([[1.5, 0.0, 0.0]]), 0.5)[0] == pytest.approx(12.0)


def test_reservoir_realised_inflow_matches_source_rate(field):
    res = Reservoir(field, interval_s=0.05)
    inlet = inlet_cvs(field)
    expected_rate = float((field.n_star[inlet] * np.linalg.norm(field.mean_cmd_m_s[inlet], axis=1) / 0.5).sum())
    assert res.rate_per_s == pytest.approx(expected_rate)
    rng = np.random.default_rng(0)
    total = sum(len(res.batch(rng)) for _ in range(400))  # 20 s
    assert abs(total - expected_rate * 20.0) <= len(inlet)


def test_reservoir_batches_enter_through_the_inlet_slice(field):
    res = Reservoir(field, interval_s=0.05)
    pos = np.concatenate([res.batch(np.random.default_rng(1)) for _ in range(20)])
    cv = field.cv_of(pos)
    assert np.all(np.isin(cv, inlet_cvs(field)))
    assert pos[:, 0].max() <= field.mean_cmd_m_s[:, 0].max() * 0.05 + 1e-12  # spread over one interval's flight


def test_reservoir_population_scale(field):
    full = Reservoir(field).rate_per_s
    s = scale_for_agents(field, int(field.n_star.sum()) // 2)
    assert Reservoir(field, population_scale=s).rate_per_s == pytest.approx(full / 2, rel=1e-2)


def test_reservoir_steady_population_close_to_n_star_density(field):
    """Agents injected at the source rate into a uniform-ish flow keep ~N* per CV at the inlet."""
    sw = Swarm(field)
    res = Reservoir(field)
    rng = np.random.default_rng(0)
    counts = np.zeros(field.n_cv)
    for k in range(200):
        for _ in range(res.due(sw.t_s)):
            sw.add_agents(res.batch(rng))
        if k >= 100:
            counts += np.bincount(sw.assign(), minlength=field.n_cv)
        sw.step()
    inlet = inlet_cvs(field)
    assert counts[inlet].mean() / 100 == pytest.approx(field.n_star[inlet].mean(), rel=0.1)


def test_kinetic_admission_mean_matches_the_average_over_directions():
    from sim.scenarios import kinetic_admission, kinetic_admission_mean

    d = np.linspace(-1.0, 1.0, 200001)  # d_x of a direction uniform on the sphere is uniform on [-1, 1]
    for u, sg in ((1.0, 0.2), (1.0, 1.0), (0.45, 0.6), (0.1, 2.0)):
        p = kinetic_admission(np.full(d.size, u), np.full(d.size, sg), d)
        assert 0.0 <= p.min() and p.max() <= 1.0
        assert kinetic_admission_mean(np.array([u]), np.array([sg]))[0] == pytest.approx(p.mean(), abs=1e-4)
    assert kinetic_admission_mean(np.array([1.0]), np.array([0.0]))[0] == 1.0  # no deviation: everyone enters
    with pytest.raises(ValueError, match="no axial entry speed"):
        kinetic_admission_mean(np.array([0.0]), np.array([0.0]))


def test_kinetic_reservoir_keeps_the_rate_and_admits_flux_weighted(field):
    """Admitted agents arrive at eq. source_rate on average, and their deviation classes are weighted
    by their axial speed u + sigma d_x: the flux of a gas that has the same density in every class."""
    from fisc_agent.map.kinetic import deviation_direction

    plain = Reservoir(field, interval_s=0.05)
    kin = Reservoir(field, interval_s=0.05, kinetic_persistence_s=2.0)
    assert kin.rate_per_s == pytest.approx(plain.rate_per_s)
    rng = np.random.default_rng(3)
    ids_all, t, next_id, n_cand = [], 0.0, 0, 0
    for k in range(4000):  # 200 s
        cand = kin.batch(rng)
        pos, ids = kin.admit(cand, next_id, t, rng)
        assert np.all(np.isin(ids, np.arange(next_id, next_id + len(cand))))
        ids_all.append(ids)
        next_id += len(cand)
        n_cand += len(cand)
        t += 0.05
    ids = np.concatenate(ids_all)
    expected = plain.rate_per_s * 200.0
    assert abs(len(ids) - expected) < 4.0 * np.sqrt(expected)
    assert n_cand > 1.1 * len(ids)  # some candidates were turned away
    # deviation at entry (recomputed for the entry times)
    inlet = inlet_cvs(field)
    u, sg = field.mean_cmd_m_s[inlet[0], 0], field.spread_m_s[inlet[0]]
    a = u / sg
    assert a >= 1.0
    # flux-weighted mean of d_x for d_x uniform on [-1, 1]: E[d (a + d)] / E[a + d] = 1 / (3 a)
    t_entry = np.concatenate([np.full(len(x), 0.05 * k) for k, x in enumerate(ids_all)])
    d_x = np.concatenate([deviation_direction(ids[t_entry == tt], tt, 2.0)[0][:, 0] for tt in np.unique(t_entry)])
    assert d_x.mean() == pytest.approx(1.0 / (3.0 * a), abs=4.0 / np.sqrt(len(d_x)))
    # the plain reservoir admits everything
    cand = plain.batch(rng)
    pos, ids2 = plain.admit(cand, 7, 0.0, rng)
    np.testing.assert_array_equal(pos, cand)
    np.testing.assert_array_equal(ids2, np.arange(7, 7 + len(cand)))


def test_swarm_takes_explicit_increasing_ids(field):
    sw = Swarm(field)
    p = field.centers_m[:3]
    np.testing.assert_array_equal(sw.add_agents(p, ids=np.array([2, 5, 9])), [2, 5, 9])
    assert sw.next_id == 10
    np.testing.assert_array_equal(sw.add_agents(p[:1]), [10])
    with pytest.raises(ValueError, match="strictly increasing"):
        sw.add_agents(p[:2], ids=np.array([12, 12]))
    with pytest.raises(ValueError, match="strictly increasing"):
        sw.add_agents(p[:1], ids=np.array([3]))
