"""``benchmarks/density_profile.py``: the slice-by-slice density diagnostic quoted in docs/simulation.md."""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from fisc_ground.mapbuild import default_map_path
from fisc_ground.mapwrite import write_map
from sim.run import RunConfig, run
from sim.scenarios import synthetic_tunnel_map

ROOT = Path(__file__).resolve().parents[2]


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses resolve their annotations through it
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def tool():
    return _load("density_profile", ROOT / "benchmarks" / "density_profile.py")


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    """The default map flown briefly (its figures are not the default run's, only consistent)."""
    out = tmp_path_factory.mktemp("run")
    run(RunConfig(out_dir=str(out), figures=False, duration_s=40.0, average_window_s=20.0))
    return out / "fields.csv"


def test_the_diagnostic_agrees_with_the_independent_fidelity_check(tool, short_run):
    checker = _load("fidelity_check", ROOT / "tests" / "sim" / "fidelity_check.py")
    mine = checker.fidelity_from_csv(str(short_run))
    p = tool.density_profile(short_run, default_map_path())
    assert p.realised.nrmse == pytest.approx(mine["nrmse_density"], abs=1e-9)
    assert p.realised.pearson == pytest.approx(mine["pearson_density"], abs=1e-9)
    # one row per axial slice of the 15 m tunnel (l = 0.5 m); every compared CV in one wall class
    assert p.x_m.size == 30 and np.all(np.diff(p.x_m) > 0)
    assert int(p.n_cv.sum()) == mine["n_density"] == sum(n for n, _, _ in p.classes.values())
    # the design is flat within its slices, so giving the run the design's slice profile keeps its scatter
    assert 0 < p.within_slice_sd < 1 and p.design_score.pearson > 0.9
    # the swarm's axial velocity tracks the field's within 20 % in every slice (steady number flux)
    assert np.all(np.abs(p.u_swarm_m_s / p.u_field_m_s - 1) < 0.2)
    # ideal tracers in the same field keep the design (every class within 5 %); holding each command
    # for the 20 Hz interval empties the cubes behind the outward steps
    assert p.tracer_pearson[0] > 0.95 and p.tracer_pearson[1] < p.tracer_pearson[0]
    assert all(abs(exact - 1) < 0.05 for exact, _ in p.tracer_classes.values())
    assert p.tracer_classes["closed upstream face"][1] < 0.7
    assert -1 <= p.swarm_pearson <= 1
    md = tool.markdown(p)
    assert "| closed upstream face |" in md and "exact tracers / designed" in md


def test_a_schema_1_map_or_another_maps_fields_are_refused_by_name(tool, short_run, tmp_path, capsys):
    cmap = synthetic_tunnel_map(nx=12)
    v1 = tmp_path / "v1.fiscmap"
    write_map(v1, {k: v for k, v in cmap.body.items() if k not in ("arrays", "schema", "schema_version")},
              {k: np.asarray(v) for k, v in cmap.arrays.items()})
    assert tool.main([str(short_run), "--map", str(v1)]) == 2
    assert "schema-1 map has no designed density" in capsys.readouterr().err
    bad = tmp_path / "fields.csv"
    bad.write_text(short_run.read_text().replace("swarm_density,", "swarm_dens,", 1))
    assert tool.main([str(bad)]) == 2
    assert "missing column(s) swarm_density" in capsys.readouterr().err
    rows = short_run.read_text().splitlines()
    rows[3] = rows[3].replace(",", ",x", 1)  # the cv_x cell of the third CV
    bad.write_text("\n".join(rows) + "\n")
    assert tool.main([str(bad)]) == 2
    assert "line 4, column cv_x: 'x" in capsys.readouterr().err
    bad.write_text("\n".join(short_run.read_text().splitlines()[:-1]) + "\n")  # one CV short: another map's
    assert tool.main([str(bad)]) == 2
    assert "(another map?)" in capsys.readouterr().err
