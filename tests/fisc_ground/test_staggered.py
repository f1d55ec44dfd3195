"""The continuity-consistent staggered field (fisc_ground.fit.staggered) and schema-2 maps."""

from __future__ import annotations

import numpy as np
import pytest

from fisc_agent.map.lookup import CommandField, map_flight_settings, PAPER_SETTINGS
from fisc_agent.map.codec import MapError, decode_map, encode_map
from fisc_ground.maps.build import FitConfig, build_map, build_map_from_reference
from fisc_ground.reference.analytic import analytic_nozzle
from fisc_ground.fit.partition import cv_open_fraction, partition_field
from fisc_ground.reference.load import load_reference
from fisc_ground.fit.staggered import (AUTO_CONTINUITY_WEIGHTS, AUTO_DENSITY_AMPLITUDES, STATIC_VELOCITY_BUDGET,
                                   STATIC_VELOCITY_LIMIT, StaggeredConfig, build_staggered,
                                   design_density, project, static_velocity_nrmse)


def _net_outflow(grid, fx, fy, fz, rho):
    """Net outflow of rho_f u through every CV's faces, recomputed here from the face arrays."""
    pad = np.full(tuple(s + 2 for s in grid.shape), -1)
    pad[1:-1, 1:-1, 1:-1] = grid
    out = np.zeros(rho.size)
    for (i, j, k) in np.argwhere(grid >= 0):
        c = grid[i, j, k]
        total = 0.0
        for a, f in enumerate((fx, fy, fz)):
            lo = [i, j, k]
            hi = [i, j, k]
            hi[a] += 1
            nb_lo = [i + 1, j + 1, k + 1]
            nb_lo[a] -= 1
            nb_hi = [i + 1, j + 1, k + 1]
            nb_hi[a] += 1
            r_lo = rho[c] if pad[tuple(nb_lo)] < 0 else 0.5 * (rho[c] + rho[pad[tuple(nb_lo)]])
            r_hi = rho[c] if pad[tuple(nb_hi)] < 0 else 0.5 * (rho[c] + rho[pad[tuple(nb_hi)]])
            total += r_hi * f[tuple(hi)] - r_lo * f[tuple(lo)]
        out[c] = total
    return out


def test_projection_is_divergence_free_with_walls_closed():
    cmap = build_map_from_reference("analytic", FitConfig())
    grid = np.asarray(cmap["grid_cv"])
    fx, fy, fz = (np.asarray(cmap[k]) for k in ("face_u_x_m_s", "face_u_y_m_s", "face_u_z_m_s"))
    rho = np.asarray(cmap["cv_design_density"])
    div = _net_outflow(grid, fx, fy, fz, rho)
    inflow = float(np.sum(rho[grid[0][grid[0] >= 0]] * fx[0][grid[0] >= 0]))
    assert np.max(np.abs(div)) < 1e-9 * inflow
    # wall faces (one side without a CV, not inlet/outlet) carry nothing
    pad = np.full(tuple(s + 2 for s in grid.shape), -1)
    pad[1:-1, 1:-1, 1:-1] = grid
    lo = pad[1:-1, :-1, 1:-1] >= 0
    hi = pad[1:-1, 1:, 1:-1] >= 0
    assert np.all(fy[lo ^ hi] == 0.0)
    assert np.all(fy[~lo & ~hi] == 0.0)
    # the inlet carries the CFD inflow
    t = np.asarray(cmap["target_velocity_m_s"])
    np.testing.assert_allclose(fx[0][grid[0] >= 0], t[grid[0][grid[0] >= 0], 0])
    assert cmap.body["staggered"]["max_divergence"] < 1e-9


def test_uniform_duct_keeps_the_cfd_velocity():
    # a straight duct of full cubes: the CFD field is already continuity-consistent
    grid = np.arange(4 * 2 * 2).reshape(4, 2, 2)
    u = np.tile([2.0, 0.0, 0.0], (16, 1))
    st = project(grid, u, np.ones(16), np.ones(16))
    np.testing.assert_allclose(st.face_u_x_m_s, 2.0)
    np.testing.assert_allclose(st.face_u_y_m_s, 0.0, atol=1e-12)
    np.testing.assert_allclose(st.face_u_z_m_s, 0.0, atol=1e-12)


def test_designed_density_follows_continuity_and_cfd_pattern():
    grid = np.arange(4).reshape(4, 1, 1)
    u = np.array([[1.0, 0, 0], [2.0, 0, 0], [2.0, 0, 0], [1.0, 0, 0]])
    cfd = np.array([1.0, 0.0, 0.0, 1.0])  # CFD density low where the flow is fast
    for beta in (0.0, 0.5, 1.0):
        rho = design_density(grid, u, cfd, cfd, beta, 1.0)
        assert rho.mean() == pytest.approx(1.0)
        assert rho[1] < rho[0] and rho[2] < rho[3]
    # beta = 1: n u is constant along the duct (continuity at the CFD velocity)
    rho = design_density(grid, u, np.full(4, 1.2), np.full(4, 3.0), 1.0, density_amplitude=1.0)
    np.testing.assert_allclose(rho * u[:, 0], rho[0] * u[0, 0])
    with pytest.raises(ValueError, match="CV 2"):
        design_density(grid, u, np.array([1.0, 2.0, np.nan, 1.0]), np.array([1.0, 2.0, np.nan, 1.0]), 0.5, 1.0)


def test_density_amplitude_scales_the_designed_contrast():
    # 4-CV duct, u = 1, 2, 2, 1: s = 1, 2, 2, 1, so the staircase's contrast A = 1 - min(1/s)/max(1/s) = 0.5
    # and at beta = 1, rho ~ 1 - k A (1 - f_cont) = 1, 1 - k/2, 1 - k/2, 1
    grid = np.arange(4).reshape(4, 1, 1)
    u = np.array([[1.0, 0, 0], [2.0, 0, 0], [2.0, 0, 0], [1.0, 0, 0]])
    flat = np.full(4, 1.2)
    for k in (0.5, 1.0, 1.5):
        rho = design_density(grid, u, flat, flat, 1.0, density_amplitude=k)
        assert rho.mean() == pytest.approx(1.0)
        assert rho.min() / rho.max() == pytest.approx(1.0 - 0.5 * k)
    with pytest.raises(ValueError, match="below 2"):  # k A = 1: the thinnest CV would be empty
        design_density(grid, u, flat, flat, 1.0, density_amplitude=2.0)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="density_amplitude"):
            FitConfig(density_amplitude=bad)


def test_schema_2_map_roundtrip_and_version_1_still_loads():
    field = analytic_nozzle()
    meta, arrays = build_map(field, FitConfig())
    m2 = decode_map(encode_map(meta, arrays))
    assert m2.schema_version == 2
    s = map_flight_settings(m2)
    assert (s.mode, s.lookahead_s) == (m2.body["flight"]["mode"], m2.body["flight"]["lookahead_s"])
    assert CommandField.from_map(m2).face_u_m_s is not None
    meta1, arrays1 = build_map(field, FitConfig(staggered=False))
    m1 = decode_map(encode_map(meta1, arrays1))
    assert m1.schema_version == 1 and "face_u_x_m_s" not in m1.arrays
    assert map_flight_settings(m1) == PAPER_SETTINGS
    # the shipped map of an older build is schema 1 or 2; either loads
    from fisc_ground.maps.build import load_shipped_default_map
    assert load_shipped_default_map().schema_version in (1, 2)


@pytest.mark.parametrize("mutate, message", [
    (lambda a, m: a.pop("face_u_y_m_s"), "face_u_y_m_s"),
    (lambda a, m: a.__setitem__("face_u_x_m_s", a["face_u_x_m_s"][:-1]), "face_u_x_m_s"),
    (lambda a, m: a.__setitem__("face_u_z_m_s", np.where(a["face_u_z_m_s"] == 0, np.nan, a["face_u_z_m_s"])),
     "non-finite"),
    (lambda a, m: m.pop("flight"), "flight"),
    (lambda a, m: m["flight"].__setitem__("lookahead_s", -1.0), "flight.lookahead_s"),
])
def test_bad_schema_2_maps_are_refused_naming_the_problem(mutate, message):
    meta, arrays = build_map(analytic_nozzle(), FitConfig())
    arrays = dict(arrays)
    meta = dict(meta, flight=dict(meta["flight"]))
    mutate(arrays, meta)
    with pytest.raises(MapError, match=message):
        decode_map(encode_map(meta, arrays))


def test_static_velocity_nrmse_is_zero_where_the_field_is_the_cfd():
    grid = np.arange(4 * 2 * 2).reshape(4, 2, 2)
    u = np.tile([2.0, 0.0, 0.0], (16, 1))
    st = project(grid, u, np.ones(16), np.ones(16))
    assert static_velocity_nrmse(grid, st.face_u_x_m_s, u) == pytest.approx(0.0, abs=1e-12)
    # a CFD twice as fast in one CV: the field's own figure against it is no longer 0
    u2 = u.copy()
    u2[5, 0] = 4.0
    assert static_velocity_nrmse(grid, st.face_u_x_m_s, u2) > 0.1


def test_automatic_amplitude_stays_within_the_static_velocity_budget():
    """No amplitude given: the largest of AUTO_DENSITY_AMPLITUDES whose static field keeps the velocity
    nRMSE within the budget (the tunnel: the largest), and 1 when even 1 misses it."""
    cvs = partition_field(load_reference("cd_nozzle_inviscid"), cell_size_m=0.5)

    def build(**kw):
        return build_staggered(cvs.grid_cv, cvs.target_velocity_m_s, cvs.target_density_kg_m3,
                               cvs.target_pressure_gauge_pa, cv_open_fraction(cvs), StaggeredConfig(**kw))

    fixed = {k: build(density_amplitude=k) for k in AUTO_DENSITY_AMPLITUDES}
    static = {k: st.static_velocity_nrmse for k, st in fixed.items()}
    assert all(fixed[k].density_amplitude == k for k in fixed)
    assert [static[k] for k in sorted(static)] == sorted(static.values())  # contrast costs velocity
    top = AUTO_DENSITY_AMPLITUDES[0]
    auto = build()
    assert auto.density_amplitude == top and static[top] <= STATIC_VELOCITY_BUDGET
    np.testing.assert_array_equal(auto.face_u_x_m_s, fixed[top].face_u_x_m_s)
    np.testing.assert_array_equal(auto.design_density, fixed[top].design_density)
    between = 0.5 * (static[AUTO_DENSITY_AMPLITUDES[1]] + static[top])
    assert build(velocity_budget=between).density_amplitude == AUTO_DENSITY_AMPLITUDES[1]
    tight = build(velocity_budget=0.5 * static[1.0])
    assert tight.density_amplitude == 1.0 and tight.static_velocity_nrmse == static[1.0]
    with pytest.raises(ValueError, match="velocity_budget"):
        StaggeredConfig(velocity_budget=0.0)


def test_automatic_continuity_weight_is_raised_only_where_the_static_field_misses_the_limit():
    """No beta given: the lowest of AUTO_CONTINUITY_WEIGHTS whose static field at k = 1 keeps the velocity
    nRMSE within the limit (the tunnel: the lowest, 0.5), a higher one when the limit is tighter, the
    last when none does; the amplitude is then chosen at that beta.  A given beta is kept as it is."""
    cvs = partition_field(load_reference("cd_nozzle_inviscid"), cell_size_m=0.5)

    def build(**kw):
        return build_staggered(cvs.grid_cv, cvs.target_velocity_m_s, cvs.target_density_kg_m3,
                               cvs.target_pressure_gauge_pa, cv_open_fraction(cvs), StaggeredConfig(**kw))

    at_k1 = {b: build(continuity_weight=b, density_amplitude=1.0).static_velocity_nrmse
             for b in AUTO_CONTINUITY_WEIGHTS}
    assert [at_k1[b] for b in AUTO_CONTINUITY_WEIGHTS] == sorted(at_k1.values(), reverse=True)  # beta buys velocity
    lowest, second = AUTO_CONTINUITY_WEIGHTS[:2]
    assert at_k1[lowest] <= STATIC_VELOCITY_LIMIT
    auto = build()
    assert auto.continuity_weight == lowest
    fixed = build(continuity_weight=lowest)
    np.testing.assert_array_equal(auto.face_u_x_m_s, fixed.face_u_x_m_s)
    assert fixed.density_amplitude == auto.density_amplitude
    tighter = build(velocity_limit=0.5 * (at_k1[lowest] + at_k1[second]))
    assert tighter.continuity_weight == second
    same = build(continuity_weight=second, density_amplitude=tighter.density_amplitude)
    np.testing.assert_array_equal(tighter.design_density, same.design_density)
    assert build(velocity_limit=1e-6).continuity_weight == AUTO_CONTINUITY_WEIGHTS[-1]
    assert build(continuity_weight=0.25, velocity_limit=1e-6).continuity_weight == 0.25
    with pytest.raises(ValueError, match="velocity_limit"):
        StaggeredConfig(velocity_limit=float("nan"))
