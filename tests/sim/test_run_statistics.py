"""``fisc-sim run``'s closest approach, near-misses and honest statistics (issue 37, items 6 and 7) on a
small synthetic map: keys, their agreement with an independent computation, d_min from the map header."""

import json
from dataclasses import replace

import numpy as np
import pytest

from fisc_ground.fields.intervals import figures_of_sums, stats_inputs
from fisc_ground.fields.separation_stats import brute_force_closest
from sim.cli import main
from sim.run import RunConfig, simulate
from sim.scenarios import synthetic_tunnel_map


@pytest.fixture(scope="module")
def cmap():
    return synthetic_tunnel_map(nx=12)


@pytest.fixture(scope="module")
def result(cmap):
    return simulate(RunConfig(duration_s=20.0, average_window_s=16.0, compare_paper=False, figures=False,
                              agents=150, block_s=2.0, separation_interval_s=1.0), cmap)


def test_point_figures_equal_the_field_runs_fidelity(result):
    """The bootstrap's point values are the very figures of FieldRun.fidelity (one definition)."""
    fid = result.field_run.fidelity()
    iv = result.field_run.statistics.intervals
    for k in ("nrmse_velocity", "nrmse_pressure", "nrmse_density", "pearson_velocity", "pearson_pressure",
              "pearson_density"):
        assert iv[k].value == pytest.approx(fid[k], rel=1e-9, nan_ok=True), k
        if np.isfinite(iv[k].lo):
            assert iv[k].lo <= iv[k].hi and iv[k].n_blocks == 8  # 16 s window in 2 s blocks


def test_closest_approach_is_over_the_agents_in_the_tunnel(result):
    a = result.approach
    assert a.steps == 21 and 0 < a.distance_m < 1.0 and a.id_a < a.id_b
    assert a.d_min_m == pytest.approx(0.92, abs=0.01)  # a map without a separation header: the defaults


@pytest.mark.parametrize("radius_m, sigma_m", [(0.0, 0.0), (0.6, 0.2)])
def test_d_min_comes_from_the_maps_header(cmap, radius_m, sigma_m):
    body = dict(cmap.body, separation={"vehicle_radius_m": radius_m, "position_sigma_m": sigma_m})
    r = simulate(RunConfig(duration_s=6.0, compare_paper=False, figures=False, agents=60,
                           separation_interval_s=1.0), replace(cmap, body=body))
    want = 2 * radius_m + 3 * np.sqrt(2) * sigma_m
    assert r.approach.d_min_m == pytest.approx(want)
    if want == 0.0:
        assert r.approach.near_misses == 0  # nothing is closer than 0 m


def test_metrics_json_and_report_carry_the_new_keys(tmp_path, cmap):
    from fisc_ground.maps.write import write_map

    path = tmp_path / "small.fiscmap"
    write_map(path, {k: v for k, v in cmap.body.items() if k not in ("arrays", "schema", "schema_version")},
              {k: np.asarray(v) for k, v in cmap.arrays.items()})
    out = tmp_path / "run"
    assert main(["run", "--map", str(path), "--duration", "12", "--average-window", "10", "-q", "-o", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert {"closest_approach_m", "near_misses", "d_min_m", "axial_profile", "intervals", "samples_per_cv"} <= set(m)
    assert m["closest_approach_m"] > 0 and m["near_misses"] >= 0
    assert set(m["intervals"]) == {"nrmse_velocity", "nrmse_pressure", "nrmse_density", "pearson_velocity",
                                   "pearson_pressure", "pearson_density"}
    prof = m["axial_profile"]
    assert len(prof["x_m"]) == 12 and prof["slice_m"] == pytest.approx(0.5)
    assert {"value", "lo", "hi", "width", "bias"} <= set(prof["pearson_density"])
    spc = m["samples_per_cv"]
    assert spc["min"] <= spc["median"] <= spc["max"] and 0 <= spc["fraction_below_min_samples"] <= 1
    report = (out / "report.md").read_text()
    assert "## Separation" in report and "near-misses" in report and "How far the figures can be trusted" in report
    assert (out / "axial_profile.png").stat().st_size > 1000


def test_profile_of_a_uniform_swarm_is_flat_and_scores_are_undefined(cmap):
    """Boundary: with identical samples everywhere the swarm's profile is constant: r and nRMSE NaN."""
    inp = stats_inputs(cmap, 1)
    n = cmap.n_cv
    sums = {"count": np.full(n, 4.0), "mass_kg": np.full(n, 4.0), "momentum_kg_m_s": np.tile([4.0, 0, 0], (n, 1)),
            "m_v2_kg_m2_s2": np.full(n, 8.0), "m_dev2_kg_m2_s2": np.full(n, 1.0), "n_time_samples": np.array(2.0),
            "n_ref_samples": np.array(2.0)}
    f = figures_of_sums(sums, inp)
    assert np.isnan(f["profile_pearson_density"]) and np.isnan(f["profile_nrmse_density"])
    zero = {k: np.zeros_like(v) for k, v in sums.items()}
    assert np.isnan(figures_of_sums(zero, inp)["profile_pearson_pressure"])  # no samples at all


def test_brute_force_agrees_on_a_run_snapshot(result):
    pos = result.field_run.snapshots[-1][1] if result.field_run.snapshots else None
    if pos is None or len(pos) < 2:
        pytest.skip("no snapshot")
    ids = np.arange(len(pos))
    from fisc_ground.fields.separation_stats import closest_pair

    assert closest_pair(ids, pos).distance_m == pytest.approx(brute_force_closest(ids, pos).distance_m)
