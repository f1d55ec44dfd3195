"""``fisc-sim run`` end to end on a small synthetic map: outputs, columns, keys, reproducibility."""

import csv
import json

import numpy as np
import pytest

from fisc_ground.mapwrite import write_map
from sim.cli import main
from sim.run import RunConfig, simulate
from sim.scenarios import synthetic_tunnel_map

REQUIRED_COLUMNS = {"cv_x", "cv_y", "cv_z", "target_u_axial", "target_pressure", "target_density", "swarm_u_axial",
                    "swarm_pressure", "swarm_density", "swarm_temperature", "samples"}
REQUIRED_KEYS = {"nrmse_velocity", "nrmse_pressure", "nrmse_density", "centreline_max_dev_velocity",
                 "centreline_max_dev_pressure", "centreline_max_dev_density", "pearson_velocity", "pearson_pressure",
                 "pearson_density", "n_cv", "agents", "steps", "wall_time_s", "agent_steps_per_s", "config"}


@pytest.fixture(scope="module")
def map_file(tmp_path_factory):
    cmap = synthetic_tunnel_map(nx=12)
    path = tmp_path_factory.mktemp("maps") / "small.fiscmap"
    write_map(path, {k: v for k, v in cmap.body.items() if k not in ("arrays", "schema", "schema_version")},
              {k: np.asarray(v) for k, v in cmap.arrays.items()})
    return path


@pytest.mark.parametrize("scenario, extra", [("reservoir", []), ("seed", ["--mode", "slot", "--collisions"])])
def test_cli_run_writes_all_outputs(tmp_path, map_file, scenario, extra):
    out = tmp_path / "run"
    rc = main(["run", "--map", str(map_file), "--scenario", scenario, "--duration", "8", "--average-window", "4",
               "--seed", "3", "-q", "-o", str(out), *extra])
    assert rc == 0
    with open(out / "fields.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert REQUIRED_COLUMNS <= set(rows[0]) and len(rows) == 12 * 12
    m = json.loads((out / "metrics.json").read_text())
    assert REQUIRED_KEYS <= set(m)
    a = m["agents"]
    assert a["injected"] == a["alive"] + a["exited"] + a["escaped"]
    assert m["steps"] == 160 and m["config"]["scenario"] == scenario
    assert m["nrmse_velocity"] is not None and m["nrmse_velocity"] < 0.2
    report = (out / "report.md").read_text()
    assert "0.15 - 0.9" in report and "nrmse_density" in report
    for name in ("velocity_cfd_fit_swarm.png", "pressure_cfd_fit_swarm.png", "density_cfd_fit_swarm.png",
                 "density_velocity_swarm.png", "centreline.png"):
        assert (out / name).stat().st_size > 1000
    assert list(out.glob("snapshot_*.png"))
    if "--collisions" in extra:
        assert m["collisions"] is not None


def test_simulation_is_reproducible_with_a_seed():
    cmap = synthetic_tunnel_map(nx=8)
    cfg = RunConfig(duration_s=4.0, average_window_s=2.0, seed=5, figures=False)
    a, b = simulate(cfg, cmap), simulate(cfg, cmap)
    np.testing.assert_array_equal(a.fields.rho_s_kg_m3, b.fields.rho_s_kg_m3)
    np.testing.assert_array_equal(a.fields.u_axial_m_s, b.fields.u_axial_m_s)
    c = simulate(RunConfig(duration_s=4.0, average_window_s=2.0, seed=6, figures=False), cmap)
    assert not np.array_equal(a.fields.rho_s_kg_m3, c.fields.rho_s_kg_m3)


def test_time_average_uses_the_window():
    cmap = synthetic_tunnel_map(nx=8)
    r = simulate(RunConfig(duration_s=4.0, average_window_s=1.0, sample_interval_s=0.1, figures=False), cmap)
    assert r.window_s == pytest.approx((3.0, 4.0))
    assert r.fields.n_time_samples == 10


def test_bad_config_is_refused():
    with pytest.raises(ValueError, match="scenario"):
        RunConfig(scenario="vortex")
