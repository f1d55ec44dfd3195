"""Fault injection through a router: the Zenoh link between the ground and the fleet is lost for
10 s by killing the router it runs through (kill -9 at a seeded random moment), then the router
is started again (issue 38, item 3: "a router" and "the loss of the link for 10 s").

Real processes, the field set-up of docs/zenoh.md on loopback (router + clients, no gossip,
so nothing bypasses the router):

    router     fisc-ground router --config router.json5      (listens on a free port)
    recorder   fisc-ground monitor --zenoh-config client.json5 --record   (the ground)
    emulate    fisc-sim emulate --agents N --swarm --zenoh-config client.json5   (the fleet)

What must happen:

- while the router is down the ground hears nobody (the link is really cut) and raises
  ``every agent stale`` within stale-after (3 s) + 2 s;
- the fleet does not notice: no agent holds (``evidence.emulated_holds``: a hold only a starved
  emulator causes, during a reported stall, makes the case xfail "inconclusive"), changes its
  map or leaves the duct (``evidence.EXCURSION_MAX_S``); each keeps counting its telemetry (its
  sequence after the outage is past the one before by at least 3 Hz x the outage), and
  ``fisc-sim emulate`` ends normally;
- within 5 s of the restarted router accepting connections the ground hears every agent again
  and the alarm clears.
"""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest

from fisc_agent.zenoh.telemetry_codec import sha_hex

from .evidence import EXCURSION_MAX_S, emulated_holds, read_evidence
from .lab import FaultLab, ground, listening
from ..e2e.conftest import cli, free_tcp_port, poll, run_cli

pytestmark = pytest.mark.slow

SWARM = "linkloss"
N_AGENTS = int(os.environ.get("FISC_FAULT_LINK_AGENTS", "6"))
"""Emulated vehicles (ids 0..N-1)."""
OUTAGE_S = 10.0
"""Time between the router's kill and its restart [s]."""
REHEAR_S = 5.0
"""Every agent heard again within this long after the restart [s]."""
DURATION_S = 42


def _configs(lab: FaultLab) -> tuple:
    port = free_tcp_port()
    router = lab.dir / "router.json5"
    router.write_text(json.dumps({"mode": "router", "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
                                  "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}))
    client = lab.dir / "client.json5"
    client.write_text(json.dumps({"mode": "client", "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
                                  "scouting": {"multicast": {"enabled": False}}}))
    return port, router, client


def _fleet_heard(client_cfg) -> bool:
    out = run_cli(ground("status", "--swarm", SWARM, "--zenoh-config", client_cfg, "--json", "--wait", "1"))
    return out.returncode == 0 and len(json.loads(out.stdout)["agents"]) >= N_AGENTS


@pytest.fixture(scope="module")
def outage(tmp_path_factory):
    lab = FaultLab(tmp_path_factory.mktemp("linkloss"), SWARM)
    try:
        lab.prepare()
        port, router_cfg, client_cfg = _configs(lab)
        router = lab.start("router", ground("router", "--config", router_cfg))
        assert poll(lambda: listening(port), 30), lab.procs.report()
        recorder = lab.monitor("recorder", lab.dir / "recorder.mcap", "--zenoh-config", client_cfg)
        emulate = lab.start("emulate", cli("fisc-sim") + [
            "emulate", "--map", lab.map, "--agents", N_AGENTS, "--duration", DURATION_S, "--swarm", SWARM,
            "--zenoh-config", client_cfg, "--trusted-key", lab.pub, "--mode", "staggered", "--no-compare",
            "--no-figures", "-q", "-o", lab.dir / "emu"])
        # the fleet is up and heard through the router, and has flown a little
        assert poll(lambda: _fleet_heard(client_cfg), 60, period_s=0.0), lab.procs.report()
        time.sleep(4.0)
        kill = lab.kills.kill_at("router", router, 0.0, 2.0)
        time.sleep(max(0.0, kill.t_s + OUTAGE_S - time.time()))
        lab.start("router-restarted", ground("router", "--config", router_cfg))
        assert poll(lambda: listening(port), 30, period_s=0.05), lab.procs.report()
        restarted_s = time.time()  # the link is back when the router accepts connections again
        print(f"fault: router restarted, listening {restarted_s - kill.t_s:.2f} s after its kill")
        time.sleep(REHEAR_S + 4.0)
        ran_to_the_end = emulate.alive
        assert poll(lambda: not emulate.alive, DURATION_S + 60, period_s=0.5), lab.procs.report()
        assert lab.interrupt(recorder) == 0, recorder.log_tail()
        return {"lab": lab, "kill": kill, "restarted_s": restarted_s, "ev": read_evidence(lab.dir / "recorder.mcap"),
                "emulate": emulate, "ran_to_the_end": ran_to_the_end}
    finally:
        lab.stop_all()


def test_while_the_router_is_down_the_ground_hears_nobody_and_alarms(outage):
    ev, kill, back = outage["ev"], outage["kill"], outage["restarted_s"]
    assert set(range(N_AGENTS)) <= set(ev.agents), sorted(ev.agents)
    during = {i: int(s.between(kill.t_s + 0.5, back).recv_s.size) for i, s in ev.agents.items()}
    assert not any(during.values()), f"telemetry crossed a dead router: {during}"
    lines = ev.alarm_lines(kill.t_s, kill.t_s + 3.0 + 2.0)
    assert any(line.startswith("every agent stale") for line in lines), ev.alarms


def test_after_the_restart_the_ground_hears_everyone_within_5_s_and_the_alarm_clears(outage):
    ev, back = outage["ev"], outage["restarted_s"]
    late = {}
    for i in range(N_AGENTS):
        after = ev.agents[i].between(back, back + REHEAR_S + 4.0).recv_s
        if not after.size or after[0] > back + REHEAR_S:
            late[i] = None if not after.size else round(float(after[0] - back), 2)
    assert not late, f"not heard within {REHEAR_S} s of the router's restart: {late}"
    settled = [lines for t, lines in ev.alarms if back < t <= back + REHEAR_S + 4.0]
    assert settled and not any(line.startswith(("every agent stale", "stale")) for line in settled[-1]), ev.alarms


def test_the_fleet_never_noticed_the_outage(outage):
    ev, kill, back, lab = outage["ev"], outage["kill"], outage["restarted_s"], outage["lab"]
    for i in range(N_AGENTS):
        s = ev.agents[i]
        assert set(x for x in sha_hex(s.records) if x) == {lab.sha}, f"agent {i} flew another map"
        before, after = s.records["seq"][s.recv_s < kill.t_s], s.records["seq"][s.recv_s > back]
        assert before.size and after.size, f"agent {i} not heard on both sides of the outage"
        assert int(np.int64(after[0]) - np.int64(before[-1])) >= 3 * (back - kill.t_s), \
            f"agent {i} stopped counting during the outage ({before[-1]} -> {after[0]})"
    breaches = ev.duct_breaches(range(N_AGENTS), EXCURSION_MAX_S)
    assert not breaches, f"left the duct (start, duration, geofence acting): {breaches}"
    assert outage["ran_to_the_end"], "fisc-sim emulate ended before the outage was judged"
    assert outage["emulate"].popen.returncode == 0, outage["emulate"].log_tail()
    holds = emulated_holds(lab.dir / "emu")  # the fleet never holds (or the machine starved it: xfail)
    if holds:
        pytest.xfail(holds)
