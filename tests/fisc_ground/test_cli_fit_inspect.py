"""`fisc-ground fit / keygen / inspect / plot` as a user runs them (real files, real processes)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fisc_agent.map.codec import load_map
from fisc_ground.cli import main
from fisc_ground.fit.scaling import KINETIC_DISPERSION_RATIO
from fisc_ground.fit.staggered import (AUTO_CONTINUITY_WEIGHTS, AUTO_DENSITY_AMPLITUDES, STATIC_VELOCITY_BUDGET,
                                   STATIC_VELOCITY_LIMIT)



def fisc_ground(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fisc_ground.cli", *args], capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def default_map(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("maps") / "tunnel.fiscmap"
    assert main(["fit", "cd_nozzle_inviscid", "-o", str(out)]) == 0
    return out


def test_fit_builtin_writes_a_verified_map(default_map, tmp_path):
    cmap = load_map(default_map)
    assert cmap.n_cv == 560  # the designed staircase keeps 560 of the 741 covered cubes
    assert cmap.body["staggered"]["staircase_contrast"] == 0.4
    every = tmp_path / "every.fiscmap"
    assert main(["fit", "cd_nozzle_inviscid", "-o", str(every), "--staircase-contrast", "off"]) == 0
    assert load_map(every).n_cv == 741  # DESIGN.md: about 740 CVs on the shipped export (paper: 772)
    assert load_map(every).body["staggered"]["staircase_contrast"] is None
    assert cmap.body["provenance"]["reference"]["name"] == "cd_nozzle_inviscid"
    assert cmap.body["n_range"] == [2, 10]
    speeds = np.linalg.norm(cmap.scale * cmap["fit_velocity_m_s"], axis=-1)
    assert np.nanmax(speeds) <= cmap.body["max_speed_m_s"] + 1e-9


def test_inspect_json_has_the_contract_keys(default_map):
    res = fisc_ground("inspect", str(default_map), "--json")
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    for key in ("n_cv", "cell_size", "scale", "kappa", "n_range", "schema_version", "sha256", "signed",
                "fit_seconds", "fit_velocity_rmse", "fit_pressure_rmse"):
        assert key in summary, key
    assert summary["cell_size"] == 0.5 and summary["signed"] is False and summary["schema_version"] == 2
    assert summary["fit_velocity_rmse"] < 1e-6
    assert summary["flight"] == {"mode": "kinetic", "lookahead_s": 0.5, "persistence_s": 2.0}
    design = summary["design"]
    assert design["continuity_weight"] == 0.5 and design["continuity_weight_mode"] == "auto"
    assert design["density_amplitude"] == 1.1 and design["density_amplitude_mode"] == "auto"


def test_inspect_text_names_the_flight_settings_and_the_design(tmp_path, default_map):
    res = fisc_ground("inspect", str(default_map))
    assert res.returncode == 0, res.stderr
    assert "flight       : kinetic, look-ahead 0.5 s, persistence 2 s (recommended)" in res.stdout
    assert ("design       : staircase contrast 0.4, continuity weight 0.5 (auto), density amplitude 1.1 (auto), "
            "static field velocity nRMSE 0.053") in res.stdout
    paper = tmp_path / "paper.fiscmap"
    assert main(["fit", "analytic", "-o", str(paper), "--preset", "paper"]) == 0
    res = fisc_ground("inspect", str(paper))
    assert "flight       : mean, look-ahead 0 s (schema 1: the paper's Algorithm 1)" in res.stdout
    assert "design       : none (no staggered field)" in res.stdout


def test_fit_preset_paper_writes_the_schema_1_map(tmp_path):
    out = tmp_path / "paper.fiscmap"
    assert main(["fit", "analytic", "-o", str(out), "--preset", "paper"]) == 0
    cmap = load_map(out)
    assert cmap.schema_version == 1 and "face_u_x_m_s" not in cmap.arrays and "flight" not in cmap.body


def test_fit_density_options_reach_the_map(tmp_path):
    plain, deep = tmp_path / "plain.fiscmap", tmp_path / "deep.fiscmap"
    assert main(["fit", "analytic", "-o", str(plain)]) == 0
    assert main(["fit", "analytic", "-o", str(deep), "--density-amplitude", "1.3", "--continuity-weight", "0.25"]) == 0
    header = load_map(deep).body["staggered"]
    assert header["density_amplitude"] == 1.3 and header["continuity_weight"] == 0.25
    assert header["density_amplitude_mode"] == header["continuity_weight_mode"] == "fixed"
    auto = load_map(plain).body["staggered"]  # no flag: chosen within the static velocity budget / limit
    assert auto["density_amplitude_mode"] == "auto" and auto["density_amplitude"] in AUTO_DENSITY_AMPLITUDES
    assert auto["continuity_weight_mode"] == "auto" and auto["continuity_weight"] in AUTO_CONTINUITY_WEIGHTS
    assert auto["velocity_budget"] == STATIC_VELOCITY_BUDGET and auto["velocity_limit"] == STATIC_VELOCITY_LIMIT
    assert auto["static_velocity_nrmse"] <= STATIC_VELOCITY_BUDGET or auto["density_amplitude"] == 1.0
    explicit = tmp_path / "auto.fiscmap"
    assert main(["fit", "analytic", "-o", str(explicit), "--density-amplitude", "auto",
                 "--continuity-weight", "auto"]) == 0
    chosen = load_map(explicit).body["staggered"]
    assert (chosen["density_amplitude"], chosen["continuity_weight"]) == (auto["density_amplitude"],
                                                                          auto["continuity_weight"])

    def ratio(path):
        rho = load_map(path)["cv_design_density"]
        return float(np.max(rho) / np.min(rho))

    assert ratio(deep) > ratio(plain) > 1.0


def test_fit_dispersion_ratio_sets_kappa_and_is_recorded(tmp_path):
    """kappa maps the CFD pressure onto the spread sigma = R x the peak target speed; P ~ sigma^2."""
    plain, hot = tmp_path / "plain.fiscmap", tmp_path / "hot.fiscmap"
    assert main(["fit", "analytic", "-o", str(plain)]) == 0
    assert main(["fit", "analytic", "-o", str(hot), "--dispersion-ratio", "1.5"]) == 0
    a, b = load_map(plain).body, load_map(hot).body
    assert b["provenance"]["config"]["dispersion_ratio"] == 1.5
    assert a["provenance"]["config"]["dispersion_ratio"] is None
    assert b["kappa"] / a["kappa"] == pytest.approx((1.5 / KINETIC_DISPERSION_RATIO) ** 2, rel=1e-9)


@pytest.mark.parametrize("args, message", [
    (["--preset", "paper", "--density-amplitude", "1.2"], "--density-amplitude: the paper's schema-1 map"),
    (["--density-amplitude", "5"], "use a density_amplitude below"),
    (["--density-amplitude", "deep"], "--density-amplitude: expected a number or 'auto', got 'deep'"),
    (["--preset", "paper", "--density-amplitude", "auto"], "--density-amplitude: the paper's schema-1 map"),
    (["--continuity-weight", "1.5"], "continuity_weight must lie in"),
    (["--continuity-weight", "half"], "--continuity-weight: expected a number or 'auto', got 'half'"),
    (["--preset", "paper", "--continuity-weight", "auto"], "--continuity-weight: the paper's schema-1 map"),
    (["--dispersion-ratio", "0"], "dispersion_ratio must be positive and finite"),
    (["--staircase-contrast", "1"], "staircase_contrast must lie in (0, 1)"),
    (["--staircase-contrast", "none"], "--staircase-contrast: expected a number or 'off', got 'none'"),
    (["--preset", "paper", "--staircase-contrast", "0.3"], "--staircase-contrast: the paper's schema-1 map"),
    (["--dispersion-ratio", "nan"], "dispersion_ratio must be positive and finite"),
])
def test_fit_refuses_bad_design_options_and_writes_nothing(tmp_path, args, message):
    out = tmp_path / "m.fiscmap"
    res = fisc_ground("fit", "analytic", "-o", str(out), *args)
    assert res.returncode == 2 and message in res.stderr, res.stderr
    assert not out.exists()


def test_signed_map_round_trip_and_refusals(tmp_path, default_map):
    assert main(["keygen", "-o", str(tmp_path / "ground")]) == 0
    assert main(["keygen", "-o", str(tmp_path / "stranger")]) == 0
    signed = tmp_path / "signed.fiscmap"
    assert main(["fit", "cd_nozzle_inviscid", "-o", str(signed), "--sign", str(tmp_path / "ground.key")]) == 0
    ok = fisc_ground("inspect", str(signed), "--json", "--trusted-key", str(tmp_path / "ground.pub"))
    assert ok.returncode == 0 and json.loads(ok.stdout)["signed"] is True

    stranger = fisc_ground("inspect", str(signed), "--trusted-key", str(tmp_path / "stranger.pub"))
    assert stranger.returncode == 2 and "not trusted" in stranger.stderr
    unsigned = fisc_ground("inspect", str(default_map), "--trusted-key", str(tmp_path / "ground.pub"))
    assert unsigned.returncode == 2 and "unsigned" in unsigned.stderr

    data = bytearray(signed.read_bytes())
    flipped = tmp_path / "flipped.fiscmap"
    data[len(data) // 2] ^= 1
    flipped.write_bytes(bytes(data))
    res = fisc_ground("inspect", str(flipped))
    assert res.returncode == 2 and "sha256" in res.stderr

    truncated = tmp_path / "truncated.fiscmap"
    truncated.write_bytes(signed.read_bytes()[:-100])
    res = fisc_ground("inspect", str(truncated))
    assert res.returncode == 2 and "truncated" in res.stderr


def test_bad_reference_exits_nonzero_and_writes_nothing(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("nodenumber, x-coordinate, y-coordinate, z-coordinate, pressure, x-velocity, y-velocity, z-velocity\n"
                   "1, 0.0, 0.0, 0.0, 1.0, 3.0, 0.0, 0.0\n"
                   "2, 0.1, 0.0, 0.0, abc, 3.0, 0.0, 0.0\n")
    out = tmp_path / "m.fiscmap"
    res = fisc_ground("fit", str(bad), "-o", str(out))
    assert res.returncode == 2
    assert "bad.csv" in res.stderr and "line 3" in res.stderr
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["bad.csv"]


def test_unknown_builtin_lists_the_known_names(tmp_path):
    res = fisc_ground("fit", "no_such_case", "-o", str(tmp_path / "m.fiscmap"))
    assert res.returncode == 2 and "cd_nozzle_inviscid" in res.stderr


def test_rans_builtin_keeps_reversed_flow_cvs(tmp_path):
    """With every covered cube a CV; the designed staircase leaves out the separated wall cubes (they
    are the least covered of their slices), so the default map of cd_nozzle has none."""
    out, designed = tmp_path / "rans.fiscmap", tmp_path / "designed.fiscmap"
    assert main(["fit", "cd_nozzle", "-o", str(designed)]) == 0
    assert not (load_map(designed)["target_velocity_m_s"][:, 0] < 0).any()
    assert main(["fit", "cd_nozzle", "-o", str(out), "--staircase-contrast", "off"]) == 0
    cmap = load_map(out)
    reversed_cvs = cmap["target_velocity_m_s"][:, 0] < 0
    assert reversed_cvs.any()  # separation on the diverging wall (x = 10.5-14.8 m)
    xs = cmap["cv_center_m"][reversed_cvs, 0]
    assert xs.min() > 9.0
    np.testing.assert_allclose(cmap["fit_mean_velocity_m_s"][reversed_cvs], cmap["target_velocity_m_s"][reversed_cvs],
                               atol=1e-6)


@pytest.mark.parametrize("case", ["cd_nozzle_inviscid", "cd_nozzle"])
def test_three_exports_of_one_solution_give_the_same_cv_count(tmp_path, case, shared_path):
    counts = {}
    for name in ("fluent_export_3d.csv", "openfoam_internal.vtu", "axisym_cells.csv"):
        out = tmp_path / f"{name}.fiscmap"
        assert main(["fit", str(shared_path("reference", case, name)), "-o", str(out)]) == 0, name
        counts[name] = load_map(out).n_cv
    assert len(set(counts.values())) == 1, counts


def test_plot_writes_the_paper_figures(tmp_path, default_map):
    assert main(["plot", str(default_map), "-o", str(tmp_path / "figs")]) == 0
    pngs = sorted(p.name for p in (tmp_path / "figs").glob("*.png"))
    assert len(pngs) >= 3
    for p in (tmp_path / "figs").glob("*.png"):
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 10_000


def _synthetic_pass(default_map, path, above_wall_m: float, estimate_bias_m_s: float = 0.0,
                    gnss_every: int = 0, columns=None):
    """A pass along y = 0 at ``above_wall_m`` over the map's wall at its throat, flown at S x the CFD speed;
    the logged (estimated) velocity off by ``estimate_bias_m_s``; every ``gnss_every``-th row with the GNSS
    velocity, exact (0: none); written with ``columns`` (default: the flight log's)."""
    from fisc_agent.flight.flightlog import COLUMNS
    from fisc_agent.map.wall import map_wall
    from fisc_ground.reference.builtin import load_builtin

    columns = columns or COLUMNS
    cmap = load_map(default_map)
    wall = map_wall(cmap.arrays)
    ref = load_builtin("cd_nozzle_inviscid")
    throat = float(wall.x_m[np.argmin(wall.radius_m)])
    z = float(wall.radius_at(throat)) + above_wall_m
    rows = []
    for k, x in enumerate(np.arange(-0.5, 15.6, 0.1)):
        p = np.array([x, 0.0, z])
        j = int(np.argmin(np.sum((ref.points_m - p) ** 2, axis=1)))
        u = cmap.scale * float(ref.velocity_m_s[j, 0])
        row = dict.fromkeys(COLUMNS, "")
        row.update(time_s=f"{0.1 * k:.4f}", state="FLOW" if x < 15.0 else "EXIT", x_m=f"{x:.4f}", y_m="0.0",
                   z_m=f"{z:.4f}", vx_m_s=f"{u + estimate_bias_m_s:.4f}", vy_m_s="0.0", vz_m_s="0.0")
        if gnss_every and k % gnss_every == 0:
            row.update(gnss_vx_m_s=f"{u:.4f}", gnss_vy_m_s="0.0")
        rows.append(row)
    path.write_text(",".join(columns) + "\n" + "".join(",".join(r[c] for c in columns) + "\n" for r in rows))
    return path


def _score_flight_json(log, default_map) -> dict:
    out = fisc_ground("score-flight", str(log), "--map", str(default_map), "--json")
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.splitlines()[0])


def test_score_flight_measures_a_pass_against_the_wall_the_map_carries(default_map, tmp_path):
    """`fisc-ground score-flight LOG --map MAP --json`: a synthetic pass along y = 0 at a height that
    puts it 0.2 m outside the map's wall at the throat, inside elsewhere, flown at S x the CFD speed."""
    score = _score_flight_json(_synthetic_pass(default_map, tmp_path / "pass.csv", 0.2), default_map)
    assert score["crossed"] and not score["held"]
    assert score["max_excursion_m"] == pytest.approx(0.2, abs=0.02)   # the wall's narrowest station, sampled
    assert score["velocity_nrmse"] < 0.01                               # it flew S x the CFD at its nodes
    assert score["velocity_nrmse_gnss"] is None                         # no GNSS velocity logged


def test_score_flight_scores_the_gnss_velocity_beside_the_estimate(default_map, tmp_path):
    """An estimate 0.2 m/s slow and an exact GNSS velocity on every third row: the estimate's nRMSE is the
    bias over the peak, the GNSS one ~0; a log written before the GNSS columns still scores, without it."""
    log = _synthetic_pass(default_map, tmp_path / "biased.csv", -0.5, estimate_bias_m_s=-0.2, gnss_every=3)
    score = _score_flight_json(log, default_map)
    assert score["velocity_nrmse"] == pytest.approx(0.2 / score["peak_target_m_s"], rel=1e-3)
    assert score["velocity_nrmse_gnss"] < 0.01
    from fisc_agent.flight.flightlog import COLUMNS

    old = [c for c in COLUMNS if not c.startswith("gnss_")]
    score = _score_flight_json(_synthetic_pass(default_map, tmp_path / "old.csv", -0.5, -0.2, 3, old), default_map)
    assert score["velocity_nrmse"] == pytest.approx(0.2 / score["peak_target_m_s"], rel=1e-3)
    assert score["velocity_nrmse_gnss"] is None
    text = fisc_ground("score-flight", str(log), "--map", str(default_map))
    assert text.returncode == 0 and "by the GNSS receiver's velocity" in text.stdout, text


def _log(path, t_wall, xyz):
    from fisc_agent.flight.flightlog import COLUMNS

    lines = [",".join(COLUMNS)]
    for k, (t, p) in enumerate(zip(t_wall, xyz)):
        row = dict.fromkeys(COLUMNS, "")
        row.update(time_s=f"{0.1 * k:.4f}", wall_time_s=f"{t:.4f}", state="FLOW", x_m=f"{p[0]:.4f}",
                   y_m=f"{p[1]:.4f}", z_m=f"{p[2]:.4f}", vx_m_s="1.0", vy_m_s="0.0", vz_m_s="0.0")
        lines.append(",".join(row[c] for c in COLUMNS))
    path.write_text("\n".join(lines) + "\n")
    return path


def test_score_flight_of_several_logs_reports_the_fleets_closest_approach(default_map, tmp_path):
    """Three vehicles at 1 m/s along x, on different wall-clock spans and sample times: b passes a at
    0.41 m (a and b are 0.41 m apart in y, b starts 1 s later on the wall clock, 1 m behind: they are
    abreast from t = 1001 s); c stays 2 m away.  The closest approach is between the logs of a and b, on
    the wall clock, with positions interpolated between samples; one near-miss below d_min 0.92 m."""
    t_a = 1000.0 + 0.1 * np.arange(100)
    a = _log(tmp_path / "a.csv", t_a, [(1.0 * (t - 1000.0), 0.0, 0.0) for t in t_a])
    t_b = 1001.05 + 0.1 * np.arange(80)  # samples between a's
    b = _log(tmp_path / "b.csv", t_b, [(1.0 * (t - 1000.0), 0.41, 0.0) for t in t_b])
    c = _log(tmp_path / "c.csv", t_a, [(1.0 * (t - 1000.0), -2.0, 0.0) for t in t_a])
    out = fisc_ground("score-flight", str(a), str(b), str(c), "--map", str(default_map), "--json")
    assert out.returncode == 0, out.stderr
    objs = [json.loads(line) for line in out.stdout.splitlines()]
    assert len(objs) == 4 and [o.get("log") for o in objs[:3]] == [str(a), str(b), str(c)]
    fleet = objs[3]["fleet"]
    assert fleet["closest_approach_m"] == pytest.approx(0.41, abs=1e-3)
    assert set(fleet["closest_approach_logs"]) == {str(a), str(b)}
    assert fleet["near_misses"] == 1 and fleet["d_min_m"] == pytest.approx(0.92, abs=0.01)
    assert 1001.0 <= fleet["closest_approach_time_s"] <= 1010.0
    text = fisc_ground("score-flight", str(a), str(c), "--map", str(default_map))
    assert text.returncode == 0, text.stderr
    assert "fleet of 2 logs: closest approach 2 m" in text.stdout and "0 near-misses" in text.stdout
    # one log: no fleet line; a bad period is a usage error naming it
    one = fisc_ground("score-flight", str(a), "--map", str(default_map))
    assert "fleet" not in one.stdout
    bad = fisc_ground("score-flight", str(a), str(b), "--map", str(default_map), "--period", "0")
    assert bad.returncode == 2 and "--period" in bad.stderr
