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

import os
import time

import pytest

from .evidence import EXCURSION_MAX_S, emulated_holds, read_evidence
from .lab import FaultLab, ground, listening, router_configs
from .outcomes import (cut_the_link, fleet_kept_map_and_counted, ground_hears_everyone_again,
                       ground_hears_nobody_and_alarms)
from ..e2e.conftest import cli, poll

pytestmark = pytest.mark.slow

SWARM = "linkloss"
N_AGENTS = int(os.environ.get("FISC_FAULT_LINK_AGENTS", "20"))
"""Emulated vehicles (ids 0..N-1), the issue's 20 (2026-12-05: 50 s, every agent heard again 0.68 s
after the router's return)."""
DURATION_S = 42


@pytest.fixture(scope="module")
def outage(tmp_path_factory):
    lab = FaultLab(tmp_path_factory.mktemp("linkloss"), SWARM)
    try:
        lab.prepare()
        port, router_cfg, client_cfg = router_configs(lab)
        router = lab.start("router", ground("router", "--config", router_cfg))
        assert poll(lambda: listening(port), 30), lab.procs.report()
        recorder = lab.monitor("recorder", lab.dir / "recorder.mcap", "--zenoh-config", client_cfg)
        emulate = lab.start("emulate", cli("fisc-sim") + [
            "emulate", "--map", lab.map, "--agents", N_AGENTS, "--duration", DURATION_S, "--swarm", SWARM,
            "--zenoh-config", client_cfg, "--trusted-key", lab.pub, "--mode", "staggered", "--no-compare",
            "--no-figures", "-q", "-o", lab.dir / "emu"])
        # the fleet is up and heard through the router, and has flown a little
        assert poll(lambda: set(range(N_AGENTS)) <= lab.heard(client_cfg), 60, period_s=0.0), lab.procs.report()
        time.sleep(4.0)
        kill, restarted_s = cut_the_link(lab, router, port, router_cfg)
        ran_to_the_end = emulate.alive
        assert poll(lambda: not emulate.alive, DURATION_S + 60, period_s=0.5), lab.procs.report()
        assert lab.interrupt(recorder) == 0, recorder.log_tail()
        return {"lab": lab, "kill": kill, "restarted_s": restarted_s, "ev": read_evidence(lab.dir / "recorder.mcap"),
                "emulate": emulate, "ran_to_the_end": ran_to_the_end}
    finally:
        lab.stop_all()


def test_while_the_router_is_down_the_ground_hears_nobody_and_alarms(outage):
    ground_hears_nobody_and_alarms(outage, range(N_AGENTS))


def test_after_the_restart_the_ground_hears_everyone_within_5_s_and_the_alarm_clears(outage):
    ground_hears_everyone_again(outage, range(N_AGENTS))


def test_the_fleet_never_noticed_the_outage(outage):
    ev, lab = outage["ev"], outage["lab"]
    fleet_kept_map_and_counted(outage, range(N_AGENTS))
    breaches = ev.duct_breaches(range(N_AGENTS), EXCURSION_MAX_S)
    assert not breaches, f"left the duct (start, duration, geofence acting): {breaches}"
    assert outage["ran_to_the_end"], "fisc-sim emulate ended before the outage was judged"
    assert outage["emulate"].popen.returncode == 0, outage["emulate"].log_tail()
    holds = emulated_holds(lab.dir / "emu")  # the fleet never holds (or the machine starved it: xfail)
    if holds:
        pytest.xfail(holds)
