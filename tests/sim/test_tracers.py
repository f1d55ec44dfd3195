"""``sim.tracers``: ideal tracers through a staggered command field, against analytic densities and
against the shipped map's design (the claim of ``fisc_ground.fit.staggered``: tracers keep rho_d)."""

from __future__ import annotations

import numpy as np
import pytest

from fisc_agent.map.lookup import CommandField
from fisc_agent.map.codec import load_map
from fisc_ground.maps.build import default_map_path
from sim.tracers import Integrator, inlet_seeds, tracer_density

CELL = 0.5
NX, NY, NZ = 6, 2, 2


def _box_duct(face_u_x_m_s: np.ndarray) -> CommandField:
    """A straight box duct of NX x NY x NZ CVs whose axial face velocity is ``face_u_x_m_s[i]`` on the
    whole x plane i (no lateral flow)."""
    grid = np.arange(NX * NY * NZ, dtype=np.int32).reshape(NX, NY, NZ)
    idx = np.argwhere(grid >= 0)
    n = idx.shape[0]
    faces = (np.broadcast_to(np.asarray(face_u_x_m_s, float)[:, None, None], (NX + 1, NY, NZ)).copy(),
             np.zeros((NX, NY + 1, NZ)), np.zeros((NX, NY, NZ + 1)))
    return CommandField(origin_m=np.zeros(3), cell_size_m=CELL, grid_cv=grid, centers_m=(idx + 0.5) * CELL,
                        mean_cmd_m_s=np.zeros((n, 3)), slot_cmd_m_s=np.zeros((n, 1, 3)), n_star=np.ones(n, int),
                        face_u_m_s=faces)


@pytest.mark.parametrize("integrator", list(Integrator))
def test_a_uniform_flow_keeps_the_inflow_density_everywhere(integrator):
    """u = 0.8 m/s everywhere: every CV holds the inlet's density, whichever the integrator; none is lost."""
    field = _box_duct(np.full(NX + 1, 0.8))
    rho_in = 1.3
    got = tracer_density(field, np.full(field.n_cv, rho_in), seeds_per_axis=4, dt_s=0.05, integrator=integrator)
    np.testing.assert_allclose(got.density, rho_in, rtol=0.005)
    assert got.lost_fraction == 0.0
    assert got.inflow == pytest.approx(rho_in * 0.8 * NY * NZ * CELL ** 2)


def test_an_accelerating_flow_holds_the_analytic_density():
    """u_x linear between face values U_i, U_i+1 in every cube (no lateral flow): steady continuity
    n u = rho_in U_0 gives the cube mean rho_in U_0 ln(U_i+1 / U_i) / (U_i+1 - U_i)."""
    u_faces = 0.5 * 1.3 ** np.arange(NX + 1)
    field = _box_duct(u_faces)
    rho_in = 1.2
    got = tracer_density(field, np.full(field.n_cv, rho_in), seeds_per_axis=4, dt_s=0.01)
    a, b = u_faces[:-1], u_faces[1:]
    want_slice = rho_in * u_faces[0] * np.log(b / a) / (b - a)
    slice_of = np.argwhere(np.asarray(field.grid_cv) >= 0)[:, 0]  # the x index of each CV (ids run x-major)
    np.testing.assert_allclose(got.density, want_slice[slice_of], rtol=0.004)
    assert got.density[slice_of == 0].mean() > 1.5 * got.density[slice_of == NX - 1].mean()  # not flat


def test_inlet_seeds_carry_the_designed_number_flux():
    """Seeds sit on the inlet plane inside the inlet faces, and their fluxes sum to rho_d u_x A per face."""
    field = _box_duct(np.full(NX + 1, 0.6))
    rho = np.linspace(1.0, 2.0, field.n_cv)
    pts, flux = inlet_seeds(field, rho, seeds_per_axis=3)
    assert pts.shape == (NY * NZ * 9, 3) and np.all(field.locate(pts)[2] >= 0)
    assert np.allclose(pts[:, 0], 0.0, atol=1e-6)
    inlet_cvs = np.asarray(field.grid_cv)[0].ravel()
    assert flux.sum() == pytest.approx(0.6 * CELL ** 2 * rho[inlet_cvs].sum())


def test_the_shipped_map_carries_its_designed_density_for_ideal_tracers():
    """The default map's staggered field (the projection of ``fisc_ground.fit.staggered`` and the linear
    rule inside each cube) keeps the designed density for tracers that follow it exactly: the median
    CV within 1.5 %, every x slice within 4 % (measured: 3.0 %), the cubes behind outward steps within
    3 %, r >= 0.98, in absolute units (mean 1)."""
    cmap = load_map(default_map_path())
    field = CommandField.from_map(cmap)
    rho_d = np.asarray(cmap["cv_design_density"], dtype=float)
    got = tracer_density(field, rho_d, seeds_per_axis=16, dt_s=0.02)
    ratio = got.density / rho_d
    assert np.median(np.abs(ratio - 1.0)) < 0.015
    assert np.corrcoef(got.density, rho_d)[0, 1] >= 0.98
    assert got.density.mean() == pytest.approx(rho_d.mean(), rel=0.01)
    assert got.lost_fraction < 0.005
    slice_of = np.argwhere(np.asarray(field.grid_cv) >= 0)[:, 0]  # CV ids run x-major
    per_slice = np.bincount(slice_of, ratio) / np.bincount(slice_of)
    assert np.all(np.abs(per_slice - 1.0) < 0.04), per_slice.round(3)
    walls = field.wall_faces[tuple(np.argwhere(np.asarray(field.grid_cv) >= 0).T)]  # CV ids run in this order
    closed_upstream = walls[:, 0, 0]
    assert closed_upstream.sum() >= 10 and abs(ratio[closed_upstream].mean() - 1.0) < 0.03
    # holding each velocity for the 20 Hz command interval empties the cubes behind the outward steps
    held = tracer_density(field, rho_d, seeds_per_axis=16, dt_s=0.05, integrator=Integrator.EULER)
    assert (held.density / rho_d)[closed_upstream].mean() < 0.7


def test_bad_inputs_are_refused_with_the_reason():
    field = _box_duct(np.full(NX + 1, 0.6))
    with pytest.raises(ValueError, match="design_density"):
        tracer_density(field, np.ones(3))
    with pytest.raises(ValueError, match="design_density"):
        tracer_density(field, np.zeros(field.n_cv))
    with pytest.raises(ValueError, match="dt_s"):
        tracer_density(field, np.ones(field.n_cv), dt_s=0.0)
    with pytest.raises(ValueError, match="seeds_per_axis"):
        tracer_density(field, np.ones(field.n_cv), seeds_per_axis=0)
    bare = CommandField(origin_m=field.origin_m, cell_size_m=CELL, grid_cv=field.grid_cv, centers_m=field.centers_m,
                        mean_cmd_m_s=field.mean_cmd_m_s, slot_cmd_m_s=field.slot_cmd_m_s, n_star=field.n_star)
    with pytest.raises(ValueError, match="schema-1"):
        tracer_density(bare, np.ones(field.n_cv))
