"""Hand-computed answers for every column of fields.csv and for the monitor's estimates.

Three agents of mass m = 2 kg (not 1: a reader that ignores the map's agent mass is off by 2x)
in a 3-CV map with l = 0.5 m (dV = 0.125 m^3), speed scale S = 2, fed to the monitor as
telemetry, recorded, replayed to fields.csv.  Every number below is worked out by hand in the
comments from the paper's equations (docs/swarm_model.md, "Where the paper's equations live"), with
a_max = (2.2 - 1) 9.81 = 11.772 m/s^2, lambda = 0.5, K_b = c_v = 1:

CV 0 (target v = (2,0,0), command S v = (4,0,0)): A v=(4,0,0), B v=(6,2,0)
    M = 4, rho = 4 / 0.125 = 32; U = (20,4,0)/4 = (5,1,0); u_axial = 5
    sum m|v|^2 = 2*16 + 2*40 = 112            -> P_s (kinetic) = 2*112/(3*0.125) = 597.333
    sum m|v - (4,0,0)|^2 = 0 + 2*8 = 16       -> swarm_pressure (dispersion) = 2*16/0.375 = 85.333
    <|v - u_s|^2>, u_s = (5,0,0): (1 + 5)/2 = 3 -> P_internal = 2/3*32*3 = 64
    T_rand = 1/2 <|v - U|^2> = 1/2 (2 + 2)/2 = 1 -> P_random = 4/3*32*1 = 42.667
    n = 16, L_c = 16^(-1/3), T_s = 1 + 0.5*11.772*16^(-1/3)
CV 1 (target (3,0,0), command (6,0,0)): C v=(6,0,3)
    rho = 16; u_axial = 6; P_s = 2*90/0.375 = 480; dispersion 2*18/0.375 = 96; P_int = 2/3*16*9 = 96
    T_rand = 0; n = 8, L_c = 0.5, T_s = 0.5*11.772*0.5 = 2.943
CV 2: empty (sums 0, means empty/NaN, samples 0)
Open fractions (map array cv_open_fraction) 1, 0.5, 0.25 divide density and swarm_pressure.
"""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from fisc_agent.zenoh import telemetry_codec as tc
from fisc_agent.map.codec import decode_map, encode_map
from fisc_ground.fields.field_report import FIELD_COLUMNS
from fisc_ground.monitor.run import TelemetryAggregator
from fisc_ground.monitor.flight_log import FlightLog, LogSettings
from fisc_ground.monitor.recording import replay

A_MAX = 1.2 * 9.81
NAN = math.nan

EXPECTED = {  # column -> (CV 0, CV 1, CV 2)
    "cv_id": (0, 1, 2),
    "cv_x": (0.25, 0.75, 1.25), "cv_y": (0.0, 0.0, 0.0), "cv_z": (0.0, 0.0, 0.0),
    "target_u_axial": (2.0, 3.0, 1.0),
    "target_pressure": (50.0, 40.0, 30.0),
    "target_density": (1.2, 1.1, 1.0),
    "target_command_u_axial": (4.0, 6.0, 2.0),
    "fit_pressure": (0.7, 0.8, 0.9),
    "swarm_u_axial": (5.0, 6.0, NAN),
    "swarm_pressure": (2 * 16 / 0.375, 2 * 18 / 0.375, 0.0),
    "swarm_density": (32.0, 16.0, 0.0),
    "swarm_temperature": (1.0 + 0.5 * A_MAX * 16 ** (-1 / 3), 0.5 * A_MAX * 0.5, NAN),
    "swarm_pressure_kinetic": (2 * 112 / 0.375, 2 * 90 / 0.375, 0.0),
    "swarm_pressure_internal": (64.0, 96.0, 0.0),
    "swarm_pressure_random": (4 / 3 * 32 * 1.0, 0.0, 0.0),
    "swarm_count": (2.0, 1.0, 0.0),
    "swarm_u_x": (5.0, 6.0, NAN), "swarm_u_y": (1.0, 0.0, NAN), "swarm_u_z": (0.0, 3.0, NAN),
    "samples": (2, 1, 0),
    "cv_open_fraction": (1.0, 0.5, 0.25),
    "swarm_density_open_volume": (32.0, 32.0, 0.0),
    "swarm_pressure_open_volume": (2 * 16 / 0.375, 2 * 2 * 18 / 0.375, 0.0),
}

AGENTS = {  # id -> (position in the map frame, velocity)
    1: ((0.20, -0.10, 0.00), (4.0, 0.0, 0.0)),
    2: ((0.30, 0.10, 0.05), (6.0, 2.0, 0.0)),
    3: ((0.70, 0.00, -0.10), (6.0, 0.0, 3.0)),
}


def three_cv_map() -> bytes:
    n = 3
    centers = np.array([[0.25, 0.0, 0.0], [0.75, 0.0, 0.0], [1.25, 0.0, 0.0]])
    target = np.array([[2.0, 0.0, 0.0], [3.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    vel = np.repeat(target[:, None, :], 2, axis=1)
    meta = {"map_version": 1, "n_cv": n, "grid": {"origin_m": [0.0, -0.25, -0.25], "cell_size_m": 0.5, "shape": [3, 1, 1]},
            "n_range": [2, 2], "scale": 2.0, "kappa": 1e-3, "agent_mass_kg": 2.0}
    arrays = {"cv_center_m": centers, "cv_index": np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]]),
              "grid_cv": np.arange(n).reshape(3, 1, 1), "n_star": np.full(n, 2), "fit_velocity_m_s": vel,
              "fit_mean_velocity_m_s": target, "fit_pressure": np.array([0.7, 0.8, 0.9]), "fit_loss": np.zeros(n),
              "target_velocity_m_s": target, "target_pressure_gauge_pa": np.array([50.0, 40.0, 30.0]),
              "target_density_kg_m3": np.array([1.2, 1.1, 1.0]), "swarm_pressure_target": np.ones(n),
              "node_count": np.full(n, 4), "cv_open_fraction": np.array([1.0, 0.5, 0.25])}
    return encode_map(meta, arrays)


def one_sample_stream() -> tuple[list[float], list[int], list[bytes]]:
    """Every agent heard at t = 100.0 s, then one message at 100.6 s that closes exactly one
    fleet sample (at 100.5 s, sample period 0.5 s)."""
    t, ids, payloads = [], [], []
    for aid, (pos, vel) in AGENTS.items():
        t.append(100.0 + 0.01 * aid), ids.append(aid)
        payloads.append(tc.encode(tc.Telemetry(agent_id=aid, seq=0, time_s=100.0, position_m=pos, velocity_m_s=vel,
                                               state="FLOW")))
    t.append(100.6), ids.append(1), payloads.append(payloads[0])
    return t, ids, payloads


def test_the_monitor_estimates_match_the_hand_computation():
    agg = TelemetryAggregator(decode_map(three_cv_map()), sample_period_s=0.5, stale_after_s=3.0)
    agg.ingest(*one_sample_stream())
    f = agg.fields()
    assert f.n_time_samples == 1
    np.testing.assert_allclose(f.rho_s_kg_m3, EXPECTED["swarm_density"])                   # uses m = 2 kg
    np.testing.assert_allclose(f.p_dispersion_pa, EXPECTED["swarm_pressure"])
    np.testing.assert_allclose(f.p_s_pa, EXPECTED["swarm_pressure_kinetic"])
    np.testing.assert_allclose(f.p_internal_pa, EXPECTED["swarm_pressure_internal"])
    np.testing.assert_allclose(f.u_axial_m_s, EXPECTED["swarm_u_axial"])
    np.testing.assert_allclose(f.t_s_m2_s2, EXPECTED["swarm_temperature"])


def test_every_fields_csv_column_of_a_replay_matches_the_hand_computation(tmp_path):
    blob = three_cv_map()
    rec_path = tmp_path / "r.mcap"
    rec = FlightLog(LogSettings(swarm="alpha", sample_period_s=0.5, stale_after_s=3.0), mcap_path=rec_path)
    rec.write_map(99.0, blob)
    t, ids, payloads = one_sample_stream()
    rec.write_telemetry(np.array(t), np.array(ids), payloads)
    rec.close()
    out = replay(rec_path, tmp_path / "out", min_samples=1, figures=False)
    with open(out["fields.csv"], newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == FIELD_COLUMNS and len(rows) == 3
    assert set(EXPECTED) == set(FIELD_COLUMNS), "a new column needs its hand-computed value here"
    for col in FIELD_COLUMNS:
        got = [float(r[col]) if r[col] not in ("", "nan") else NAN for r in rows]
        np.testing.assert_allclose(got, EXPECTED[col], rtol=1e-12, atol=1e-12, err_msg=col)


@pytest.mark.parametrize("mass_kg", [0.5, 3.0])
def test_density_and_pressures_scale_with_the_agent_mass(mass_kg):
    """Changing only the map's agent mass scales density and every pressure by m / 2 kg."""
    base = decode_map(three_cv_map())
    body = dict(base.body, agent_mass_kg=mass_kg)
    body.pop("arrays")
    for k in ("schema", "schema_version"):
        body.pop(k)
    cmap = decode_map(encode_map(body, {k: np.array(v) for k, v in base.arrays.items()}))
    assert cmap.body["agent_mass_kg"] == mass_kg
    agg = TelemetryAggregator(cmap)
    agg.ingest(*one_sample_stream())
    f = agg.fields()
    k = mass_kg / 2.0
    np.testing.assert_allclose(f.rho_s_kg_m3, k * np.array(EXPECTED["swarm_density"]))
    np.testing.assert_allclose(f.p_dispersion_pa, k * np.array(EXPECTED["swarm_pressure"]))
    np.testing.assert_allclose(f.p_s_pa, k * np.array(EXPECTED["swarm_pressure_kinetic"]))
