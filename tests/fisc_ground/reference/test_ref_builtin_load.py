"""Built-in references (package data, no ../shared needed) and the load_reference dispatcher."""

import subprocess
import sys

import numpy as np
import pytest

from fisc_ground.reference.builtin import DEFAULT_BUILTIN, builtin_names, load_builtin
from fisc_ground.reference.field import ReferenceError
from fisc_ground.reference.fluent_csv import read_fluent_csv
from fisc_ground.reference.load import load_reference



def test_names():
    assert builtin_names() == ("cd_nozzle_inviscid", "cd_nozzle", "analytic")
    assert DEFAULT_BUILTIN == "cd_nozzle_inviscid"


@pytest.mark.parametrize("name", ["cd_nozzle_inviscid", "cd_nozzle"])
def test_cfd_builtins_load_from_package_data(name):
    f = load_builtin(name)
    assert f.name == name and f.source == f"builtin:{name}"
    assert f.n_nodes == 63539 and f.pressure_kind == "gauge"
    assert f.points_m.dtype == np.float64 and f.density_kg_m3 is not None
    assert len(f.source_sha256) == 64 and f.extras["origin"] == f"{name}/fluent_export_3d.csv"
    assert np.all(np.isfinite(f.velocity_m_s)) and np.all(np.isfinite(f.pressure_gauge_pa))


def test_separated_rans_case_keeps_reversed_flow_nodes():
    rans = load_builtin("cd_nozzle")
    rev = rans.velocity_m_s[:, 0] < 0.0
    assert rev.sum() > 100
    # reversed flow sits near the diverging wall (x = 10.5 .. 14.8 m)
    assert rans.points_m[rev, 0].min() > 10.0
    assert not np.any(load_builtin("cd_nozzle_inviscid").velocity_m_s[:, 0] < 0.0)


@pytest.mark.parametrize("name", ["cd_nozzle_inviscid", "cd_nozzle"])
def test_builtin_equals_its_source_csv(name, shared_path):
    csv = shared_path("reference", name, "fluent_export_3d.csv")
    b, f = load_builtin(name), read_fluent_csv(csv)
    assert b.source_sha256 == f.source_sha256
    for a, c in ((b.points_m, f.points_m), (b.velocity_m_s, f.velocity_m_s),
                 (b.pressure_gauge_pa, f.pressure_gauge_pa), (b.density_kg_m3, f.density_kg_m3)):
        np.testing.assert_array_equal(a, c)


def test_builtins_work_without_shared(tmp_path):
    # a fresh interpreter in an unrelated directory: only the installed package data is used
    code = ("from fisc_ground.reference.builtin import load_builtin;"
            "f = load_builtin('cd_nozzle_inviscid'); print(f.n_nodes)")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                         text=True, check=True)
    assert out.stdout.strip() == "63539"


def test_analytic_builtin():
    f = load_builtin("analytic")
    assert f.source == "builtin:analytic" and f.n_nodes == 63539


def test_unknown_builtin_lists_known_names():
    with pytest.raises(ReferenceError) as e:
        load_builtin("cd_nozle")
    assert "cd_nozle" in str(e.value)
    for n in builtin_names():
        assert n in str(e.value)
    with pytest.raises(ReferenceError, match="cd_nozzle_inviscid"):
        load_reference("builtin:nope")


def test_load_reference_dispatch(tmp_path):
    assert load_reference("cd_nozzle").name == "cd_nozzle"
    assert load_reference("builtin:analytic").name == "analytic"
    fl = tmp_path / "three_d.csv"
    fl.write_text("x-coordinate,y-coordinate,z-coordinate,pressure,"
                  "x-velocity,y-velocity,z-velocity\n"
                  "0,0,0,101400,1,0,0\n0,0,1,101300,1,0,0\n")
    f = load_reference(fl)
    assert f.extras["format"] == "fluent-csv"
    assert f.pressure_kind == "absolute"  # load_reference defaults to 'auto'
    np.testing.assert_allclose(f.pressure_gauge_pa, [75.0, -25.0])
    assert load_reference(fl, pressure_kind="gauge").pressure_gauge_pa[0] == 101400.0
    ax = tmp_path / "two_d.csv"
    rows = ["x,r,u_x,u_r,p"] + [f"{(i + 0.5) * 0.1},{(j + 0.5) * 0.1},1,0,0"
                                for i in range(10) for j in range(5)]
    ax.write_text("\n".join(rows) + "\n")
    g = load_reference(str(ax))
    assert g.extras["format"] == "axisym-csv" and g.density_kg_m3 is None
    np.testing.assert_allclose(g.velocity_m_s[:, 0], 1.0)


def test_load_reference_errors(tmp_path):
    with pytest.raises(ReferenceError, match=r"missing\.csv: file not found"):
        load_reference(tmp_path / "missing.csv")
    with pytest.raises(ReferenceError, match="not a built-in either"):
        load_reference("no_such_reference")
    odd = tmp_path / "field.xlsx"
    odd.write_bytes(b"PK")
    with pytest.raises(ReferenceError, match=r"unsupported file type '\.xlsx'"):
        load_reference(odd)
