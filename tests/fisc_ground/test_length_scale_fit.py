"""A tunnel sized for the vehicles and separation by design, as ``fisc-ground fit`` builds them:
``--length-scale``, ``--vehicle-radius``, ``--position-sigma``, the header and ``inspect``."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from fisc_agent.map.codec import MapError, decode_map, encode_map, load_map
from fisc_agent.map.separation import DEFAULT_D_MIN_M, d_min_m, map_separation
from fisc_ground.cli import main
from fisc_ground.fit.length_scale import map_length_scale, scale_reference, time_ratio
from fisc_ground.fit.separation_budget import poisson_density_for_nn
from fisc_ground.maps.build import FitConfig, build_map
from fisc_ground.reference.load import load_reference


@pytest.fixture(scope="module")
def maps():
    """The embedded default at L = 1 and 2 (header, arrays)."""
    field = load_reference("cd_nozzle_inviscid")
    return {L: build_map(field, FitConfig(length_scale=L, map_version=1)) for L in (1.0, 2.0)}


def test_a_scaled_map_is_the_unscaled_one_magnified(maps):
    (m1, a1), (m2, a2) = maps[1.0], maps[2.0]
    assert m2["n_cv"] == m1["n_cv"] and m2["grid"]["shape"] == m1["grid"]["shape"]
    np.testing.assert_allclose(a2["cv_center_m"], 2.0 * a1["cv_center_m"], rtol=0, atol=1e-12)
    assert m2["grid"]["cell_size_m"] == 2.0 * m1["grid"]["cell_size_m"]
    np.testing.assert_allclose(m2["grid"]["origin_m"], 2.0 * np.asarray(m1["grid"]["origin_m"]), atol=1e-12)
    np.testing.assert_allclose(a2["duct_wall_m"], 2.0 * a1["duct_wall_m"], atol=1e-12)   # the wall too
    # velocities kept (within --max-speed: the same S), times x L
    assert m2["scale"] == pytest.approx(m1["scale"], rel=1e-12)
    np.testing.assert_allclose(a2["fit_velocity_m_s"], a1["fit_velocity_m_s"], rtol=0, atol=1e-9)
    assert m2["flight"]["persistence_s"] == 2.0 * m1["flight"]["persistence_s"]
    assert m2["flight"]["lookahead_s"] == m1["flight"]["lookahead_s"]       # a vehicle time: kept
    assert m2["kappa"] == pytest.approx(m1["kappa"] / 8.0, rel=1e-9)         # pressure per volume: L^-3
    assert (m1["length_scale"], m2["length_scale"]) == (1.0, 2.0)
    assert m2["separation"]["mean_transit_s"] == pytest.approx(2.0 * m1["separation"]["mean_transit_s"])


def test_the_budget_grows_as_the_scaled_volume_over_d_min_cubed(maps):
    s1, s2 = maps[1.0][0]["separation"], maps[2.0][0]["separation"]
    assert s2["tunnel_volume_m3"] == pytest.approx(8.0 * s1["tunnel_volume_m3"])
    n_star = poisson_density_for_nn(DEFAULT_D_MIN_M)     # the densest CV's number density at E[NN] = d_min
    rho = maps[1.0][1]["cv_design_density"]
    for s in (s1, s2):
        assert s["max_in_tunnel"] == math.floor(n_star * s["tunnel_volume_m3"] / rho.max())
    assert s2["max_in_tunnel"] == pytest.approx(8 * s1["max_in_tunnel"], abs=8)
    assert s1["d_min_m"] == s2["d_min_m"] == pytest.approx(DEFAULT_D_MIN_M)


def test_length_scale_one_is_the_reference_itself_and_bad_scales_are_named():
    field = load_reference("cd_nozzle_inviscid")
    assert scale_reference(field, 1.0) is field
    assert time_ratio(3.0) == 3.0 and map_length_scale({}) == 1.0
    for bad in (0.0, -2.0, math.nan, math.inf, True, "2"):
        with pytest.raises(ValueError, match="length scale"):
            scale_reference(field, bad)
        with pytest.raises(ValueError, match="length scale"):
            FitConfig(length_scale=bad)


def test_fit_config_refuses_bad_separation():
    with pytest.raises(ValueError, match="vehicle radius"):
        FitConfig(vehicle_radius_m=-0.1)
    with pytest.raises(ValueError, match="position sigma"):
        FitConfig(position_sigma_m=math.nan)
    with pytest.raises(ValueError, match="d_min = 0"):
        FitConfig(vehicle_radius_m=0.0, position_sigma_m=0.0)
    assert FitConfig(vehicle_radius_m=0.0, position_sigma_m=0.01).separation.d_min_m > 0   # just inside


def test_fit_records_the_flags_and_inspect_says_what_the_map_allows(tmp_path, capsys):
    out = tmp_path / "big.fiscmap"
    assert main(["fit", "cd_nozzle_inviscid", "-o", str(out), "--length-scale", "2", "--vehicle-radius", "0.3",
                 "--position-sigma", "0.05"]) == 0
    assert "vehicles in the tunnel at once" in capsys.readouterr().out
    cmap = load_map(out)
    sep = cmap.body["separation"]
    assert (sep["vehicle_radius_m"], sep["position_sigma_m"]) == (0.3, 0.05)
    assert sep["d_min_m"] == pytest.approx(d_min_m(0.3, 0.05)) == pytest.approx(map_separation(cmap.body).d_min_m)
    assert map_separation(cmap.body).admission_period_s == sep["admission_period_s"]
    assert cmap.body["length_scale"] == 2.0 and cmap.cell_size_m == 1.0
    assert cmap.body["provenance"]["config"]["length_scale"] == 2.0
    assert main(["inspect", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"at most {sep['max_in_tunnel']} vehicles in the tunnel at once at d_min = {d_min_m(0.3, 0.05):.3g} m" in text
    assert "admit one vehicle every" in text and "L = 2 (lengths x2, speeds x1, times x2" in text
    assert main(["inspect", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["length_scale"] == 2.0
    for key in ("vehicle_radius_m", "position_sigma_m", "d_min_m", "max_in_tunnel", "admission_period_s",
                "densest_nn_m", "mean_transit_s", "limit"):
        assert summary["separation"][key] == pytest.approx(sep[key]) if key != "limit" else summary["separation"][key] == sep[key]
    assert summary["separation"]["recorded"] is True


@pytest.mark.parametrize("flags, named", [
    (["--length-scale", "0"], "--length-scale"), (["--length-scale", "-1"], "--length-scale"),
    (["--length-scale", "nan"], "--length-scale"), (["--length-scale", "big"], "--length-scale"),
    (["--vehicle-radius", "-0.01"], "--vehicle-radius"), (["--vehicle-radius", "inf"], "--vehicle-radius"),
    (["--position-sigma", "nan"], "--position-sigma"), (["--position-sigma", "x"], "--position-sigma"),
])
def test_bad_fit_flags_exit_2_naming_the_flag(flags, named, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["fit", "cd_nozzle_inviscid", "-o", str(tmp_path / "m.fiscmap"), *flags])
    assert exc.value.code == 2
    assert named in capsys.readouterr().err


def test_a_zero_spacing_exits_2_with_a_named_error(tmp_path, capsys):
    assert main(["fit", "cd_nozzle_inviscid", "-o", str(tmp_path / "m.fiscmap"), "--vehicle-radius", "0",
                 "--position-sigma", "0"]) == 2
    assert "d_min = 0" in capsys.readouterr().err


def _reencoded(cmap, **changes):
    meta = {k: v for k, v in cmap.body.items() if k not in ("arrays", "schema")}
    for k, v in changes.items():
        if v is None:
            meta.pop(k, None)
        else:
            meta[k] = v
    return encode_map(meta, dict(cmap.arrays))


def test_a_map_without_the_keys_still_decodes_and_inspects_as_the_defaults(maps, tmp_path, capsys):
    meta, arrays = maps[1.0]
    cmap = decode_map(encode_map(meta, arrays))
    old = decode_map(_reencoded(cmap, separation=None, length_scale=None))
    sep = map_separation(old.body)
    assert sep.d_min_m == pytest.approx(DEFAULT_D_MIN_M) and sep.max_in_tunnel is None
    path = tmp_path / "old.fiscmap"
    path.write_bytes(_reencoded(cmap, separation=None, length_scale=None))
    assert main(["inspect", str(path)]) == 0
    text = capsys.readouterr().out
    assert "no budget recorded" in text and "L = 1" in text


@pytest.mark.parametrize("changes, what", [
    ({"separation": {"vehicle_radius_m": -1.0}}, "vehicle radius"),
    ({"separation": {"vehicle_radius_m": "0.25"}}, "vehicle_radius_m must be a number"),
    ({"separation": {"max_in_tunnel": 0}}, "max_in_tunnel"),
    ({"separation": {"max_in_tunnel": 2.5}}, "max_in_tunnel"),
    ({"separation": {"admission_period_s": 0.0}}, "admission_period_s"),
    ({"separation": [1, 2]}, "separation"),
    ({"length_scale": 0}, "length_scale"), ({"length_scale": True}, "length_scale"),
])
def test_a_malformed_header_is_a_schema_error(maps, changes, what):
    meta, arrays = maps[1.0]
    cmap = decode_map(encode_map(meta, arrays))
    with pytest.raises(MapError, match=what) as exc:
        decode_map(_reencoded(cmap, **changes))
    assert exc.value.kind.value == "schema"
