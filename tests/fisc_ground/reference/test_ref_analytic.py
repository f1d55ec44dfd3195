"""Oracle tests of the analytic quasi-1-D isentropic reference."""

import numpy as np
import pytest

from fisc_ground.reference.analytic import (
    GAMMA_AIR,
    R_GAS_AIR_J_KG_K,
    analytic_nozzle,
    area_mach_ratio,
    body_lattice,
    isentropic_quasi_1d,
    subsonic_mach_from_area_ratio,
    tunnel_radius_m,
    tunnel_radius_slope,
)
from fisc_ground.reference.field import P_REF_PA, ReferenceError

X = np.linspace(0.0, 15.0, 601)


@pytest.fixture(scope="module")
def flow():
    return isentropic_quasi_1d(X, tunnel_radius_m(X))


def test_tunnel_radius_matches_design_formula():
    np.testing.assert_allclose(tunnel_radius_m([0.0, 6.0, 15.0, 3.0, 10.5]),
                               [1.5, 0.75, 1.5, 1.125, 1.125], atol=1e-12)
    # continuous slope: central difference of R agrees with the exact slope
    h = 1e-6
    np.testing.assert_allclose((tunnel_radius_m(X + h) - tunnel_radius_m(X - h)) / (2 * h),
                               tunnel_radius_slope(X), atol=1e-6)


def test_area_mach_inversion_roundtrip():
    m = np.array([1e-3, 0.01, 0.039, 0.3, 0.7, 0.99, 1.0])
    np.testing.assert_allclose(subsonic_mach_from_area_ratio(area_mach_ratio(m)), m, rtol=1e-12)
    with pytest.raises(ValueError, match="choke"):
        subsonic_mach_from_area_ratio(np.array([0.9]))


def test_mass_flow_constant(flow):
    mdot = flow.density_kg_m3 * flow.velocity_m_s * flow.area_m2
    np.testing.assert_allclose(mdot, flow.mass_flow_kg_s, rtol=1e-9)
    # ~28.1 kg/s as the CFD inlet/outlet mass flow
    assert flow.mass_flow_kg_s == pytest.approx(28.11, rel=2e-3)


def test_isentropic_and_stagnation_temperature(flow):
    s = flow.pressure_pa / flow.density_kg_m3 ** GAMMA_AIR
    np.testing.assert_allclose(s, s[0], rtol=1e-12)
    cp = GAMMA_AIR * R_GAS_AIR_J_KG_K / (GAMMA_AIR - 1.0)
    t0 = flow.temperature_k + flow.velocity_m_s ** 2 / (2 * cp)
    np.testing.assert_allclose(t0, flow.stagnation_temperature_k, rtol=1e-13)
    np.testing.assert_allclose(flow.pressure_pa, flow.density_kg_m3 * R_GAS_AIR_J_KG_K
                               * flow.temperature_k, rtol=1e-13)


def test_boundary_conditions_and_cfd_throat_velocity(flow):
    assert flow.velocity_m_s[0] == pytest.approx(3.38, rel=1e-12)
    assert flow.temperature_k[0] == pytest.approx(300.0, rel=1e-12)
    assert flow.pressure_pa[-1] == pytest.approx(P_REF_PA, rel=1e-14)
    throat = np.argmin(flow.radius_m)
    # CFD README (inviscid case): throat mean axial velocity 13.5296 m/s
    assert flow.velocity_m_s[throat] == pytest.approx(13.53, rel=0.03)
    assert flow.velocity_m_s[throat] == pytest.approx(13.5296, rel=1e-3)
    assert flow.mach.max() < 0.05 and np.argmax(flow.velocity_m_s) == throat


def test_field_on_lattice_and_streamline_slope():
    f = analytic_nozzle()
    assert f.n_nodes == 63539  # the Fluent-style export's node count
    assert f.source == "builtin:analytic" and f.density_kg_m3 is not None
    x, y, z = f.points_m.T
    r = np.hypot(y, z)
    assert np.all(r < tunnel_radius_m(x))
    u = f.velocity_m_s
    # velocity direction at radius r follows the scaled wall: u_r / u_x = (r/R) dR/dx
    u_r = np.where(r > 0, (u[:, 1] * y + u[:, 2] * z) / np.where(r > 0, r, 1), 0.0)
    np.testing.assert_allclose(u_r, u[:, 0] * r / tunnel_radius_m(x) * tunnel_radius_slope(x),
                               atol=1e-12)
    # no swirl, zero radial velocity on the axis
    np.testing.assert_allclose(u[:, 1] * z - u[:, 2] * y, 0.0, atol=1e-12)
    assert np.all(u[r == 0, 1:] == 0.0)
    # outlet plane at ambient pressure
    np.testing.assert_allclose(f.pressure_gauge_pa[x == 15.0], 0.0, atol=1e-9)


def test_custom_radius_profile():
    f = analytic_nozzle(radius_m=lambda x: np.full(np.shape(x), 0.5), length_m=2.0,
                        name="pipe")
    np.testing.assert_allclose(f.velocity_m_s[:, 0], 3.38, rtol=1e-12)
    np.testing.assert_allclose(f.velocity_m_s[:, 1:], 0.0, atol=1e-12)
    np.testing.assert_allclose(f.pressure_gauge_pa, 0.0, atol=1e-9)
    # a linear cone: numerical slope gives u_r / u_x = (r/R) R'
    cone = analytic_nozzle(radius_m=lambda x: 1.0 - 0.1 * np.asarray(x), length_m=3.0, name="c")
    x, y, _ = cone.points_m.T
    sel = y > 0
    np.testing.assert_allclose(cone.velocity_m_s[sel, 1] / cone.velocity_m_s[sel, 0],
                               y[sel] / (1.0 - 0.1 * x[sel]) * -0.1, rtol=1e-6)
    with pytest.raises(ReferenceError, match="choke"):
        analytic_nozzle(radius_m=lambda x: 1.0 - 0.3 * np.asarray(x), length_m=3.0,
                        inlet_velocity_m_s=150.0)


def test_body_lattice_layout():
    pts = body_lattice(0.0, 1.0, lambda x: np.full(np.shape(x), 0.25))
    xs = np.unique(pts[:, 0])
    np.testing.assert_array_equal(xs, np.round(np.arange(11) * 0.1, 9))
    assert 0.3 in xs  # correctly rounded decimals, not 3 * 0.1
    # nodes with y^2+z^2 < 0.25^2 per plane: 21 (0, +-0.1, +-0.2 combos, minus corners (0.2,0.2))
    assert pts.shape[0] == 11 * 21
    # symmetric about the axis
    np.testing.assert_array_equal(np.sort(pts[:, 1]), np.sort(-pts[:, 1]))
