"""Over real Zenoh sessions: a late agent learns the latest go from the ground's re-published state,
old commands stay refused, clock skew, and the ground's health / silence alarms."""

from __future__ import annotations

from fisc_agent.flight.readiness import HealthKind, HealthProblem

import time

import numpy as np

from fisc_agent.zenoh import telemetry_codec as tc
from fisc_agent.zenoh.fleet_commands import encode_command, key_id_of
from fisc_agent.zenoh.keys import Keys
from fisc_agent.zenoh.link import AgentZenohLink
from fisc_ground.monitor.aggregator import TelemetryAggregator
from fisc_ground.zenoh.command_relay import CommandRelay
from fisc_ground.zenoh.fleet import TelemetryListener, make_command, matching, send_command, status_report

from .conftest import snap, wait_for

KEYS = Keys("fisc", "alpha")


def agent(session, agent_id, ground_key, got, **kw):
    return AgentZenohLink(None, "alpha", agent_id, [ground_key[1]], False, lambda m: None, got.append,
                          session=session, **kw).start()


def test_a_late_agent_learns_the_latest_go_and_hold_and_no_old_command_comes_back(net, sessions, ground_key):
    hub, member = net
    ground = sessions(hub)
    relay = CommandRelay(ground, "alpha", trusted_keys=[ground_key[1]], period_s=0.3)
    early: list = []
    first = agent(sessions(member), 1, ground_key, early)
    now = time.time()
    go = make_command("go", "alpha", now_unix_s=now - 1)
    hold = make_command("hold", "alpha", targets=(2,), now_unix_s=now)
    assert send_command(ground, KEYS, go, ground_key[0]).matched
    send_command(ground, KEYS, hold, ground_key[0])
    assert wait_for(lambda: [c.name for c in early] == ["go"])
    assert wait_for(lambda: len(relay.latest.commands()) == 2)
    # agent 2 starts after both commands: it learns the go, then its own hold, in that order
    late: list = []
    second = agent(sessions(member), 2, ground_key, late)
    assert wait_for(lambda: [c.name for c in late] == ["go", "hold"])
    assert late[1].addressed and not late[0].addressed
    time.sleep(1.0)  # several re-publications later: nothing twice, no refusal, agent 1 not given agent 2's hold
    assert [c.name for c in late] == ["go", "hold"] and [c.name for c in early] == ["go"]
    assert second.commands.stats.refused == 0 and first.commands.stats.refused == 0
    # the old go captured and replayed live is refused (its key's floor), and counted
    pub = ground.declare_publisher(KEYS.cmd)
    assert wait_for(lambda: matching(pub))
    pub.put(encode_command(go, ground_key[0]))
    assert wait_for(lambda: second.commands.stats.last_refusal == "replay")
    # a restarted agent 2 with its floors from the state file learns nothing again
    floors = second.commands.floors
    assert floors == {key_id_of(ground_key[1]): hold.seq}
    second.close()
    again: list = []
    restarted = agent(sessions(member), 2, ground_key, again, command_floors=floors)
    assert wait_for(lambda: restarted.commands.stats.bundles >= 2)
    assert again == [] and restarted.commands.stats.refused == 0
    for link in (first, restarted):
        link.close()
    pub.undeclare()
    relay.close()


def test_a_go_older_than_the_standing_window_does_not_launch_a_fresh_agent(net, sessions, ground_key):
    hub, member = net
    ground = sessions(hub)
    relay = CommandRelay(ground, "alpha", trusted_keys=[ground_key[1]], period_s=0.2)
    pub = ground.declare_publisher(KEYS.cmd)
    got: list = []
    link = agent(sessions(member), 1, ground_key, got)  # subscribes: it hears the old go live too
    assert wait_for(lambda: matching(pub))
    pub.put(encode_command(make_command("go", "alpha", now_unix_s=time.time() - 200), ground_key[0]))
    assert wait_for(lambda: len(relay.latest.commands()) == 1)
    late: list = []
    fresh = agent(sessions(member), 2, ground_key, late)
    assert wait_for(lambda: fresh.commands.stats.bundles >= 3)
    assert late == [] and got == []
    s = fresh.commands.stats
    assert (s.refused, s.last_refusal, s.last_refused_command) == (1, "stale", "go")  # once, not per re-publication
    for x in (link, fresh, relay):
        x.close()
    pub.undeclare()


def test_a_ten_second_clock_skew_either_way_breaks_no_command(net, sessions, ground_key):
    hub, member = net
    ground = sessions(hub)
    shared = sessions(member)
    got = {-10: [], 10: []}
    links = [agent(shared, i, ground_key, got[skew], command_clock=lambda s=skew: time.time() + s)
             for i, skew in ((1, -10), (2, 10))]
    for name in ("hold", "land"):
        send_command(ground, KEYS, make_command(name, "alpha"), ground_key[0])
    assert wait_for(lambda: all([c.name for c in v] == ["hold", "land"] for v in got.values()))
    assert all(link.commands.stats.refused == 0 for link in links)
    for link in links:
        link.close()


def test_status_and_monitor_raise_health_authority_and_every_agent_stale_alarms(net, sessions):
    hub, member = net
    ground = sessions(hub)
    shared = sessions(member)
    listener = TelemetryListener(ground, KEYS)
    problems = {1: dict(battery_pct=18.0), 2: dict(authority="hands-off", battery_pct=80.0),
                3: dict(health_problems=(HealthProblem(HealthKind.ESTIMATOR, "estimator: pos_horiz_abs not OK"),),
                        battery_pct=None)}
    links = [AgentZenohLink(None, "alpha", i, None, True, lambda m: None, lambda c: None, session=shared).start()
             for i in problems]
    for i, link in zip(problems, links):
        link.start_telemetry(lambda i=i: snap(agent_id=i, landed="in-air", **problems[i]), 20)
    assert wait_for(lambda: len(listener.snapshot()) == 3)
    report = status_report(listener.snapshot(), time.time())
    by_id = {a["id"]: a for a in report["agents"]}
    assert (by_id[1]["battery_pct"], by_id[2]["authority"], by_id[3]["health"]) == (18.0, "hands-off", ["estimator"])
    assert by_id[3]["battery_pct"] is None and by_id[1]["landed"] == "in-air" and not by_id[1]["stale"]
    text = "\n".join(report["alarms"])
    assert "low battery (< 30 %): agents 1 (18 %)" in text and "hands-off" in text and "agents 2" in text
    assert "unhealthy estimator: agents 3" in text and "stale" not in text
    # the monitor's aggregator, fed the same messages, says the same; then the fleet falls silent
    agg = TelemetryAggregator(None, stale_after_s=3.0)
    latest = listener.snapshot()
    ids = sorted(latest)
    agg.ingest(np.array([latest[i][1] for i in ids]), np.array(ids), [tc.encode(latest[i][0]) for i in ids])
    assert {"low battery", "hands-off", "unhealthy estimator"} <= {a.split(" (")[0].split(":")[0] for a in agg.view().alarms}
    for link in links:
        link.close()
    later = time.time() + 3.5
    assert any(a.startswith("every agent stale: none of the 3 agents") for a in agg.view(later).alarms)
    assert not any("low battery" in a for a in agg.view(later).alarms)  # a stale agent's health is old news
    assert status_report(listener.snapshot(), later)["alarms"][0].startswith("every agent stale")
    some = status_report({**listener.snapshot(), 9: (latest[1][0], later)}, later)
    assert some["alarms"][0] == "stale (not heard for 3 s): agents 1, 2, 3"
    listener.close()
