"""The separation budget (fisc_ground.fit.separation_budget): Poisson nearest neighbour, the largest
swarm at d_min, the flux and inlet admission periods, each against its closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fisc_agent.flight.spacing import ENTRY_OPEN_FRACTION, ENTRY_TIMING_TOLERANCE_S
from fisc_ground.fit.separation_budget import (GAMMA_4_3, AdmissionLimit, near_fraction, poisson_density_for_nn,
                                               poisson_nn_mean_m, relative_density, separation_budget)


def box(nx: int, ny: int, nz: int) -> np.ndarray:
    """cv_index of a full nx x ny x nz block of CVs."""
    return np.array([(i, j, k) for i in range(nx) for j in range(ny) for k in range(nz)])


def test_poisson_mean_nearest_neighbour_is_the_closed_form_and_its_inverse():
    assert poisson_nn_mean_m(1.0) == pytest.approx(GAMMA_4_3 * (4 * math.pi / 3) ** (-1 / 3))
    assert GAMMA_4_3 == pytest.approx(0.892979511569249)
    for d in (0.1, 0.92, 3.0):
        assert poisson_nn_mean_m(poisson_density_for_nn(d)) == pytest.approx(d, rel=1e-12)
    assert poisson_nn_mean_m(8.0) == pytest.approx(poisson_nn_mean_m(1.0) / 2)  # n^(-1/3)
    assert poisson_nn_mean_m(0.0) == math.inf
    for bad in (-1e-9, math.nan, math.inf):
        with pytest.raises(ValueError, match="number density"):
            poisson_nn_mean_m(bad)
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="nearest-neighbour distance"):
            poisson_density_for_nn(bad)


def test_poisson_mean_is_the_sampled_mean():
    """A sampled Poisson gas (uniform points, periodic box so there is no edge) has the closed-form mean."""
    rng = np.random.default_rng(1)
    n, side = 4000, 10.0
    p = rng.uniform(0, side, (n, 3))
    best = np.full(n, np.inf)
    for i in range(n):
        d = np.abs(p - p[i])
        d = np.minimum(d, side - d)
        r = np.sqrt((d * d).sum(axis=1))
        r[i] = np.inf
        best[i] = r.min()
    assert best.mean() == pytest.approx(poisson_nn_mean_m(n / side ** 3), rel=0.03)
    d = 0.4
    assert np.mean(best < d) == pytest.approx(near_fraction(n / side ** 3, d), abs=0.03)


def test_near_fraction_at_the_budget_is_one_minus_exp_of_minus_gamma_cubed():
    d = 0.92
    assert near_fraction(poisson_density_for_nn(d), d) == pytest.approx(1 - math.exp(-GAMMA_4_3 ** 3))
    assert near_fraction(0.0, d) == 0.0


def test_uniform_box_budget_is_volume_over_the_poisson_volume():
    """Uniform density and speed U in an nx x m block of cubes l: N_max = floor(n* V), tau = nx l / U,
    the flux period tau / N_max, the inlet period (d / U + t_tol) / (1 - f)."""
    l, d, U = 0.5, 0.92, 1.3
    idx = box(30, 4, 4)
    b = separation_budget(idx, np.ones(len(idx)), np.full(len(idx), U), l, d)
    volume = len(idx) * l ** 3
    assert b.tunnel_volume_m3 == pytest.approx(volume)
    assert b.max_in_tunnel == math.floor(poisson_density_for_nn(d) * volume)
    assert b.densest_nn_m >= d and poisson_nn_mean_m((b.max_in_tunnel + 1) / volume) < d  # the largest such N
    assert b.mean_transit_s == pytest.approx(30 * l / U)
    assert b.flux_period_s == pytest.approx(b.mean_transit_s / b.max_in_tunnel)
    assert b.inlet_period_s == pytest.approx((d / U + ENTRY_TIMING_TOLERANCE_S) / (1 - ENTRY_OPEN_FRACTION))
    assert b.admission_period_s == max(b.flux_period_s, b.inlet_period_s)
    assert b.in_tunnel_admitted == pytest.approx(b.mean_transit_s / b.admission_period_s)
    assert b.in_tunnel_admitted <= b.max_in_tunnel


def test_max_in_tunnel_scales_as_volume_over_d_min_cubed():
    idx = box(40, 6, 6)
    rho, u = np.ones(len(idx)), np.ones(len(idx))
    base = separation_budget(idx, rho, u, 0.5, 0.92)
    double = separation_budget(idx, rho, u, 1.0, 0.92)        # 8 x the volume
    half_d = separation_budget(idx, rho, u, 0.5, 0.46)        # d_min / 2: 8 x the density
    assert double.max_in_tunnel == pytest.approx(8 * base.max_in_tunnel, abs=8)
    assert half_d.max_in_tunnel == pytest.approx(8 * base.max_in_tunnel, abs=8)


def test_the_densest_cv_sets_the_budget():
    """Doubling one CV's designed density (the others renormalised) halves the swarm that CV allows."""
    idx = box(20, 4, 4)
    u = np.ones(len(idx))
    flat = separation_budget(idx, relative_density(np.ones(len(idx)), np.ones(len(idx))), u, 1.0, 0.9)
    rho = np.ones(len(idx))
    rho[5] = 2.0
    peaked = separation_budget(idx, relative_density(rho, rho), u, 1.0, 0.9)
    total = rho.sum()
    assert peaked.max_in_tunnel == math.floor(poisson_density_for_nn(0.9) * total / 2.0)
    assert peaked.max_in_tunnel < flat.max_in_tunnel


def test_a_lone_vehicle_is_always_allowed():
    """A tunnel too small for two vehicles at d_min still admits one at a time (period = transit time)."""
    idx = box(4, 1, 1)
    b = separation_budget(idx, np.ones(4), np.ones(4), 0.5, 5.0)
    assert b.max_in_tunnel == 1
    assert b.flux_period_s == pytest.approx(b.mean_transit_s) == pytest.approx(2.0)


def test_the_inlet_or_the_flux_sets_the_admission():
    idx = box(10, 2, 2)
    rho = np.ones(len(idx))
    slow_inlet = np.where(idx[:, 0] == 0, 0.1, 2.0)
    b = separation_budget(idx, rho, slow_inlet, 0.5, 0.92)
    assert b.limit is AdmissionLimit.INLET and b.admission_period_s == b.inlet_period_s
    assert b.inlet_speed_m_s == pytest.approx(0.1)
    long_idx = box(200, 1, 1)   # a long thin fast tunnel: the inlet clears a vehicle faster than the flux budget
    b = separation_budget(long_idx, np.ones(200), np.full(200, 5.0), 0.5, 0.92)
    assert b.flux_period_s > b.inlet_period_s and b.limit is AdmissionLimit.FLUX


def test_transit_time_uses_the_mean_slice_flux_and_counts_reversed_cvs():
    """Little's law with a slice that carries a reversed CV: tau = l sum rho / mean slice flux."""
    idx = box(2, 2, 1)
    u = np.array([1.0, 1.0, 3.0, -1.0])   # slice 0 flux 2, slice 1 flux 2
    b = separation_budget(idx, np.ones(4), u, 1.0, 0.5)
    assert b.mean_transit_s == pytest.approx(4 / 2)


@pytest.mark.parametrize("u, match", [([-1.0, -1.0, 3.0, 3.0], "inlet slice flows backwards"),
                                      ([-1.0, -1.0, -1.0, -1.0], "no net axial flow")])
def test_no_through_flow_is_refused_by_name(u, match):
    with pytest.raises(ValueError, match=match):
        separation_budget(box(2, 2, 1), np.ones(4), np.array(u), 1.0, 0.5)


@pytest.mark.parametrize("cell, d", [(0.0, 0.9), (0.5, 0.0), (0.5, math.nan), (math.inf, 0.9)])
def test_bad_sizes_are_refused(cell, d):
    with pytest.raises(ValueError, match="separation budget"):
        separation_budget(box(2, 1, 1), np.ones(2), np.ones(2), cell, d)


def test_relative_density_falls_back_to_the_cfd_density_and_refuses_non_positive():
    np.testing.assert_allclose(relative_density(None, np.array([1.0, 3.0])), [0.5, 1.5])
    np.testing.assert_allclose(relative_density(np.array([2.0, 2.0]), np.array([1.0, 3.0])), [1.0, 1.0])
    for bad in (np.array([1.0, 0.0]), np.array([]), np.array([1.0, np.nan])):
        with pytest.raises(ValueError, match="relative density"):
            relative_density(bad, bad)


def test_header_is_json_numbers_and_the_limit_word():
    b = separation_budget(box(3, 1, 1), np.ones(3), np.ones(3), 1.0, 0.9)
    h = b.as_header()
    assert isinstance(h["max_in_tunnel"], int) and h["limit"] in ("flux", "inlet")
    assert all(isinstance(v, float) for k, v in h.items() if k not in ("max_in_tunnel", "limit"))
