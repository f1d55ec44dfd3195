"""Specification of the VTK/VTU importer (meshio), including the axisymmetric-wedge revolve."""


import meshio
import numpy as np
import pytest

from fisc_ground.reference.analytic import body_lattice
from fisc_ground.reference.field import P_REF_PA, ReferenceError
from fisc_ground.reference.fluent_csv import read_fluent_csv
from fisc_ground.reference.vtk import read_vtk





def box_mesh(n=3):
    """A 3-D block of (n-1)^3 hexahedra spanning [0,2] x [-1,1] x [-1,1]."""
    g = np.linspace(0.0, 1.0, n)
    X, Y, Z = np.meshgrid(2 * g, 2 * g - 1, 2 * g - 1, indexing="ij")
    pts = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    idx = np.arange(n ** 3).reshape(n, n, n)
    c = idx[:-1, :-1, :-1].ravel()
    s1, s2 = n * n, n
    hexes = np.column_stack([c, c + s1, c + s1 + s2, c + s2,
                             c + 1, c + s1 + 1, c + s1 + s2 + 1, c + s2 + 1])
    return pts, hexes


def test_3d_cell_data_uses_centroids_and_converts_absolute_pressure(tmp_path):
    pts, hexes = box_mesh()
    cent = pts[hexes].mean(axis=1)
    U = np.column_stack([1 + cent[:, 0], cent[:, 1], -cent[:, 2]])
    p = P_REF_PA + 5.0 * cent[:, 0]
    mesh = meshio.Mesh(pts, [("hexahedron", hexes)],
                       cell_data={"U": [U], "p": [p], "rho": [np.full(8, 1.2)]})
    path = tmp_path / "box.vtu"
    mesh.write(path)
    f = read_vtk(path)
    assert f.extras["data_location"] == "cell" and "revolved" not in f.extras
    np.testing.assert_allclose(f.points_m, cent)
    np.testing.assert_allclose(f.velocity_m_s, U)
    assert f.pressure_kind == "absolute"
    np.testing.assert_allclose(f.pressure_gauge_pa, 5.0 * cent[:, 0], atol=1e-9)
    np.testing.assert_allclose(f.density_kg_m3, 1.2)
    # explicit gauge keeps the numbers
    g = read_vtk(path, pressure_kind="gauge")
    np.testing.assert_allclose(g.pressure_gauge_pa, p)


def test_3d_point_data_and_alternative_names(tmp_path):
    pts, hexes = box_mesh()
    mesh = meshio.Mesh(pts, [("hexahedron", hexes)],
                       point_data={"Velocity": pts * 2.0, "Pressure": pts[:, 0] - 3.0})
    path = tmp_path / "pd.vtk"
    mesh.write(path, binary=False)
    f = read_vtk(path)
    assert f.extras["data_location"] == "point" and f.pressure_kind == "gauge"
    np.testing.assert_allclose(f.points_m, pts)
    np.testing.assert_allclose(f.velocity_m_s, pts * 2.0)
    assert f.density_kg_m3 is None


def test_bad_vtk_inputs(tmp_path):
    pts, hexes = box_mesh()
    path = tmp_path / "nofields.vtu"
    meshio.Mesh(pts, [("hexahedron", hexes)], cell_data={"T": [np.ones(8)]}).write(path)
    with pytest.raises(ReferenceError, match=r"nofields\.vtu: no velocity .* and pressure"):
        read_vtk(path)
    U = np.ones((8, 3))
    U[5, 1] = np.nan
    path = tmp_path / "nan.vtu"
    meshio.Mesh(pts, [("hexahedron", hexes)], cell_data={"U": [U], "p": [np.zeros(8)]}).write(path)
    with pytest.raises(ReferenceError,
                       match=r"nan\.vtu: cell data 'U': non-finite value at cell 5"):
        read_vtk(path)
    garbage = tmp_path / "garbage.vtu"
    garbage.write_text("this is not xml")
    with pytest.raises(ReferenceError, match=r"garbage\.vtu: cannot read as VTK"):
        read_vtk(garbage)
    with pytest.raises(ReferenceError, match="file not found"):
        read_vtk(tmp_path / "missing.vtu")


def wedge_mesh(length=1.0, radius=0.5, nx=20, nr=8, half_angle_deg=2.5):
    """An OpenFOAM-like annular wedge (hexahedra, r from 0.02 to R), wall vertices at y = R."""
    t = np.tan(np.radians(half_angle_deg))
    xs = np.linspace(0.0, length, nx + 1)
    rs = np.linspace(0.02, radius, nr + 1)
    X, Rr, S = np.meshgrid(xs, rs, [-1.0, 1.0], indexing="ij")
    pts = np.column_stack([X.ravel(), Rr.ravel(), (S * Rr * t).ravel()])
    idx = np.arange(pts.shape[0]).reshape(nx + 1, nr + 1, 2)
    a = idx[:-1, :-1, 0].ravel()
    b = idx[1:, :-1, 0].ravel()
    c = idx[1:, 1:, 0].ravel()
    d = idx[:-1, 1:, 0].ravel()
    hexes = np.column_stack([a, b, c, d, a + 1, b + 1, c + 1, d + 1])
    return pts, hexes


def test_synthetic_wedge_is_revolved(tmp_path):
    pts, hexes = wedge_mesh()
    cent = pts[hexes].mean(axis=1)
    r = np.hypot(cent[:, 1], cent[:, 2])
    u_r = 0.1 * r
    U = np.column_stack([1.0 + cent[:, 0], u_r * cent[:, 1] / r, u_r * cent[:, 2] / r])
    mesh = meshio.Mesh(pts, [("hexahedron", hexes)],
                       cell_data={"U": [U], "p": [P_REF_PA + 10.0 * cent[:, 0]]})
    path = tmp_path / "wedge.vtu"
    mesh.write(path)
    f = read_vtk(path)
    assert f.extras["revolved"] and f.extras["sector_span_deg"] == pytest.approx(5.0)
    assert f.pressure_kind == "absolute"
    lattice = body_lattice(0.0, 1.0, lambda q: np.full(np.shape(q), 0.5))
    np.testing.assert_array_equal(f.points_m, lattice)
    X, Y, Z = f.points_m.T
    R = np.hypot(Y, Z)
    inside = (X >= 0.025) & (X <= 0.975) & (R >= 0.05) & (R <= 0.45)
    np.testing.assert_allclose(f.velocity_m_s[inside, 0], 1.0 + X[inside], atol=1e-9)
    np.testing.assert_allclose(f.velocity_m_s[inside, 1], 0.1 * Y[inside], atol=1e-6)
    np.testing.assert_allclose(f.pressure_gauge_pa[inside], 10.0 * X[inside], atol=1e-6)


@pytest.mark.parametrize("case", ["cd_nozzle_inviscid", "cd_nozzle"])
def test_real_openfoam_wedge(case, shared_path):
    f = read_vtk(shared_path("reference", case, "openfoam_internal.vtu"))
    fl = read_fluent_csv(shared_path("reference", case, "fluent_export_3d.csv"))
    assert f.extras["revolved"] and f.extras["axisym_points"] == 18000
    assert f.pressure_kind == "absolute"  # OpenFOAM's p, detected and converted
    np.testing.assert_array_equal(f.points_m, fl.points_m)  # same lattice node set
    # float32 absolute pressure: gauge agrees with the CSV to ~1 Pa (boundary half-cells)
    np.testing.assert_allclose(f.pressure_gauge_pa, fl.pressure_gauge_pa, atol=1.0)
    r = np.hypot(fl.points_m[:, 1], fl.points_m[:, 2])
    core = r < 0.6
    np.testing.assert_allclose(f.velocity_m_s[core], fl.velocity_m_s[core], atol=0.05)


def test_damaged_or_sparse_vtu_gives_a_message_not_an_empty_read_error(tmp_path):
    """meshio raises ReadError('') on a cut-off XML file; a sparse file is refused before meshio."""
    cut = tmp_path / "cut.vtu"
    cut.write_text('<?xml version="1.0"?>\n<VTKFile type="UnstructuredGrid">')
    with pytest.raises(ReferenceError, match=r"cut\.vtu: cannot read as VTK: ReadError: meshio gave no details"):
        read_vtk(cut)
    zeros = tmp_path / "zeros.vtu"
    zeros.write_bytes(b"\0" * 4096)
    with pytest.raises(ReferenceError, match=r"zeros\.vtu: cannot read as VTK: not a VTU file"):
        read_vtk(zeros)
