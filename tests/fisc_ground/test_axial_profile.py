"""The axial profile (fisc_ground.fields.axial_profile): slices, volumes, the CFD's volume-weighted means,
the swarm's density and spread pressure, against hand-computed values."""

import numpy as np
import pytest

from fisc_ground.fields.axial_profile import axial_profile, profile_scores, slice_geometry


def _geom(open_fraction=(1.0, 0.5, 1.0, 1.0)):
    # four 0.5 m CVs: two in the first slice (x = 0.25), one each in the next two
    centres = np.array([[0.25, 0.25, 0.25], [0.25, -0.25, 0.25], [0.75, 0.25, 0.25], [1.25, 0.25, 0.25]])
    return slice_geometry(centres, 0.5, np.array(open_fraction), np.array([10.0, 40.0, 5.0, 1.0]),
                          np.array([1.0, 4.0, 2.0, 3.0]))


def test_slices_volumes_and_volume_weighted_cfd_means():
    g = _geom()
    np.testing.assert_allclose(g.x_m, [0.25, 0.75, 1.25])
    np.testing.assert_array_equal(g.slice_of_cv, [0, 0, 1, 2])
    np.testing.assert_allclose(g.volume_m3, [2 * 0.125, 0.125, 0.125])
    # slice 0: weights 1 and 0.5 (the CFD's open volume in each CV)
    assert g.cfd_pressure_pa[0] == pytest.approx((10.0 + 0.5 * 40.0) / 1.5)
    assert g.cfd_density_kg_m3[0] == pytest.approx((1.0 + 0.5 * 4.0) / 1.5)
    no_rho = slice_geometry(np.array([[0.25, 0, 0]]), 0.5, np.ones(1), np.ones(1), None)
    assert np.isnan(no_rho.cfd_density_kg_m3).all()


def test_density_and_spread_pressure_of_the_slices():
    g = _geom()
    k = 2.0  # two time samples
    # slice 0: agents of mass 1 at velocities (1,0,0) and (3,0,0) in its two CVs, each sample
    count = np.array([2.0, 2.0, 4.0, 0.0])
    mass = count.copy()
    momentum = np.array([[2.0, 0, 0], [6.0, 0, 0], [8.0, 0, 0], [0, 0, 0]])
    m_v2 = np.array([2.0, 18.0, 16.0, 0.0])
    sums = {"count": count, "mass_kg": mass, "momentum_kg_m_s": momentum, "m_v2_kg_m2_s2": m_v2,
            "m_dev2_kg_m2_s2": np.zeros(4), "n_time_samples": np.array(k), "n_ref_samples": np.array(k)}
    p = axial_profile(sums, g, min_samples=1)
    assert p.swarm_density_kg_m3[0] == pytest.approx(4.0 / (k * 0.25))
    assert p.swarm_density_kg_m3[1] == pytest.approx(4.0 / (k * 0.125))
    assert np.isnan(p.swarm_density_kg_m3[2]) and not p.compared[2]  # no sample
    # slice 0's spread about its mean 2 m/s: four samples at 1 and 3 -> sum m ||v - U||^2 = 4
    assert p.swarm_pressure_pa[0] == pytest.approx(2.0 / 3.0 * 4.0 / (k * 0.25))
    assert p.swarm_pressure_pa[1] == pytest.approx(0.0)  # all at 2 m/s
    # min_samples boundary: a slice with exactly min_samples samples is compared, one fewer is not
    assert axial_profile(sums, g, min_samples=4).compared[:2].tolist() == [True, True]
    assert axial_profile(sums, g, min_samples=5).compared[:2].tolist() == [False, False]


def test_scores_of_a_profile_equal_to_the_cfd_and_of_too_few_slices():
    g = _geom(open_fraction=(1.0, 1.0, 1.0, 1.0))
    # a swarm density proportional to the CFD's slice means: r = 1, nRMSE = 0
    rho_cfd = g.cfd_density_kg_m3
    mass = np.array([rho_cfd[0], rho_cfd[0], rho_cfd[1], rho_cfd[2]]) * 0.125 * 3.0
    sums = {"count": np.full(4, 5.0), "mass_kg": mass, "momentum_kg_m_s": np.zeros((4, 3)),
            "m_v2_kg_m2_s2": np.array([1.0, 2.0, 3.0, 0.5]), "m_dev2_kg_m2_s2": np.zeros(4),
            "n_time_samples": np.array(3.0), "n_ref_samples": np.array(3.0)}
    s = profile_scores(axial_profile(sums, g, min_samples=1))
    assert s["pearson_density"] == pytest.approx(1.0) and s["nrmse_density"] == pytest.approx(0.0, abs=1e-12)
    one = dict(sums, count=np.array([5.0, 5.0, 0.0, 0.0]), mass_kg=np.array([1.0, 1.0, 0.0, 0.0]))
    s1 = profile_scores(axial_profile(one, g, min_samples=1))
    assert np.isnan(s1["pearson_density"]) and np.isnan(s1["nrmse_density"])  # one slice: undefined


def test_bad_geometry_named():
    with pytest.raises(ValueError, match="slice length"):
        slice_geometry(np.zeros((1, 3)), 0.5, np.ones(1), np.ones(1), None, slice_m=0.0)
    with pytest.raises(ValueError, match="centers_m"):
        slice_geometry(np.zeros((0, 3)), 0.5, np.ones(0), np.ones(0), None)
