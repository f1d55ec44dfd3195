"""Monitor aggregation (100 agents over Zenoh), recording, and replay == live estimate."""

from __future__ import annotations

import csv
import json
import time

import numpy as np
import pytest

from fisc_agent.zenoh import telemetry_codec as tc
from fisc_agent.map.codec import decode_map
from fisc_agent.zenoh.keys import Keys
from fisc_agent.zenoh.link import AgentZenohLink
from fisc_ground.monitor.run import TelemetryPipe
from fisc_ground.monitor.aggregator import NO_AGENT, TelemetryAggregator
from fisc_ground.monitor.view import render
from fisc_ground.monitor.flight_log import FlightLog, LogSettings
from fisc_ground.monitor.recording import aggregate, iter_messages, read_recording, replay

from .conftest import snap, wait_for

CSV_COLUMNS = ["cv_x", "cv_y", "cv_z", "target_u_axial", "target_pressure", "target_density", "swarm_u_axial",
               "swarm_pressure", "swarm_density", "swarm_temperature", "samples"]


def telemetry(agent_id, t, pos, vel=(3.0, 0.0, 0.0), state="FLOW", **kw):
    return tc.encode(tc.Telemetry(agent_id=agent_id, seq=0, time_s=t, position_m=tuple(pos),
                                  velocity_m_s=tuple(vel), state=state, **kw))


def synthetic_stream(n_agents=30, seconds=5.0, rate_hz=10.0, seed=0):
    rng = np.random.default_rng(seed)
    times, ids, payloads = [], [], []
    for k in range(int(seconds * rate_hz)):
        for a in range(n_agents):
            t = 1000.0 + k / rate_hz + rng.uniform(0, 0.01)
            pos = (rng.uniform(0, 6), rng.uniform(-1, 1), rng.uniform(-1, 1))
            times.append(t), ids.append(a), payloads.append(telemetry(a, t, pos, rng.normal(3, 0.3, 3)))
    return np.array(times), np.array(ids), payloads


def test_the_monitor_samples_the_fleet_at_the_agents_telemetry_period():
    """A longer fleet sampling period drops positions (a vehicle crosses a throat slice in 0.3 s)."""
    from fisc_agent.cli import build_parser
    from fisc_ground.monitor.aggregator import SAMPLE_PERIOD_S, TelemetryAggregator
    from fisc_ground.monitor.flight_log import LogSettings

    rate_hz = build_parser().parse_args(["--mavlink", "udpin:0.0.0.0:14540", "--id", "0"]).telemetry_rate
    assert SAMPLE_PERIOD_S == pytest.approx(1.0 / rate_hz)
    assert TelemetryAggregator().sample_period_s == LogSettings().sample_period_s == SAMPLE_PERIOD_S


def test_aggregator_is_independent_of_batching(make_map):
    cmap = decode_map(make_map(1))
    t, ids, p = synthetic_stream()
    whole = TelemetryAggregator(cmap)
    whole.ingest(t, ids, p)
    pieces = TelemetryAggregator(cmap)
    cuts = [0, 1, 7, 100, 101, 640, 1200, len(p)]
    for a, b in zip(cuts[:-1], cuts[1:]):
        pieces.ingest(t[a:b], ids[a:b], p[a:b])
    fa, fb = whole.fields(), pieces.fields()
    assert fa.n_time_samples == fb.n_time_samples > 5
    for name, arr in fa.as_arrays().items():
        np.testing.assert_array_equal(arr, fb.as_arrays()[name], err_msg=name)
    assert fa.samples.sum() > 0 and np.nanmax(fa.rho_s_kg_m3) > 0


def test_aggregator_samples_on_grid_times_that_round_onto_themselves(make_map):
    """Receive times on the sampling grid where floor(t / p) + 1 lands back on t in floating point
    (4.3 / 0.1 = 42.99999999999999): ingest used to loop forever on them (a simulated run's clock
    hits them; a monitor's UNIX clock can)."""
    cmap = decode_map(make_map(1))
    agg = TelemetryAggregator(cmap, sample_period_s=0.1, stale_after_s=0.15)
    times = np.round(np.arange(80, 120) * 0.05, 10)  # 4.0 .. 5.95 s, 4.3 among them
    assert 4.3 in times.tolist()
    for t in times:
        agg.ingest([t], [1], [telemetry(1, t, (1.0, 0.0, 0.0))])
    assert agg.fields().n_time_samples == 19  # one per 0.1 s grid point after the first message


def test_aggregator_view_counts_states_stale_agents_and_alarms(make_map):
    cmap = decode_map(make_map(1))
    agg = TelemetryAggregator(cmap, stale_after_s=2.0)
    msgs = [(0, 100.0, (1, 0, 0), "FLOW", {}), (1, 100.0, (1, 0.2, 0), "HOLD", {"flags": frozenset({"failsafe"})}),
            (2, 100.0, (50, 0, 0), "FLOW", {}),                          # far outside the tunnel
            (3, 95.0, (1, 0, 0), "FLOW", {}),                            # stale
            (4, 100.0, (1, 0, 0), "FLOW", {"maps_rejected": 1, "reject_reason": "signature"})]
    agg.ingest([m[1] for m in msgs], [m[0] for m in msgs], [telemetry(m[0], m[1], m[2], state=m[3], **m[4]) for m in msgs])
    agg.ingest([100.1], [7], [telemetry(8, 100.1, (1, 0, 0))])          # key says 7, payload says 8
    agg.ingest([100.2], [NO_AGENT], [b"\x05garbage"])
    v = agg.view(100.5)
    assert v.n_agents == 5 and v.stale == (3,)
    assert v.by_state == {"FLOW": 3, "HOLD": 1}
    text = "\n".join(v.alarms)
    assert "outside the tunnel: agents 2" in text and "failsafe: agents 1" in text and "refused a map: agents 4" in text
    assert v.spoofed == 1 and v.bad_messages == 1 and "spoofing" in text
    render(v, agg.fields(), cmap, 0, "test")  # renders without error


def test_truncated_recording_is_read_up_to_the_last_complete_chunk(tmp_path, make_map):
    path = tmp_path / "rec.mcap"
    rec = FlightLog(LogSettings(swarm="alpha", sample_period_s=0.5, stale_after_s=3.0), mcap_path=path)
    blob = make_map(1)
    rec.write_map(999.0, blob)
    t, ids, p = synthetic_stream(n_agents=30, seconds=30.0)  # ~9000 messages: several MCAP chunks
    for a in range(0, len(p), 300):
        rec.write_telemetry(t[a:a + 300], ids[a:a + 300], p[a:a + 300])
    rec.close()
    full = read_recording(path)
    assert full.n_messages == len(p) and full.maps() == [blob] and not full.truncated
    assert full.settings.sample_period_s == 0.5 and full.settings.swarm == "alpha"
    got = [m for m in iter_messages(full)]
    assert [g[2] for g in got] == p and [g[0] for g in got] == t.tolist()  # exact, in order
    path.write_bytes(path.read_bytes()[: int(path.stat().st_size * 0.6)])
    cut = read_recording(path)
    assert cut.truncated and 0 < cut.n_messages < len(p)
    assert [m[2] for m in iter_messages(cut)] == \
        p[:cut.n_messages]  # a prefix of the stream


def test_hundred_agents_reach_the_monitor_and_replay_equals_live(net, sessions, make_map, tmp_path, ground_key):
    hub, member = net
    blob = make_map(5, nx=12)
    cmap = decode_map(blob)
    monitor_session = sessions(hub)
    rec_path = tmp_path / "live.mcap"
    recorder = FlightLog(LogSettings(swarm="alpha", sample_period_s=0.2, stale_after_s=1.0), mcap_path=rec_path)
    agg = TelemetryAggregator(None, sample_period_s=0.2, stale_after_s=1.0)
    pipe = TelemetryPipe(Keys("fisc", "alpha"), agg, recorder)
    pipe.set_map(cmap, blob)
    pipe.attach(monitor_session)
    shared = [sessions(member) for _ in range(4)]
    rng = np.random.default_rng(3)
    links = []
    for i in range(100):
        link = AgentZenohLink(None, "alpha", i, [ground_key[1]], False, lambda m: None, lambda c: None,
                              session=shared[i % 4]).start()
        # slow enough to stay inside the 6 m test map however long a loaded machine takes
        start = np.array([rng.uniform(0, 3.0), rng.uniform(-0.7, 0.7), rng.uniform(-0.7, 0.7)])
        vel = np.array([0.1, rng.normal(0, 0.005), rng.normal(0, 0.005)])
        t0 = time.time()
        link.start_telemetry(lambda s=start, v=vel, t0=t0: snap(
            position_map_m=s + v * (time.time() - t0), velocity_map_m_s=v, map_sha256=cmap.sha256,
            map_version=cmap.map_version), rate_hz=10)
        links.append(link)
    try:
        assert wait_for(lambda: len(agg.slots) == 100, timeout_s=20)
        assert wait_for(lambda: agg.acc is not None and agg.acc.n_time_samples >= 8, timeout_s=20)
    finally:
        for link in links:
            link.close()
    pipe.close()
    recorder.close()
    assert pipe.dropped == 0
    live_view = agg.view()
    # 100 agents in a 3 m x 1.4 m x 1.4 m box are far closer than d_min: the separation alarm, and only it
    assert live_view.by_state.get("FLOW") == 100
    assert [a.split(":")[0] for a in live_view.alarms] == ["separation"]
    live = agg.fields()
    assert live.samples.sum() >= 400  # agents join during the first samples
    replayed = aggregate(read_recording(rec_path))
    assert replayed.cmap.sha256 == cmap.sha256
    for name, arr in live.as_arrays().items():
        np.testing.assert_array_equal(arr, replayed.fields().as_arrays()[name], err_msg=name)
    out = replay(rec_path, tmp_path / "out", min_samples=1, figures=True)
    with open(out["fields.csv"]) as fh:
        header = next(csv.reader(fh))
    assert all(c in header for c in CSV_COLUMNS)
    metrics = json.loads(out["metrics.json"].read_text())
    assert metrics["agents"] == 100 and metrics["n_cv_compared"] > 0 and "nrmse_velocity" in metrics
    assert (tmp_path / "out" / "density_cfd_fit_swarm.png").is_file()


def test_dashboard_shows_heat_maps_counts_and_drops(make_map):
    from rich.console import Console

    cmap = decode_map(make_map(1))
    agg = TelemetryAggregator(cmap)
    agg.ingest(*synthetic_stream(n_agents=20, seconds=2.0))
    console = Console(record=True, width=120, color_system="truecolor")
    console.print(render(agg.view(), agg.fields(), cmap, 7, "FISC swarm alpha"))
    text = console.export_text()
    assert "swarm density" in text and "swarm pressure" in text and "FLOW" in text
    assert "dropped 7" in text and "v1" in text


def test_monitor_follows_a_newer_map(net, sessions, make_map):
    from fisc_ground.monitor.run import MapFollower, fetch_map
    from fisc_ground.zenoh.publish import MapServer

    hub, member = net
    server = MapServer(sessions(hub), "alpha", announce_period_s=0.2)
    server.serve(make_map(100))
    mon = sessions(member)
    keys = Keys("fisc", "alpha")
    assert wait_for(lambda: fetch_map(mon, keys, None, timeout_s=1.0) is not None)
    cmap, blob = fetch_map(mon, keys, None)
    agg = TelemetryAggregator(None)
    pipe = TelemetryPipe(keys, agg)
    pipe.set_map(cmap, blob)
    follower = MapFollower(mon, keys, pipe, None, cmap.map_version)
    server.serve(make_map(200, seed=4))
    assert wait_for(lambda: agg.cmap is not None and agg.cmap.map_version == 200)
    follower.close()
    pipe.close()
    server.close()
