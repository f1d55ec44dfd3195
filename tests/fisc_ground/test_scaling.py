"""Specification of the pressure mapping kappa and the speed scale S (DESIGN.md section 3)."""

from __future__ import annotations


import numpy as np
import pytest

from fisc_ground.fit.fitting import fit_velocities, initial_dispersion
from fisc_ground.fit.partition import partition
from fisc_ground.fit.scaling import (
    DEFAULT_DISPERSION_RATIO,
    DEFAULT_MAX_SPEED_M_S,
    Scaling,
    choose_kappa,
    choose_scale,
    default_max_dispersion,
    swarm_pressure_target,
)

DV = 0.125


def test_swarm_pressure_target_is_the_affine_image_of_cfd_pressure():
    p_cfd = np.array([-104.0, -20.0, 0.5, -50.0])
    pt = swarm_pressure_target(p_cfd, 2.0)
    np.testing.assert_allclose(pt, 2.0 * (p_cfd + 104.0))
    assert pt.min() == 0.0 and np.all(pt >= 0)
    np.testing.assert_array_equal(np.argsort(pt), np.argsort(p_cfd))  # pattern kept
    with pytest.raises(ValueError, match="CV 1: CFD pressure is not finite"):
        swarm_pressure_target(np.array([0.0, np.nan]), 1.0)


def test_kappa_puts_the_worst_dispersion_at_the_requested_value():
    p_cfd = np.array([-100.0, -40.0, 0.0, 10.0])
    for n_min, disp, mass in [(2, 1.0, 1.0), (3, 0.4, 0.25)]:
        kappa = choose_kappa(p_cfd, DV, mass, n_min, disp)
        pt = swarm_pressure_target(p_cfd, kappa)
        sigma = initial_dispersion(pt, DV, mass, n_min)
        assert sigma.max() == pytest.approx(disp)
        assert sigma.argmax() == 3  # the CV of highest CFD pressure
    # uniform CFD pressure: every target is 0 whatever kappa is
    assert choose_kappa(np.full(5, -3.0), DV, 1.0, 2, 1.0) == 1.0
    with pytest.raises(ValueError, match="max_dispersion_m_s"):
        choose_kappa(p_cfd, DV, 1.0, 2, 0.0)


def test_default_dispersion_is_a_fraction_of_the_peak_target_speed():
    vt = np.array([[3.0, 4.0, 0.0], [-1.0, 0.0, 0.0]])
    assert default_max_dispersion(vt) == pytest.approx(DEFAULT_DISPERSION_RATIO * 5.0)
    assert default_max_dispersion(vt, ratio=0.5) == pytest.approx(2.5)


def test_scale_is_the_largest_that_keeps_every_command_within_the_speed_limit():
    v = np.array([[[3.0, 4.0, 0.0], [np.nan, np.nan, np.nan]], [[-10.0, 0.0, 0.0], [1.0, 1.0, 1.0]]])
    s = choose_scale(v, 5.0)
    assert s == pytest.approx(0.5)
    speeds = np.linalg.norm(s * v, axis=-1)
    assert np.nanmax(speeds) == pytest.approx(5.0)
    assert choose_scale(v) == pytest.approx(DEFAULT_MAX_SPEED_M_S / 10.0)
    assert choose_scale(v, 50.0, max_scale=1.0) == 1.0  # optional cap
    assert choose_scale(np.zeros((2, 3)), 5.0) == 1.0  # nothing moves
    with pytest.raises(ValueError, match="max_speed_m_s"):
        choose_scale(v, -1.0)
    with pytest.raises(ValueError, match="no finite"):
        choose_scale(np.full((2, 3), np.nan))


def test_scaled_reference_map_is_flyable(shared_path):
    """End to end on the shipped inviscid export: default kappa and S give flyable commands."""
    data = np.loadtxt(shared_path("reference", "cd_nozzle_inviscid", "fluent_export_3d.csv"), delimiter=",", skiprows=1)
    cv = partition(data[:, 1:4], data[:, 6:9], data[:, 4], data[:, 5])
    disp = default_max_dispersion(cv.target_velocity_m_s)
    kappa = choose_kappa(cv.target_pressure_gauge_pa, cv.cell_volume_m3, 1.0, 2, disp)
    pt = swarm_pressure_target(cv.target_pressure_gauge_pa, kappa)
    fit = fit_velocities(cv.target_velocity_m_s, pt, cv.cell_volume_m3, agent_mass_kg=1.0, n_min=2)
    assert fit.converged.all()
    s = choose_scale(fit.velocities_m_s, DEFAULT_MAX_SPEED_M_S)
    scaling = Scaling(kappa=kappa, scale=s, max_speed_m_s=DEFAULT_MAX_SPEED_M_S, max_dispersion_m_s=disp)
    cmd_speed = np.linalg.norm(scaling.scale * fit.velocities_m_s, axis=-1)
    assert np.nanmax(cmd_speed) == pytest.approx(DEFAULT_MAX_SPEED_M_S)
    assert np.all(np.linalg.norm(s * fit.mean_velocity_m_s, axis=1) <= DEFAULT_MAX_SPEED_M_S + 1e-9)
    # the per-agent rms deviation of every fitted CV stays within the chosen dispersion
    dev = fit.velocities_m_s - cv.target_velocity_m_s[:, None, :]
    rms = np.sqrt(np.nanmean(np.sum(dev * dev, axis=-1), axis=1))
    assert rms.max() <= disp * (1 + 1e-9)
    assert s == pytest.approx(0.145, abs=0.01)  # 13.6 m/s throat + dispersion within the 2 m/s limit
