"""Specification of the axisymmetric importer and the revolve into 3-D."""


import numpy as np
import pytest

from fisc_ground.reference.analytic import body_lattice
from fisc_ground.reference.axisym import (
    estimate_wall_from_cells,
    read_axisym_csv,
    revolve_axisymmetric,
)
from fisc_ground.reference.field import ReferenceError
from fisc_ground.reference.fluent_csv import read_fluent_csv





def cell_grid(length=2.0, radius=1.0, nx=40, nr=10, grading=1.0):
    """Cell centres of a structured (x, r) mesh of a pipe, optional geometric radial grading."""
    w = grading ** np.arange(nr)
    faces = np.concatenate([[0.0], np.cumsum(w)]) / w.sum() * radius
    rc = 0.5 * (faces[1:] + faces[:-1])
    xc = (np.arange(nx) + 0.5) * length / nx
    X, Rr = np.meshgrid(xc, rc, indexing="ij")
    return X.ravel(), Rr.ravel()


def test_revolve_reproduces_linear_fields_and_rotates_radial_velocity():
    x, r = cell_grid()
    ux = 2.0 + 0.5 * x - 0.3 * r
    ur = 0.2 * r
    p = 10.0 - 4.0 * x
    rho = 1.2 + 0.01 * x
    pts, vel, pres, dens = revolve_axisymmetric(x, r, ux, ur, p, rho, spacing_m=0.1)
    # same lattice as the body of revolution R = 1 over x in [0, 2]
    np.testing.assert_array_equal(pts, body_lattice(0.0, 2.0, lambda q: np.ones(np.shape(q))))
    X, Y, Z = pts.T
    R = np.hypot(Y, Z)
    inside = (X >= 0.025) & (X <= 1.975) & (R <= 0.95)  # inside the cell-centre hull
    # u_x is linear in r only off the axis (|r| has a kink there): check beyond the first row
    off_axis = inside & (R >= 0.05)
    np.testing.assert_allclose(vel[off_axis, 0], (2.0 + 0.5 * X - 0.3 * R)[off_axis], atol=1e-12)
    np.testing.assert_allclose(pres[inside], (10.0 - 4.0 * X)[inside], atol=1e-12)
    np.testing.assert_allclose(dens[inside], (1.2 + 0.01 * X)[inside], atol=1e-12)
    # u_r = 0.2 r rotated into y, z: u_y = 0.2 y, u_z = 0.2 z (also across the axis)
    np.testing.assert_allclose(vel[inside, 1], 0.2 * Y[inside], atol=1e-12)
    np.testing.assert_allclose(vel[inside, 2], 0.2 * Z[inside], atol=1e-12)
    assert np.all(vel[R == 0.0, 1:] == 0.0)
    # nearest fallback outside the hull: finite everywhere
    assert np.all(np.isfinite(vel)) and np.all(np.isfinite(pres))


def test_revolve_without_density():
    x, r = cell_grid(nx=10, nr=5)
    _, _, _, dens = revolve_axisymmetric(x, r, np.ones_like(x), 0 * x, 0 * x, None)
    assert dens is None


def test_wall_estimate_handles_geometric_grading():
    for grading in (1.0, 0.9, 0.96):
        x, r = cell_grid(nr=30, grading=grading)
        xw, rw = estimate_wall_from_cells(x, r)
        assert xw.size == 40
        np.testing.assert_allclose(rw, 1.0, atol=1e-9)


def write(tmp_path, text, name="ax.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def small_csv(x, r, extra_header="", extra=None):
    lines = ["x,r,u_x,u_r,p,rho,T" + extra_header]
    for i, (a, b) in enumerate(zip(x, r)):
        lines.append(f"{a},{b},{3.0 + a},{0.0},{-a},{1.2},{300.0}" + (extra[i] if extra else ""))
    return "\n".join(lines) + "\n"


def test_read_small_axisym_csv(tmp_path):
    x, r = cell_grid(nx=20, nr=6)
    f = read_axisym_csv(write(tmp_path, small_csv(x, r)))
    assert f.extras["revolved"] and f.pressure_kind == "gauge"
    lattice = body_lattice(0.0, 2.0, lambda q: np.ones(np.shape(q)))
    np.testing.assert_array_equal(f.points_m, lattice)
    X = f.points_m[:, 0]
    inside = (X >= 0.05) & (X <= 1.95) & (np.hypot(f.points_m[:, 1], f.points_m[:, 2]) <= r.max())
    np.testing.assert_allclose(f.velocity_m_s[inside, 0], 3.0 + X[inside], atol=1e-12)
    np.testing.assert_allclose(f.pressure_gauge_pa[inside], -X[inside], atol=1e-12)


def test_axisym_bad_inputs(tmp_path):
    x, r = cell_grid(nx=10, nr=4)
    text = small_csv(x, r).replace("u_r", "w")
    with pytest.raises(ReferenceError, match=r"ax\.csv: line 1: missing required column\(s\): u_r"):
        read_axisym_csv(write(tmp_path, text))
    lines = small_csv(x, r).splitlines()
    lines[5] = "-" + lines[5].split(",", 1)[0] + "," + "-0.5," + lines[5].split(",", 2)[2]
    with pytest.raises(ReferenceError, match=r"line 6, column 2 \('r'\): negative radius"):
        read_axisym_csv(write(tmp_path, "\n".join(lines)))
    lines = small_csv(x, r).splitlines()
    lines.append(lines[3])
    with pytest.raises(ReferenceError, match=r"duplicate point .* lines 4 and 42"):
        read_axisym_csv(write(tmp_path, "\n".join(lines)))
    lines = small_csv(x, r).splitlines()
    lines[8] = lines[8].replace("300.0", "warm")
    with pytest.raises(ReferenceError, match=r"line 9, column 7 \('T'\): non-numeric value 'warm'"):
        read_axisym_csv(write(tmp_path, "\n".join(lines)))
    with pytest.raises(ReferenceError, match="3-D export"):
        read_axisym_csv(write(tmp_path, small_csv(x, r, ",z", [",0"] * x.size)))


@pytest.mark.parametrize("case", ["cd_nozzle_inviscid", "cd_nozzle"])
def test_real_axisym_gives_the_fluent_node_set(case, shared_path):
    f = read_axisym_csv(shared_path("reference", case, "axisym_cells.csv"))
    fl = read_fluent_csv(shared_path("reference", case, "fluent_export_3d.csv"))
    assert f.n_nodes == 63539
    np.testing.assert_array_equal(f.points_m, fl.points_m)
    # same solution: away from the wall layer the interpolants agree closely
    r = np.hypot(fl.points_m[:, 1], fl.points_m[:, 2])
    core = r < 0.6
    np.testing.assert_allclose(f.velocity_m_s[core], fl.velocity_m_s[core], atol=0.05)
    np.testing.assert_allclose(f.pressure_gauge_pa, fl.pressure_gauge_pa, atol=1.0)
