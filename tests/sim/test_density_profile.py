"""``benchmarks/density_profile.py``: the slice-by-slice density diagnostic of docs/studies/density_study.md."""

import csv
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from fisc_agent.map.lookup import CommandField
from fisc_agent.map.codec import load_map
from fisc_ground.maps.build import default_map_path
from fisc_ground.maps.write import write_map
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
    assert "What the min-max density nRMSE is made of" in md and "| 0.9-1.0 |" in md


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


def _with_column(src: Path, dst: Path, column: str, values) -> Path:
    """A copy of the fields.csv ``src`` with ``column`` replaced by ``values`` (one per row)."""
    with open(src, newline="") as fh:
        rows = list(csv.DictReader(fh))
    for r, v in zip(rows, values, strict=True):
        r[column] = repr(float(v))
    with open(dst, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return dst


def test_what_the_min_max_error_is_made_of_matches_an_independent_recount(tool, short_run, tmp_path):
    checker = _load("fidelity_check", ROOT / "tests" / "sim" / "fidelity_check.py")
    p = tool.density_profile(short_run, default_map_path())
    f = tool.read_fields(short_run)
    use = f["samples"] > 0
    swarm, x = f["swarm_density"][use], f["cv_x"][use]
    # the bands split every compared CV and the whole squared error
    assert sum(b.n_cv for b in p.error_bands) == int(use.sum())
    assert sum(b.share for b in p.error_bands) == pytest.approx(1.0)
    assert [b.hi for b in p.error_bands] == list(tool.ERROR_BANDS)
    lo, hi = p.swarm_range
    assert lo * np.median(swarm) == pytest.approx(swarm.min()) and hi * np.median(swarm) == pytest.approx(swarm.max())
    # "every CV at its slice's mean", recounted by the independent checker from a rewritten fields.csv
    means = {xv: swarm[x == xv].mean() for xv in np.unique(x)}
    flat = np.where(use, [means.get(xv, 0.0) for xv in f["cv_x"]], f["swarm_density"])
    check = checker.fidelity_from_csv(str(_with_column(short_run, tmp_path / "flat.csv", "swarm_density", flat)))
    assert p.slice_means_only.nrmse == pytest.approx(check["nrmse_density"], abs=1e-9)
    assert p.slice_means_only.pearson == pytest.approx(check["pearson_density"], abs=1e-9)
    # the densest CVs at their slice's mean likewise
    top = np.flatnonzero(use)[np.argsort(swarm)[-tool.DENSEST:]]
    dense = f["swarm_density"].copy()
    dense[top] = [means[xv] for xv in f["cv_x"][top]]
    check = checker.fidelity_from_csv(str(_with_column(short_run, tmp_path / "dense.csv", "swarm_density", dense)))
    assert p.densest_at_slice_mean.nrmse == pytest.approx(check["nrmse_density"], abs=1e-9)


def test_several_runs_of_one_map_are_averaged_cv_by_cv(tool, short_run, tmp_path):
    checker = _load("fidelity_check", ROOT / "tests" / "sim" / "fidelity_check.py")
    f = tool.read_fields(short_run)
    other = _with_column(short_run, tmp_path / "other.csv", "swarm_density", 3.0 * f["target_density"])
    p = tool.density_profile([short_run, other], default_map_path())
    mean = _with_column(short_run, tmp_path / "mean.csv", "swarm_density",
                        0.5 * (f["swarm_density"] + 3.0 * f["target_density"]))
    check = checker.fidelity_from_csv(str(mean))
    assert p.realised.nrmse == pytest.approx(check["nrmse_density"], abs=1e-9)
    assert p.realised.pearson == pytest.approx(check["pearson_density"], abs=1e-9)
    # a CV that one run never sampled is left out
    samples = f["samples"].copy()
    samples[np.flatnonzero(samples > 0)[0]] = 0
    unsampled = _with_column(short_run, tmp_path / "unsampled.csv", "samples", samples)
    assert int(tool.density_profile([short_run, unsampled], default_map_path()).n_cv.sum()) == int((samples > 0).sum())
    # runs of another map (other CFD targets) are refused by name, as is an empty list
    moved = _with_column(short_run, tmp_path / "moved.csv", "target_density", 2.0 * f["target_density"])
    with pytest.raises(ValueError, match="moved.csv: not a run of the same map"):
        tool.density_profile([short_run, moved], default_map_path())
    with pytest.raises(ValueError, match="no fields.csv given"):
        tool.read_runs([])


def test_the_largest_within_slice_excess_and_its_share_every_run_has(tool, short_run, tmp_path):
    cmap = load_map(default_map_path())
    design, centres = np.asarray(cmap["cv_design_density"]), np.asarray(cmap["cv_center_m"])
    f = tool.read_fields(short_run)

    def over_slice(dens):  # recounted here: realised / designed over the slice's mean of that ratio
        use = f["samples"] > 0
        r = np.full(dens.size, np.nan)
        r[use] = (dens[use] / dens[use].mean()) / (design[use] / design[use].mean())
        for xv in np.unique(f["cv_x"][use]):
            m = use & (f["cv_x"] == xv)
            r[m] /= r[m].mean()
        return r

    p = tool.density_profile(short_run, default_map_path())
    mine = over_slice(f["swarm_density"])
    assert p.runs == 1 and np.isnan(p.residual_r_between_runs)
    assert len(p.largest_excess) == tool.EXCESS
    assert [e.cv_id for e in p.largest_excess] == list(np.argsort(-np.nan_to_num(mine, nan=-1.0))[:tool.EXCESS])
    for e in p.largest_excess:
        assert e.over_slice == pytest.approx(mine[e.cv_id]) and e.centre_m == pytest.approx(centres[e.cv_id])
        assert e.wall_class in tool.wall_classes(CommandField.from_map(cmap)) and 0 < e.open_fraction <= 1
    # the same run twice shares all of its scatter; a run of another pattern only what the two share
    twice = tool.density_profile([short_run, short_run], default_map_path())
    assert twice.runs == 2 and twice.residual_r_between_runs == pytest.approx(1.0)
    other = 3.0 * f["target_density"] * (1.0 + 0.1 * np.sin(f["cv_id"]))
    p2 = tool.density_profile([short_run, _with_column(short_run, tmp_path / "o.csv", "swarm_density", other)],
                              default_map_path())
    use = f["samples"] > 0
    assert p2.residual_r_between_runs == pytest.approx(np.corrcoef(mine[use], over_slice(other)[use])[0, 1])
    md = tool.markdown(p2)
    assert "correlate r" in md and "furthest above their slice" in md


def test_each_slices_band_and_the_figure(tool, short_run, tmp_path, capsys):
    f = tool.read_fields(short_run)
    use = f["samples"] > 0
    swarm, x = f["swarm_density"][use], f["cv_x"][use]
    norm = (swarm - swarm.min()) / (swarm.max() - swarm.min())  # recounted: min-max over every compared CV
    p = tool.density_profile(short_run, default_map_path())
    lo, hi = p.swarm_band
    for i, xv in enumerate(p.x_m):
        assert lo[i] == pytest.approx(norm[x == xv].min()) and hi[i] == pytest.approx(norm[x == xv].max())
    assert np.all(lo <= p.swarm + 1e-12) and np.all(p.swarm <= hi + 1e-12)
    png = tmp_path / "profile.png"
    assert tool.main([str(short_run), "--plot", str(png)]) == 0
    assert f"figure: {png}" in capsys.readouterr().out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
