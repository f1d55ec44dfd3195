"""Specification of the Fluent-style CSV importer (read_fluent_csv)."""


import numpy as np
import pytest

from fisc_ground.reference.field import P_REF_PA, ReferenceError
from fisc_ground.reference.fluent_csv import read_fluent_csv

HEADER = ("nodenumber, x-coordinate, y-coordinate, z-coordinate, pressure, density, "
          "x-velocity, y-velocity, z-velocity")
ROWS = [
    (1, 0.0, 0.0, 0.0, 10.0, 1.17, 3.0, 0.1, 0.2),
    (2, 0.0, 0.1, 0.0, 11.0, 1.18, 3.1, 0.0, 0.0),
    (3, 0.1, 0.0, 0.1, -5.0, 1.16, 3.2, -0.1, 0.3),
    (4, 0.1, 0.1, 0.1, -6.0, 1.15, 3.3, 0.2, -0.2),
]


def write(tmp_path, text, name="f.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def canonical(tmp_path):
    body = "\n".join(", ".join(str(v) for v in r) for r in ROWS)
    return write(tmp_path, HEADER + "\n" + body + "\n", "canonical.csv")




def test_reads_canonical_layout(tmp_path):
    f = read_fluent_csv(canonical(tmp_path))
    a = np.array(ROWS)
    assert f.n_nodes == 4
    np.testing.assert_array_equal(f.points_m, a[:, 1:4])
    np.testing.assert_array_equal(f.velocity_m_s, a[:, 6:9])
    np.testing.assert_array_equal(f.pressure_gauge_pa, a[:, 4])
    np.testing.assert_array_equal(f.density_kg_m3, a[:, 5])
    assert f.pressure_kind == "gauge"
    assert f.name == "canonical" and len(f.source_sha256) == 64


def test_shuffled_columns_whitespace_extra_columns_no_nodenumber(tmp_path):
    ref = read_fluent_csv(canonical(tmp_path))
    header = ("  Z-Velocity ,Static-Pressure,  X-COORDINATE , temperature, Y-Velocity,"
              "z-coordinate,x-velocity , y-coordinate  ")
    lines = [header]
    for r in ROWS:
        lines.append(f"  {r[8]} ,  {r[4]},{r[1]}   ,  300.0 , {r[7]},{r[3]} ,{r[6]},   {r[2]}")
    f = read_fluent_csv(write(tmp_path, "\n".join(lines) + "\n\n"))
    np.testing.assert_array_equal(f.points_m, ref.points_m)
    np.testing.assert_array_equal(f.velocity_m_s, ref.velocity_m_s)
    np.testing.assert_array_equal(f.pressure_gauge_pa, ref.pressure_gauge_pa)
    assert f.density_kg_m3 is None  # density is optional


def test_whitespace_separated_file(tmp_path):
    ref = read_fluent_csv(canonical(tmp_path))
    text = HEADER.replace(",", " ") + "\n" + "\n".join(" ".join(str(v) for v in r) for r in ROWS)
    f = read_fluent_csv(write(tmp_path, text))
    np.testing.assert_array_equal(f.velocity_m_s, ref.velocity_m_s)


def test_absolute_pressure_column_and_auto_detection_give_same_gauge(tmp_path):
    ref = read_fluent_csv(canonical(tmp_path))
    rows = "\n".join(", ".join(str(v) for v in (*r[:4], r[4] + P_REF_PA, *r[5:])) for r in ROWS)
    abs_named = read_fluent_csv(write(tmp_path, HEADER.replace("pressure", "absolute-pressure")
                                      + "\n" + rows, "a.csv"))
    auto = read_fluent_csv(write(tmp_path, HEADER + "\n" + rows, "b.csv"), pressure_kind="auto")
    explicit = read_fluent_csv(tmp_path / "b.csv", pressure_kind="absolute")
    gauge_auto = read_fluent_csv(canonical(tmp_path), pressure_kind="auto")
    for f in (abs_named, auto, explicit):
        assert f.pressure_kind == "absolute"
        np.testing.assert_allclose(f.pressure_gauge_pa, ref.pressure_gauge_pa, atol=1e-9)
    assert gauge_auto.pressure_kind == "gauge"
    np.testing.assert_array_equal(gauge_auto.pressure_gauge_pa, ref.pressure_gauge_pa)
    with pytest.raises(ReferenceError, match="pressure_kind"):
        read_fluent_csv(canonical(tmp_path), pressure_kind="relative")


def bad(tmp_path, rows, header=HEADER):
    body = "\n".join(", ".join(str(v) for v in r) for r in rows)
    return write(tmp_path, header + "\n" + body + "\n", "bad.csv")


def test_missing_columns_are_named(tmp_path):
    p = bad(tmp_path, [r[:8] for r in ROWS], header=HEADER.rsplit(",", 1)[0])
    with pytest.raises(ReferenceError) as e:
        read_fluent_csv(p)
    msg = str(e.value)
    assert str(p) in msg and "line 1" in msg and "z-velocity" in msg and "x-velocity," not in msg
    p = bad(tmp_path, [(r[0], *r[1:4], *r[5:]) for r in ROWS],
            header=HEADER.replace(" pressure,", ""))
    with pytest.raises(ReferenceError, match="missing required column.*pressure"):
        read_fluent_csv(p)


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "NaN"])
def test_non_finite_value_names_line_and_column(tmp_path, value):
    rows = [list(r) for r in ROWS]
    rows[2][6] = value  # third data row = line 4, x-velocity = column 7
    with pytest.raises(ReferenceError) as e:
        read_fluent_csv(bad(tmp_path, rows))
    msg = str(e.value)
    assert "bad.csv" in msg and "line 4" in msg and "column 7" in msg and "x-velocity" in msg


def test_non_numeric_cell_names_line_column_and_text(tmp_path):
    rows = [list(r) for r in ROWS]
    rows[1][4] = "12.5Pa"
    with pytest.raises(ReferenceError) as e:
        read_fluent_csv(bad(tmp_path, rows))
    msg = str(e.value)
    assert "line 3" in msg and "column 5" in msg and "'pressure'" in msg and "'12.5Pa'" in msg


def test_empty_cell_and_wrong_cell_count(tmp_path):
    rows = [list(r) for r in ROWS]
    rows[0][8] = ""
    with pytest.raises(ReferenceError, match=r"line 2, column 9 .*empty cell"):
        read_fluent_csv(bad(tmp_path, rows))
    rows = [list(r) for r in ROWS]
    rows[3] = rows[3][:7]
    with pytest.raises(ReferenceError, match=r"line 5: 7 cells but the header has 9"):
        read_fluent_csv(bad(tmp_path, rows))


def test_line_numbers_count_blank_lines(tmp_path):
    rows = [", ".join(str(v) for v in r) for r in ROWS]
    rows[3] = rows[3].replace("3.3", "oops")
    text = HEADER + "\n" + rows[0] + "\n\n   \n" + "\n".join(rows[1:]) + "\n"
    with pytest.raises(ReferenceError, match=r"line 7, column 7 .*'oops'"):
        read_fluent_csv(write(tmp_path, text))


def test_empty_and_header_only(tmp_path):
    with pytest.raises(ReferenceError, match="empty file"):
        read_fluent_csv(write(tmp_path, "", "e.csv"))
    with pytest.raises(ReferenceError, match="empty file"):
        read_fluent_csv(write(tmp_path, "\n  \n", "e2.csv"))
    with pytest.raises(ReferenceError, match=r"h\.csv: header only"):
        read_fluent_csv(write(tmp_path, HEADER + "\n\n", "h.csv"))
    with pytest.raises(ReferenceError, match="file not found"):
        read_fluent_csv(tmp_path / "nope.csv")


def test_duplicate_points_name_both_lines(tmp_path):
    rows = [list(r) for r in ROWS] + [[5, 0.1, 0.0, 0.1, 1, 1, 1, 1, 1],
                                      [6, 0.0, 0.0, 0.0, 1, 1, 1, 1, 1]]
    # lines: header 1, rows 2..7; row 6 (line 6) repeats line 4, row 7 repeats line 2
    with pytest.raises(ReferenceError) as e:
        read_fluent_csv(bad(tmp_path, rows))
    assert "duplicate point" in str(e.value) and "lines 4 and 6" in str(e.value)


def test_2d_file_is_recognised(tmp_path):
    rows = [list(r) for r in ROWS]
    for r in rows:
        r[3] = 0.0
    rows[1][2] = 0.2
    rows[3][2] = 0.3
    with pytest.raises(ReferenceError) as e:
        read_fluent_csv(bad(tmp_path, rows))
    assert "looks 2-D" in str(e.value) and "read_axisym_csv" in str(e.value)
    header2d = "x-coordinate, y-coordinate, pressure, x-velocity, y-velocity"
    p = write(tmp_path, header2d + "\n0, 0, 1, 2, 3\n0, 1, 1, 2, 3\n", "two_d.csv")
    with pytest.raises(ReferenceError) as e:
        read_fluent_csv(p)
    assert "z-coordinate" in str(e.value) and "looks 2-D" in str(e.value)


@pytest.mark.parametrize("case", ["cd_nozzle_inviscid", "cd_nozzle"])
def test_real_export(case, shared_path):
    f = read_fluent_csv(shared_path("reference", case, "fluent_export_3d.csv"))
    assert f.n_nodes == 63539
    assert f.pressure_kind == "gauge" and f.density_kg_m3 is not None
    assert np.all(np.isfinite(f.velocity_m_s))
    # lattice layout: 0.1 m spacing from x = 0 to the outlet plane x = 15, axis nodes present
    assert f.points_m[:, 0].min() == 0.0 and f.points_m[:, 0].max() == 15.0
    assert np.any(np.all(f.points_m[:, 1:] == 0.0, axis=1))
    # inlet velocity 3.38 m/s
    inlet = f.points_m[:, 0] == 0.0
    np.testing.assert_allclose(f.velocity_m_s[inlet, 0].mean(), 3.38, rtol=1e-3)


def test_trailing_comma_on_some_rows_only(tmp_path):
    ref = read_fluent_csv(canonical(tmp_path))
    rows = [", ".join(str(v) for v in r) for r in ROWS]
    rows[1] += ","
    f = read_fluent_csv(write(tmp_path, HEADER + "\n" + "\n".join(rows) + "\n"))
    np.testing.assert_array_equal(f.velocity_m_s, ref.velocity_m_s)
    np.testing.assert_array_equal(f.points_m, ref.points_m)
