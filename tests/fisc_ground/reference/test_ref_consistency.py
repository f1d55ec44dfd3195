"""The three CFD sources of one solution (Fluent CSV, axisymmetric CSV, OpenFOAM VTU), the
built-in and the analytic reference describe the same flow."""


import numpy as np
import pytest

from fisc_ground.reference.analytic import analytic_nozzle
from fisc_ground.reference.axisym import read_axisym_csv
from fisc_ground.reference.builtin import load_builtin
from fisc_ground.reference.fluent_csv import read_fluent_csv
from fisc_ground.reference.vtk import read_vtk

@pytest.fixture(scope="module")
def sources(shared_path):
    case = ("reference", "cd_nozzle_inviscid")
    return {"fluent": read_fluent_csv(shared_path(*case, "fluent_export_3d.csv")),
            "axisym": read_axisym_csv(shared_path(*case, "axisym_cells.csv")),
            "vtu": read_vtk(shared_path(*case, "openfoam_internal.vtu")),
            "builtin": load_builtin("cd_nozzle_inviscid"),
            "analytic": analytic_nozzle()}


def slice_mean(f, x, comp=0):
    return float(f.velocity_m_s[f.points_m[:, 0] == x, comp].mean())


def occupied_cubes(f, l=0.5):
    """Number of distinct l-cubes holding nodes (x from the inlet, axis on faces)."""
    idx = np.floor((f.points_m - [f.points_m[:, 0].min(), 0.0, 0.0]) / l).astype(int)
    return np.unique(idx, axis=0).shape[0]


def test_same_node_set_everywhere(sources):
    ref = sources["fluent"].points_m
    for name, f in sources.items():
        np.testing.assert_array_equal(f.points_m, ref, err_msg=name)
    counts = {n: occupied_cubes(f) for n, f in sources.items()}
    assert len(set(counts.values())) == 1, counts


@pytest.mark.parametrize("x", [2.0, 6.0, 10.0, 13.0])
def test_mean_axial_velocity_per_slice_agrees(sources, x):
    ref = slice_mean(sources["fluent"], x)
    for name in ("axisym", "vtu", "builtin"):
        assert slice_mean(sources[name], x) == pytest.approx(ref, rel=0.01), name
    # quasi-1-D theory: within a few % of the CFD lattice-slice mean
    assert slice_mean(sources["analytic"], x) == pytest.approx(ref, rel=0.03)


def test_throat_matches_readme(sources):
    # README: throat mean axial velocity 13.5296 m/s
    for name, f in sources.items():
        assert slice_mean(f, 6.0) == pytest.approx(13.53, rel=0.01), name


def test_pressure_drop_to_throat_agrees(sources):
    def throat_drop(f):
        p = f.pressure_gauge_pa
        x = f.points_m[:, 0]
        return p[x == 0.0].mean() - p[x == 6.0].mean()

    ref = throat_drop(sources["fluent"])
    for name, f in sources.items():
        assert throat_drop(f) == pytest.approx(ref, rel=0.05), name
