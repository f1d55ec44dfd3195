"""Specification of the paper's velocity fitting (section "Velocity-Fitting"), vectorised."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fisc_ground.fit.fitting import (
    NOISE_BLOCK_CVS,
    FitResult,
    arrow_solve,
    fit_cv_reference,
    fit_rmse,
    fit_velocities,
    initial_dispersion,
    initial_guess,
    objective,
    pressure_coefficient,
    select_n_star,
    swarm_pressure,
)

DV = 0.125  # 0.5 m cubes


def _random_targets(n, seed=0, reversed_fraction=0.3):
    rng = np.random.default_rng(seed)
    vt = rng.normal(size=(n, 3)) * np.array([6.0, 1.0, 1.0]) + np.array([4.0, 0.0, 0.0])
    flip = rng.random(n) < reversed_fraction
    vt[flip, 0] = -np.abs(vt[flip, 0])  # reversed-flow CVs (separation bubble)
    pt = rng.uniform(0.0, 80.0, size=n)
    return vt, pt


def test_swarm_pressure_is_equation_pressure_constraint():
    v = np.array([[1.0, 0.0, 0.0], [3.0, 0.0, 0.0], [np.nan, np.nan, np.nan]])  # 2 agents + 1 empty slot
    m, dv = 2.0, 0.5
    c = 2 * m / (3 * dv)
    # about the mean (2, 0, 0): sum ||d||^2 = 2
    assert swarm_pressure(v, m, dv) == pytest.approx(c * 2.0)
    # about a given target velocity (0, 0, 0): sum ||v||^2 = 10
    assert swarm_pressure(v, m, dv, np.zeros(3)) == pytest.approx(c * 10.0)
    assert pressure_coefficient(m, dv) == pytest.approx(c)
    # batched over CVs
    both = swarm_pressure(np.stack([v, v]), m, np.array([dv, 2 * dv]))
    np.testing.assert_allclose(both, [c * 2.0, c * 1.0])


def test_objective_is_equation_iterative_objective():
    v = np.array([[1.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    m, dv, alpha = 1.0, DV, 0.5
    vt = np.array([2.0, 1.0, 0.0])  # mean misses by (0, 1, 0)
    p = swarm_pressure(v, m, dv)
    assert objective(v, vt, p + 4.0, m, dv, alpha) == pytest.approx(1.0 + alpha * 4.0)
    assert objective(v, vt, p - 4.0, m, dv, alpha) == pytest.approx(1.0 + alpha * 4.0)  # |.|


def test_arrow_solve_equals_dense_linalg_solve():
    rng = np.random.default_rng(1)
    m = 200
    inv_n = 1.0 / rng.integers(2, 11, size=m)
    b = rng.normal(size=(3, m)) * 0.1
    q = rng.uniform(1.0, 5.0, size=m)
    r_v = rng.normal(size=(3, m))
    r_p = rng.normal(size=m)
    a = np.zeros((m, 4, 4))
    a[:, [0, 1, 2], [0, 1, 2]] = inv_n[:, None]
    a[:, :3, 3] = b.T
    a[:, 3, :3] = b.T
    a[:, 3, 3] = q
    y = np.linalg.solve(a, np.concatenate([r_v.T, r_p[:, None]], axis=1)[..., None])[..., 0]
    y_v, y_p = arrow_solve(inv_n, b, q, r_v, r_p)
    np.testing.assert_allclose(y_v.T, y[:, :3], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(y_p, y[:, 3], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("mass, alpha", [(1.0, 1.0), (0.3, 10.0), (2.5, 0.01)])
def test_every_fitted_cv_meets_its_mean_and_pressure_targets(mass, alpha):
    vt, pt = _random_targets(1500, seed=2)
    vol = np.full(1500, DV)
    vol[::3] = 1.0  # per-CV volumes are allowed
    res = fit_velocities(vt, pt, vol, agent_mass_kg=mass, alpha=alpha)
    assert isinstance(res, FitResult)
    assert res.converged.all()
    assert np.all((res.n_star >= 2) & (res.n_star <= 10))
    np.testing.assert_allclose(res.mean_velocity_m_s, vt, atol=1e-6, rtol=0)
    np.testing.assert_allclose(res.pressure, pt, atol=1e-6, rtol=0)
    assert np.all(res.loss < 1e-6)
    # shapes, NaN beyond N*, and the documented per-CV quantities are consistent
    assert res.velocities_m_s.shape == (1500, 10, 3)
    k = np.arange(10)[None, :]
    filled = np.all(np.isfinite(res.velocities_m_s), axis=2)
    np.testing.assert_array_equal(filled, k < res.n_star[:, None])
    np.testing.assert_allclose(res.pressure, swarm_pressure(res.velocities_m_s, mass, vol, vt))
    np.testing.assert_allclose(res.loss, objective(res.velocities_m_s, vt, pt, mass, vol, alpha), atol=1e-12)
    assert res.candidate_loss.shape == (1500, 9)
    assert np.all(res.iterations >= 1) and np.all(res.iterations <= 50)
    assert res.seconds > 0
    v_rmse, p_rmse = fit_rmse(res, vt, pt)
    assert v_rmse < 1e-6 and p_rmse < 1e-6


def test_newton_converges_quadratically_to_the_scaled_start():
    """The min-norm Newton step fixes the mean and rescales the deviations, so the iteration ends at
    v_target + d0 sqrt(P_target / P(v0)) with d0 the start's deviations; it takes few iterations."""
    vt, pt = _random_targets(300, seed=4)
    res = fit_velocities(vt, pt, DV, n_min=4, n_max=4, seed=11)
    (v0,) = initial_guess(vt, pt, np.full(300, DV), 1.0, np.array([4]), 4, seed=11)
    v0 = v0.transpose(2, 0, 1)  # (n, N, 3)
    d0 = v0 - v0.mean(axis=1, keepdims=True)
    p0 = swarm_pressure(v0, 1.0, DV)
    expected = vt[:, None, :] + d0 * np.sqrt(pt / p0)[:, None, None]
    np.testing.assert_allclose(res.velocities_m_s[:, :4], expected, atol=1e-9)
    assert res.iterations.max() <= 12


def test_initial_guess_follows_the_paper():
    vt, pt = _random_targets(5000, seed=5)
    cand = np.arange(2, 11)
    starts = initial_guess(vt, pt, np.full(5000, DV), 1.0, cand, 10, seed=0)
    for n_agents, v0 in zip(cand, starts):
        assert v0.shape == (n_agents, 3, 5000)
        xi = (v0 - vt.T) / initial_dispersion(pt, DV, 1.0, n_agents)
        assert abs(xi.mean()) < 0.02 and abs(xi.std() - 1.0) < 0.02  # xi ~ N(0, I)
    sigma2 = initial_dispersion(pt, DV, 1.0, 5) ** 2
    np.testing.assert_allclose(sigma2, pt * 3 * DV / (2 * 1.0 * 5))


def test_zero_pressure_target_gives_n_identical_vectors():
    vt = np.array([[3.0, 0.1, -0.2], [-2.0, 0.0, 0.5], [0.0, 0.0, 0.0]])
    res = fit_velocities(vt, np.zeros(3), DV)
    assert res.converged.all()
    for j in range(3):
        vj = res.velocities_m_s[j, : res.n_star[j]]
        np.testing.assert_allclose(vj, np.broadcast_to(vt[j], vj.shape), atol=1e-12)
    np.testing.assert_allclose(res.pressure, 0.0, atol=1e-20)


def test_reversed_flow_targets_fit_like_any_other():
    vt = np.array([[-3.0, 0.2, 0.0], [-0.5, -0.5, 0.1]])
    pt = np.array([10.0, 0.0])
    res = fit_velocities(vt, pt, DV)
    np.testing.assert_allclose(res.mean_velocity_m_s, vt, atol=1e-9)
    np.testing.assert_allclose(res.pressure, pt, atol=1e-9)


def test_vectorised_fit_agrees_with_the_single_cv_reference():
    vt, pt = _random_targets(6, seed=7)
    res = fit_velocities(vt, pt, DV, n_min=2, n_max=6)
    for j in range(6):
        v_ref, n_ref, loss_ref, cand_ref = fit_cv_reference(vt[j], pt[j], DV, n_min=2, n_max=6, seed=j)
        assert n_ref == res.n_star[j]
        assert loss_ref < 1e-6 and res.loss[j] < 1e-6
        assert np.all(cand_ref < 1e-6) and np.all(res.candidate_loss[j] < 1e-6)
        np.testing.assert_allclose(v_ref.mean(axis=0), vt[j], atol=1e-6)
        assert swarm_pressure(v_ref, 1.0, DV, vt[j]) == pytest.approx(pt[j], abs=1e-6)


def test_n_star_is_least_loss_with_ties_going_to_the_largest_n():
    cand = np.arange(2, 7)
    losses = np.array(
        [
            [5.0, 4.0, 0.1, 3.0, 2.0],  # clear minimum
            [0.0, 1e-9, 0.0, 2e-7, 0.5],  # ties within tol -> largest tied N
            [1e-12, 1e-12, 1e-12, 1e-12, 1e-12],  # all tied -> n_max
        ]
    )
    np.testing.assert_array_equal(cand[select_n_star(losses, cand, 1e-6)], [4, 5, 6])


def test_a_candidate_that_cannot_realise_the_pressure_loses():
    """With N = 1 there is no dispersion, so a positive pressure target leaves loss alpha * P."""
    vt = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    pt = np.array([3.0, 0.0])
    res = fit_velocities(vt, pt, DV, n_min=1, n_max=1, alpha=2.0)
    np.testing.assert_allclose(res.loss, [6.0, 0.0], atol=1e-12)
    res2 = fit_velocities(vt, pt, DV, n_min=1, n_max=3, alpha=2.0)
    np.testing.assert_allclose(res2.candidate_loss[0, 0], 6.0)
    assert res2.n_star[0] > 1 and res2.loss[0] < 1e-6
    assert res2.n_star[1] == 3  # all tied at 0 -> largest N


def test_results_are_reproducible_and_independent_of_chunking():
    n = 2 * NOISE_BLOCK_CVS + 300
    vt, pt = _random_targets(n, seed=8)
    a = fit_velocities(vt, pt, DV, seed=3)
    b = fit_velocities(vt, pt, DV, seed=3, chunk_cvs=NOISE_BLOCK_CVS)
    for f in ("n_star", "iterations", "converged"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
    # equal up to round-off (reductions over differently sized batches may sum in another order)
    np.testing.assert_allclose(a.velocities_m_s, b.velocities_m_s, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.candidate_loss, b.candidate_loss, rtol=0, atol=1e-9)
    c = fit_velocities(vt, pt, DV, seed=4)
    assert not np.allclose(np.nan_to_num(a.velocities_m_s), np.nan_to_num(c.velocities_m_s))
    np.testing.assert_allclose(c.pressure, pt, atol=1e-6)


def test_max_iter_cap_reports_non_convergence():
    vt, pt = _random_targets(50, seed=9)
    res = fit_velocities(vt, pt + 1.0, DV, max_iter=1)
    assert not res.converged.any()
    assert np.all(res.iterations == 1)
    v_rmse, p_rmse = fit_rmse(res, vt, pt + 1.0)
    assert np.isnan(v_rmse) and np.isnan(p_rmse)  # no valid CV


def test_fit_rmse_uses_only_valid_cvs():
    vt = np.zeros((3, 3))
    pt = np.array([1.0, 2.0, 3.0])
    res = FitResult(
        velocities_m_s=np.zeros((3, 2, 3)),
        n_star=np.array([2, 2, 2], dtype=np.int32),
        loss=np.zeros(3),
        mean_velocity_m_s=np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0], [100.0, 0.0, 0.0]]),
        pressure=np.array([1.0, 4.0, 50.0]),
        iterations=np.ones(3, dtype=np.int32),
        converged=np.array([True, True, False]),
        seconds=0.0,
        candidate_loss=np.zeros((3, 1)),
    )
    v_rmse, p_rmse = fit_rmse(res, vt, pt)
    assert v_rmse == pytest.approx(np.sqrt((25.0 + 0.0) / 2))
    assert p_rmse == pytest.approx(np.sqrt((0.0 + 4.0) / 2))
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.seconds = 1.0  # type: ignore[misc]


def test_bad_inputs_are_refused_naming_the_cv():
    vt, pt = _random_targets(5, seed=10)
    bad_v = vt.copy()
    bad_v[3, 1] = np.nan
    with pytest.raises(ValueError, match="CV 3: target velocity is not finite"):
        fit_velocities(bad_v, pt, DV)
    bad_p = pt.copy()
    bad_p[2] = np.inf
    with pytest.raises(ValueError, match="CV 2: pressure target is not finite"):
        fit_velocities(vt, bad_p, DV)
    neg = pt.copy()
    neg[4] = -1.0
    with pytest.raises(ValueError, match="CV 4: pressure target -1.0 is negative"):
        fit_velocities(vt, neg, DV)
    vol = np.full(5, DV)
    vol[1] = 0.0
    with pytest.raises(ValueError, match="CV 1: cell volume"):
        fit_velocities(vt, pt, vol)
    with pytest.raises(ValueError, match="n_min"):
        fit_velocities(vt, pt, DV, n_min=5, n_max=4)
    with pytest.raises(ValueError, match="pressure_target must have shape"):
        fit_velocities(vt, pt[:4], DV)
    with pytest.raises(ValueError, match="agent_mass_kg"):
        fit_velocities(vt, pt, DV, agent_mass_kg=0.0)


def test_empty_input_gives_an_empty_result():
    res = fit_velocities(np.zeros((0, 3)), np.zeros(0), DV)
    assert res.n_cv == 0 and res.velocities_m_s.shape == (0, 10, 3)
