"""Fleet commands end to end (signed, replay/stale protection, acks) and fleet status."""

from __future__ import annotations

import time

import pytest
from nacl.signing import SigningKey

from fisc_agent.zenoh import telemetry_codec as tc
from fisc_agent.zenoh.fleet_commands import encode_command
from fisc_agent.zenoh.keys import Keys
from fisc_agent.zenoh.link import AgentZenohLink
from fisc_ground.zenoh.fleet import TelemetryListener, matching, make_command, send_command, status_report

from .conftest import snap, wait_for


@pytest.fixture()
def fleet(net, sessions, ground_key):
    hub, member = net
    ground = sessions(hub)
    shared = sessions(member)
    got = {i: [] for i in range(3)}
    links = [AgentZenohLink(None, "alpha", i, [ground_key[1]], False, lambda m: None, got[i].append,
                           session=shared).start() for i in range(3)]
    yield ground, links, got
    for link in links:
        link.close()


def test_signed_command_reaches_every_agent_and_is_acknowledged(fleet, ground_key):
    ground, links, got = fleet
    keys = Keys("fisc", "alpha")
    listener = TelemetryListener(ground, keys)
    cmd = make_command("hold", "alpha")
    for link in links:
        link.start_telemetry(lambda: snap(position_map_m=(1, 0, 0)), rate_hz=20)
    res = send_command(ground, keys, cmd, ground_key[0], ack_timeout_s=10, listener=listener)
    assert res.matched
    assert wait_for(lambda: all(len(v) == 1 for v in got.values()))
    assert all(v[0].name == "hold" and v[0].signed for v in got.values())
    assert set(res.acked) == {0, 1, 2}
    listener.close()


def test_targeted_command_only_reaches_its_agent(fleet, ground_key):
    ground, links, got = fleet
    send_command(ground, Keys("fisc", "alpha"), make_command("land", "alpha", targets=(0, 2)), ground_key[0])
    assert wait_for(lambda: len(got[2]) == 1 and len(got[0]) == 1)
    time.sleep(0.3)
    assert got[1] == [] and links[1].commands.stats.refused == 0  # another agent's command is no refusal
    assert got[0][0].addressed and got[0][0].targets == (0, 2)


def test_replayed_stale_forged_and_foreign_commands_are_ignored(fleet, ground_key):
    ground, links, got = fleet
    pub = ground.declare_publisher("fisc/alpha/cmd")
    assert wait_for(lambda: matching(pub))
    now = time.time()
    fresh = encode_command(make_command("hold", "alpha", now_unix_s=now), ground_key[0])
    pub.put(fresh)
    assert wait_for(lambda: all(len(v) == 1 for v in got.values()))
    pub.put(fresh)  # replayed
    pub.put(encode_command(make_command("resume", "alpha", now_unix_s=now - 3600), ground_key[0]))  # stale
    pub.put(encode_command(make_command("land", "alpha", now_unix_s=now + 1), SigningKey.generate().encode()))
    pub.put(encode_command(make_command("land", "alpha", now_unix_s=now + 2), None))  # unsigned
    pub.put(encode_command(make_command("land", "beta", now_unix_s=now + 3), ground_key[0]))  # other swarm
    assert wait_for(lambda: all(link.commands.stats.refused == 5 for link in links))
    last = links[0].commands.stats
    assert (last.last_refusal, last.last_refused_command) == ("swarm", "land")
    assert all([c.name for c in v] == ["hold"] for v in got.values())
    pub.put(encode_command(make_command("resume", "alpha", now_unix_s=now + 4), ground_key[0]))
    assert wait_for(lambda: all([c.name for c in v] == ["hold", "resume"] for v in got.values()))
    pub.undeclare()


def test_status_lists_agents_with_the_contract_keys(fleet):
    ground, links, _ = fleet
    listener = TelemetryListener(ground, Keys("fisc", "alpha"))
    sha = "ab" * 32
    for link in links:
        link.start_telemetry(lambda: snap(map_sha256=sha, position_map_m=(1.0, 2.0, 3.0)), 20)
    assert wait_for(lambda: len(listener.snapshot()) == 3)
    report = status_report(listener.snapshot(), time.time())
    assert [a["id"] for a in report["agents"]] == [0, 1, 2]
    for a in report["agents"]:
        assert {"id", "state", "map_sha256", "last_seen_s"} <= set(a)
        assert a["state"] == "FLOW" and a["map_sha256"] == sha and 0 <= a["last_seen_s"] < 10
    # a message whose key names another agent than its payload is not believed
    forged = tc.encode(tc.Telemetry(agent_id=1, seq=1, time_s=0, position_m=(0, 0, 0), velocity_m_s=(0, 0, 0)))
    bad = listener.bad
    pub = links[1]._session.declare_publisher("fisc/alpha/agents/9/telemetry")  # noqa: SLF001
    assert wait_for(lambda: matching(pub))
    pub.put(forged)
    assert wait_for(lambda: listener.bad > bad)
    assert 9 not in listener.snapshot()
    pub.undeclare()
    listener.close()


class StandInRunner:
    """What the dispatcher needs of a ``Runner``: ``fleet_command(FleetOrder)``."""

    def __init__(self):
        self.orders = []

    def fleet_command(self, order):
        self.orders.append(order)


def test_start_at_is_a_go_at_its_time_on_the_given_clock_and_a_later_hold_cancels_it():
    from fisc_agent.flight.mission_types import FleetOrder, MissionCommand
    from fisc_agent.zenoh.fleet_commands import FleetCommand
    from fisc_agent.zenoh.runner import CommandDispatcher

    skew = -10.0  # the agent's clock (the autopilot's GNSS time) is 10 s behind the companion's
    runner = StandInRunner()
    d = CommandDispatcher(runner, clock=lambda: time.time() + skew, poll_s=0.02)
    start = time.time() + skew + 0.3
    d(FleetCommand("start-at", "alpha", 1, time.time(), start_at_unix_s=start, targets=(3,), key_id="k1"))
    assert runner.orders == [] and d.pending_start_unix_s == start
    assert wait_for(lambda: runner.orders == [FleetOrder(MissionCommand.GO, True, 1, "k1")], timeout_s=3)
    assert d.pending_start_unix_s is None
    d(FleetCommand("start-at", "alpha", 2, time.time(), start_at_unix_s=time.time() + skew + 0.3))
    d(FleetCommand("resume", "alpha", 3, time.time()))  # a resume does not cancel the start
    d(FleetCommand("hold", "alpha", 4, time.time()))    # a hold does
    time.sleep(0.6)
    assert [o.command for o in runner.orders] == ["go", "resume", "hold"]
    d(FleetCommand("start-at", "alpha", 5, time.time(), start_at_unix_s=time.time() + skew - 5))  # already due
    assert wait_for(lambda: len(runner.orders) == 4 and runner.orders[-1] == FleetOrder(MissionCommand.GO, False, 5))
    d(FleetCommand("takeover", "alpha", 6, time.time(), targets=(3,)))
    assert runner.orders[-1] == FleetOrder(MissionCommand.TAKEOVER, True, 6)
    d.cancel()
