"""Hostile input at the monitor (issue 12): a bad key, a failing batch, forged agent ids,
unsigned maps.  Real Zenoh sessions on a free loopback port."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from fisc_agent.zenoh import telemetry_codec as tc
from fisc_agent.map.codec import MapError, decode_map
from fisc_agent.zenoh.keys import Keys
from fisc_ground.monitor.run import AgentRoster, MapFollower, TelemetryAggregator, TelemetryPipe, fetch_map, render
from fisc_ground.monitor.flight_log import FlightLog, LogSettings
from fisc_ground.monitor.recording import read_recording
from fisc_ground.zenoh.publish import MapServer

from .conftest import wait_for


def telemetry(agent_id, t=100.0, pos=(1.0, 0.0, 0.0), vel=(3.0, 0.0, 0.0)):
    return tc.encode(tc.Telemetry(agent_id=agent_id, seq=0, time_s=t, position_m=pos, velocity_m_s=vel, state="FLOW"))


def consumer_alive(pipe: TelemetryPipe) -> bool:
    return any(t.name == "fisc-monitor-consumer" and t.is_alive() for t in threading.enumerate()) and pipe._thread.is_alive()


def test_a_huge_agent_id_in_the_key_neither_kills_the_worker_nor_stops_recording(net, sessions, make_map, tmp_path):
    """Finding 5: a put on .../agents/99999999999999999999/telemetry raised OverflowError in the
    consumer thread; the thread died and the recording and dashboard froze."""
    hub, member = net
    blob = make_map(1)
    keys = Keys("fisc", "alpha")
    rec_path = tmp_path / "live.mcap"
    recorder = FlightLog(LogSettings(swarm="alpha", sample_period_s=0.2, stale_after_s=3.0), mcap_path=rec_path)
    agg = TelemetryAggregator(None, sample_period_s=0.2)
    pipe = TelemetryPipe(keys, agg, recorder)
    pipe.set_map(decode_map(blob), blob)
    pipe.attach(sessions(hub))
    sender = sessions(member)
    bad_key = "fisc/alpha/agents/99999999999999999999/telemetry"
    try:
        # the subscriber matches once the sessions are connected: resend until the bad message arrives
        assert wait_for(lambda: (sender.put(bad_key, telemetry(7)), pipe.received > 0)[1], timeout_s=10)
        assert pipe.drain(5.0)
        for k in range(5):  # afterwards, a genuine agent
            sender.put(keys.telemetry(3), telemetry(3, t=101.0 + k))
        assert wait_for(lambda: 3 in agg.slots, timeout_s=10), "the monitor stopped ingesting after the bad key"
        assert consumer_alive(pipe)
        assert pipe.worker_errors == 0  # handled as a message naming no agent, not as a crash
        view = pipe.view()
        assert view.n_agents == 1 and view.spoofed >= 1  # counted and shown, never an agent
    finally:
        pipe.close()
        recorder.close()
    rec = read_recording(rec_path)
    ids = np.concatenate([e[2] for e in rec.events if e[0] == "telemetry"])
    assert 3 in ids.tolist() and 0xFFFFFFFF in ids.tolist()  # recording went on past the bad message


class _DiskFullOnce:
    """A recorder whose first telemetry write fails (a disk error); then it records."""

    def __init__(self):
        self.calls = 0
        self.written: list[int] = []

    def write_telemetry(self, recv, ids, payloads):
        self.calls += 1
        if self.calls == 1:
            raise OSError(28, "No space left on device")
        self.written.extend(int(i) for i in ids)

    def write_map(self, t, blob, cmap=None):
        pass

    def publish(self, agg, force=False):
        return False


def test_a_failing_batch_is_counted_shown_and_the_worker_keeps_going(make_map):
    from rich.console import Console

    cmap = decode_map(make_map(1))
    rec = _DiskFullOnce()
    agg = TelemetryAggregator(cmap)
    pipe = TelemetryPipe(Keys("fisc", "alpha"), agg, rec)
    try:
        pipe.offer(100.0, "fisc/alpha/agents/1/telemetry", telemetry(1))
        assert pipe.drain(5.0)
        pipe.offer(100.1, "fisc/alpha/agents/2/telemetry", telemetry(2, t=100.1))
        assert pipe.drain(5.0)
        assert consumer_alive(pipe)
        assert pipe.worker_errors == 1 and pipe.lost_to_errors == 1 and "No space left" in pipe.last_error
        assert rec.written == [2] and 2 in agg.slots and 1 not in agg.slots
        console = Console(record=True, width=160)
        console.print(render(pipe.view(), agg.fields(), cmap, pipe.dropped, "t", pipe.worker_errors, pipe.last_error))
        text = console.export_text()
        assert "worker errors" in text and "No space left" in text
    finally:
        pipe.close()


def test_forged_agent_ids_are_capped_and_counted(make_map):
    """Finding 7: 1.2M forged agent ids were all shown; now at most max_agents are tracked."""
    cmap = decode_map(make_map(1))
    agg = TelemetryAggregator(cmap, max_agents=50)
    n = 5000
    ids = np.arange(n)
    agg.ingest(np.full(n, 100.0), ids, [telemetry(int(i)) for i in ids])
    v = agg.view(100.0)
    assert v.n_agents == 50 and len(agg.slots) == 50 and len(agg.latest) <= 128
    assert v.over_cap == n - 50 and any("agent ids refused" in a for a in v.alarms)
    agg.ingest([100.5], [7], [telemetry(7, t=100.5)])  # a tracked agent still updates
    assert agg.view(100.5).over_cap == n - 50


def test_a_roster_shows_only_its_agents():
    roster = AgentRoster.parse("1-10, 20,15-16")
    assert roster.spec() == "1-10,15-16,20"
    np.testing.assert_array_equal(roster.contains(np.array([0, 1, 10, 11, 15, 16, 17, 20, 21, 2**40])),
                                  [False, True, True, False, True, True, False, True, False, False])
    agg = TelemetryAggregator(None, roster=roster)
    agg.ingest([1.0, 1.0, 1.0], [5, 11, 20], [telemetry(5), telemetry(11), telemetry(20)])
    v = agg.view(1.0)
    assert sorted(agg.slots) == [5, 20] and v.off_roster == 1 and any("not on the roster" in a for a in v.alarms)
    for bad in ("", "a-b", "5-1", "-3", "4294967295"):
        with pytest.raises(ValueError):
            AgentRoster.parse(bad)


def test_the_monitor_refuses_an_unsigned_map_unless_allowed(net, sessions, make_map):
    """Finding 6: a monitor without --trusted-key switched to any announced unsigned map."""
    hub, member = net
    keys = Keys("fisc", "alpha")
    server = MapServer(sessions(hub), "alpha", announce_period_s=0.2)
    mon = sessions(member)
    try:
        server.serve(make_map(100))  # signed: the positive control
        assert wait_for(lambda: fetch_map(mon, keys, None, timeout_s=1.0) is not None)
        cmap, blob = fetch_map(mon, keys, None)
        assert cmap.signed and cmap.map_version == 100
        agg = TelemetryAggregator(None)
        pipe = TelemetryPipe(keys, agg)
        pipe.set_map(cmap, blob)
        follower = MapFollower(mon, keys, pipe, None, cmap.map_version)
        server.serve(make_map(200, signing_key=None))  # an unsigned, newer map is announced
        assert wait_for(lambda: 200 in follower.refused, timeout_s=10), "the unsigned map was not fetched and refused"
        assert agg.cmap.map_version == 100
        with pytest.raises(MapError, match="unsigned"):
            fetch_map(mon, keys, None, timeout_s=2.0)
        got = fetch_map(mon, keys, None, timeout_s=2.0, allow_unsigned=True)
        assert got is not None and got[0].map_version == 200 and not got[0].signed
        follower.close()
        pipe.close()
    finally:
        server.close()


def test_monitor_cli_records_its_map_file_and_refuses_an_unsigned_one(net, make_map, tmp_path, capsys):
    from fisc_ground.cli import main

    hub, _ = net
    signed, unsigned = tmp_path / "signed.fiscmap", tmp_path / "unsigned.fiscmap"
    signed.write_bytes(make_map(3))
    unsigned.write_bytes(make_map(4, signing_key=None))
    rec = tmp_path / "m.mcap"
    base = ["monitor", "--swarm", "alpha", "--zenoh-config", str(hub), "--duration", "0.3"]
    assert main([*base, "--map", str(signed), "--record", str(rec)]) == 0
    assert read_recording(rec).maps() == [signed.read_bytes()]  # replay needs the map in the recording
    assert main([*base, "--map", str(unsigned)]) == 2  # invalid input
    assert "the map is unsigned" in capsys.readouterr().err
    assert main([*base, "--map", str(unsigned), "--allow-unsigned"]) == 0


def test_status_listener_caps_forged_agent_ids(net, sessions):
    from fisc_ground.zenoh.fleet import TelemetryListener

    hub, member = net
    keys = Keys("fisc", "alpha")
    listener = TelemetryListener(sessions(hub), keys, max_agents=3)
    sender = sessions(member)
    try:
        assert wait_for(lambda: (sender.put(keys.telemetry(0), telemetry(0)), 0 in listener.snapshot())[1])
        for aid in range(1, 20):
            sender.put(keys.telemetry(aid), telemetry(aid))
        assert wait_for(lambda: listener.over_cap >= 17)
        assert sorted(listener.snapshot()) == [0, 1, 2]
    finally:
        listener.close()
