"""``fisc-sim sweep``: the spec, the grid, and a 2-worker dask LocalCluster giving the serial numbers."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest

from sim.sweep.spec import METRICS, SweepSpecError, load_spec, parse_spec, rows_equal, run_serial

SPEC = """
[base]
scenario = "seed"
duration_s = 2.0
agents = 120
max_speed_m_s = 2.0

[grid]
map = ["cd_nozzle_inviscid", "case.py:small_duct"]
configuration = [
    { label = "paper", preset = "paper" },
    { label = "slot:0.5", mode = "slot", lookahead_s = 0.5 },
]
seed = [0, 1]
"""

CASE = """
import numpy as np
from fisc_ground.reference.analytic import analytic_nozzle

def small_duct():
    return analytic_nozzle(lambda x: 1.0 + 0.2 * np.cos(np.pi * np.asarray(x) / 6.0), length_m=6.0,
                           inlet_velocity_m_s=2.0, name="small_duct")
"""


@pytest.fixture
def spec_file(tmp_path: Path) -> Path:
    (tmp_path / "case.py").write_text(CASE)
    path = tmp_path / "spec.toml"
    path.write_text(SPEC)
    return path


def test_grid_is_the_product_in_spec_order(spec_file):
    spec = load_spec(spec_file)
    points = spec.points()
    assert len(points) == 2 * 2 * 2
    assert [dict(p.labels)["seed"] for p in points[:2]] == [0, 1]  # the last dimension varies fastest
    assert dict(points[0].labels) == {"map": "cd_nozzle_inviscid", "configuration": "paper", "seed": 0}
    assert points[2].run["mode"] == "slot" and points[2].run["lookahead_s"] == 0.5
    assert points[4].run["map"] == f"{spec_file.parent / 'case.py'}:small_duct"  # resolved beside the spec
    assert all(p.run["figures"] is False for p in points)


@pytest.mark.parametrize("text, needle", [
    ("[grid]\nmode = []", "non-empty list"),
    ("[grid]\nmodes = ['slot']", "'modes' is not a RunConfig field"),
    ("[base]\nscenario = 'wind'", "scenario 'wind'"),
    ("[grid.fit]\ncell_size = [0.5]", "'fit.cell_size' is not a FitConfig field"),
    ("[other]\nx = 1", "unknown table"),
])
def test_bad_specs_name_the_key(text, needle):
    import tomllib

    with pytest.raises(SweepSpecError, match=needle.replace("[", r"\[").replace("(", r"\(")):
        parse_spec(tomllib.loads(text))


def test_fit_settings_reach_the_map(tmp_path):
    import tomllib

    from sim.sweep.spec import point_map

    spec = parse_spec(tomllib.loads('[grid]\npreset = ["paper"]\n[grid.fit]\ncell_size_m = [0.5, 1.0]'))
    sizes = [point_map(p).cell_size_m for p in spec.points()]
    assert sizes == [0.5, 1.0]


@pytest.mark.slow
def test_two_worker_local_cluster_gives_the_serial_numbers(spec_file, tmp_path):
    from dask.distributed import Client

    from sim.sweep.run import local_cluster, run_distributed, write_outputs

    spec = load_spec(spec_file)
    serial = run_serial(spec)
    seen = []
    with local_cluster(2) as cluster:
        with Client(cluster) as client:
            assert len(client.scheduler_info()["workers"]) == 2
            rows = run_distributed(spec, client, progress=lambda done, total: seen.append((done, total)))
        # the CLI on "any cluster": --scheduler ADDRESS of a running scheduler
        from sim.cli import main

        assert main(["sweep", str(spec_file), "-o", str(tmp_path / "cli"), "--scheduler", cluster.scheduler_address,
                     "-q", "--no-figures"]) == 0
    with open(tmp_path / "cli" / "results.csv") as fh:
        via_cli = list(csv.DictReader(fh))
    assert [float(r["nrmse_velocity"]) for r in via_cli] == pytest.approx([r["nrmse_velocity"] for r in serial],
                                                                           rel=1e-12)
    assert seen[-1] == (8, 8)
    assert [r["index"] for r in rows] == list(range(8))
    assert all(math.isfinite(r["nrmse_velocity"]) and r["injected"] == 120 for r in rows)
    assert len({r["nrmse_velocity"] for r in rows}) > 4  # the configurations really differ
    assert rows_equal(serial, rows)
    changed = [dict(r) for r in rows]
    changed[3]["nrmse_pressure"] *= 1.0 + 1e-9
    assert not rows_equal(serial, changed)  # the comparison can fail

    paths = write_outputs(spec, rows, tmp_path / "out")
    with open(paths["table"]) as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 8 and float(table[5]["nrmse_density"]) == pytest.approx(rows[5]["nrmse_density"], rel=1e-12)
    for metric in METRICS:
        assert paths[metric].stat().st_size > 1000


@pytest.mark.slow
def test_cli_sweep_writes_table_and_figures(spec_file, tmp_path):
    from sim.cli import main

    out = tmp_path / "o"
    assert main(["sweep", str(spec_file), "-o", str(out), "--serial", "-q", "--no-figures"]) == 0
    assert (out / "results.csv").read_text().count("\n") == 9 and (out / "sweep.json").exists()
    bad = tmp_path / "bad.toml"
    bad.write_text("[grid]\nmode = ['warp']\n")
    assert main(["sweep", str(bad), "-o", str(out)]) == 2


def test_fit_settings_on_a_ready_made_map_are_refused(tmp_path):
    import tomllib

    with pytest.raises(SweepSpecError, match="ready-made map"):
        parse_spec(tomllib.loads('[base]\nmap = "x.fiscmap"\n[grid.fit]\ncell_size_m = [0.5]'))


def test_parquet_needs_pandas_and_pyarrow_or_is_written(spec_file, tmp_path, capsys):
    import importlib.util

    from sim.cli import main

    have = all(importlib.util.find_spec(m) is not None for m in ("pandas", "pyarrow"))
    spec = tmp_path / "one.toml"
    spec.write_text('[base]\nscenario = "seed"\nduration_s = 0.5\nagents = 20\n[grid]\nseed = [0]\n')
    rc = main(["sweep", str(spec), "-o", str(tmp_path / "pq"), "--serial", "-q", "--no-figures", "--parquet"])
    if have:
        assert rc == 0 and (tmp_path / "pq" / "results.parquet").stat().st_size > 0
    else:
        assert rc == 1 and "pip install pandas pyarrow" in capsys.readouterr().err
        assert not (tmp_path / "pq").exists()  # refused before any run
