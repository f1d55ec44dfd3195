"""The monitor's separation watch and honest statistics (issue 37, items 6 and 7): the live alarm at its
d_min boundary, closest approach and near-misses over the fleet samples, the dashboard's lines, the d_min
spheres of the Foxglove scene, and replay's metrics."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fisc_agent.map.codec import decode_map
from fisc_agent.map.separation import DEFAULT_D_MIN_M
from fisc_ground.monitor import foxglove_scene as fs
from fisc_ground.monitor.aggregator import TelemetryAggregator
from fisc_ground.monitor.alarms import separation_alarm
from fisc_ground.monitor.flight_log import FlightLog, LogSettings
from fisc_ground.monitor.recording import replay
from fisc_ground.monitor.view import render

from .test_monitor_replay import synthetic_stream, telemetry


def test_separation_alarm_at_its_boundary():
    ids = np.array([3, 5, 9])
    pos = np.array([[0.0, 0, 0], [0.41, 0, 0], [5.0, 0, 0]])
    pair, line = separation_alarm(ids, pos, 0.92)
    assert line == "separation: agents 3 and 5 at 0.41 m < d_min 0.92 m"
    assert (pair.id_a, pair.id_b) == (3, 5)
    at = np.array([[0.0, 0, 0], [0.92, 0, 0]])
    assert separation_alarm(ids[:2], at, 0.92)[1] is None  # exactly d_min apart: no alarm
    assert separation_alarm(ids[:2], at, 0.92 + 1e-9)[1] is not None  # just inside
    assert separation_alarm(ids[:1], at[:1], 0.92) == (separation_alarm(ids[:1], at[:1], 0.92)[0], None)  # one agent
    assert separation_alarm(np.zeros(0, dtype=int), np.zeros((0, 3)), 0.92)[1] is None  # none
    nan = np.array([[0.0, 0, 0], [np.nan, 0, 0], [0.3, 0, 0]])
    assert separation_alarm(ids, nan, 0.92)[1] == "separation: agents 3 and 9 at 0.30 m < d_min 0.92 m"
    crowd = np.array([[0.0, 0, 0], [0.3, 0, 0], [0.6, 0, 0]])
    assert separation_alarm(ids, crowd, 0.92)[1].endswith("(+2 more pairs)")


def test_live_alarm_and_closest_approach_among_fresh_agents(make_map):
    cmap = decode_map(make_map(1))
    agg = TelemetryAggregator(cmap, sample_period_s=0.5, stale_after_s=2.0)
    assert agg.d_min_m == pytest.approx(DEFAULT_D_MIN_M)  # a map without a separation header
    # agents 3 and 5 close in on each other; agent 7 sits on 3 but is stale by t = 103
    for k in range(7):
        t = 100.0 + 0.5 * k
        gap = max(2.0 - 0.4 * k, 0.4)
        msgs = [(3, (1.0, 0.0, 0.0)), (5, (1.0 + gap, 0.0, 0.0))] + ([(7, (1.0, 0.1, 0.0))] if k == 0 else [])
        agg.ingest([t] * len(msgs), [m[0] for m in msgs], [telemetry(m[0], t, m[1]) for m in msgs])
    v = agg.view(103.0)
    assert v.stale == (7,)
    assert v.closest_ids == (3, 5) and v.closest_m == pytest.approx(0.4, abs=1e-6)
    assert "separation: agents 3 and 5 at 0.40 m < d_min 0.92 m" in v.alarms
    a = v.approach
    assert a["closest_approach_m"] == pytest.approx(0.1, abs=1e-6)  # 3 and 7 while 7 was fresh
    assert a["closest_approach_ids"] == [3, 7]
    assert a["near_misses"] == 2  # (3, 7) once, (3, 5) once since it closed below d_min


def test_dashboard_and_statistics_lines(make_map):
    from rich.console import Console

    cmap = decode_map(make_map(1, nx=12))
    agg = TelemetryAggregator(cmap, sample_period_s=0.5, stale_after_s=3.0)
    agg.ingest(*synthetic_stream(n_agents=20, seconds=40.0, rate_hz=2.0))
    v = agg.view(min_samples=1)
    assert len(v.statistics) == 3
    assert v.statistics[0].startswith("profile density r ") and "[" in v.statistics[0]
    assert ("wide in ~" in v.statistics[0]) or ("interval < 0.1 wide" in v.statistics[0])
    assert v.statistics[2].startswith("samples per CV: min ")
    console = Console(record=True, width=160, color_system=None)
    console.print(render(v, agg.fields(), cmap, 0, "FISC swarm alpha"))
    text = console.export_text()
    assert "closest approach" in text and "d_min 0.92 m" in text and "profile density r" in text
    # the statistics are not recomputed at every view: only after STATS_EVERY_SAMPLES new samples
    assert agg.view(min_samples=1).statistics == v.statistics


def _decoded(scene):
    """A SceneUpdate through its protobuf bytes, as a Foxglove client reads it."""
    from foxglove import messages as m
    from mcap.records import Schema
    from mcap_protobuf.decoder import DecoderFactory

    sch = m.SceneUpdate.get_schema()
    decoder = DecoderFactory().decoder_for("protobuf", Schema(id=1, name=sch.name, encoding=sch.encoding,
                                                              data=bytes(sch.data)))
    return decoder(scene.encode())


def test_scene_spheres_have_the_diameter_d_min():
    rec = np.zeros(2, dtype=fs.tc.DTYPE)
    rec["position_m"] = [[1.0, 0, 0], [2.0, 0, 0]]
    points = fs.agent_points(np.array([1, 2]), rec)
    ent = {e.id: e for e in _decoded(fs.scene_update(0.0, [], points, d_min_m=0.92)).entities}
    spheres = ent["d_min"].spheres
    assert len(spheres) == 2
    assert spheres[0].size.x == pytest.approx(0.92) and spheres[1].pose.position.x == pytest.approx(2.0)
    assert "d_min" not in {e.id for e in _decoded(fs.scene_update(0.0, [], points)).entities}


def test_replay_reports_intervals_profile_samples_and_closest_approach(tmp_path, make_map):
    path = tmp_path / "rec.mcap"
    rec = FlightLog(LogSettings(swarm="alpha", sample_period_s=0.5, stale_after_s=3.0), mcap_path=path)
    rec.write_map(999.0, make_map(1, nx=12))
    t, ids, p = synthetic_stream(n_agents=20, seconds=30.0, rate_hz=2.0)
    rec.write_telemetry(t, ids, p)
    rec.close()
    out = replay(path, tmp_path / "out", min_samples=1, figures=True)
    m = json.loads(out["metrics.json"].read_text())
    assert {"intervals", "axial_profile", "samples_per_cv", "closest_approach_m", "near_misses", "d_min_m"} <= set(m)
    assert m["intervals"]["nrmse_velocity"]["n_blocks"] == 3  # 30 s in 10 s blocks
    assert m["closest_approach_m"] > 0 and m["near_misses"] > 0  # 20 agents in a small box
    assert (tmp_path / "out" / "axial_profile.png").stat().st_size > 1000
