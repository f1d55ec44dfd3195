"""The Zenoh link between the ground and three real PX4's agents lost for 10 s, by killing the
router it runs through (issue 38, item 3: "a router" and the 10 s link loss, "once with three real
PX4"); ``test_link_loss.py`` is the emulated flight.

Real processes, the field set-up of docs/zenoh.md on loopback (router + clients, no gossip, so
nothing bypasses the router):

    router     fisc-ground router --config router.json5      (listens on a free port)
    recorder   fisc-ground monitor --zenoh-config client.json5 --record   (the ground)
    publisher  fisc-ground publish MAP --zenoh-config client.json5
    PX4 x 3    start.sh 3 (``sitl_kit.Px4Sitl``), 3 m apart, stock parameters but the offboard-loss
               failsafe of docs/deployment.md (``test_px4_kills.FAILSAFE_PARAMS``)
    agents     fisc-agent --go --zenoh-config client.json5, one pass then the exit's hold

Once every agent is in the air, heard through the router, and one has entered the duct, the router
is killed at a random moment (seed ``FISC_FAULT_SEED``) and started again 10 s later.  What must
happen (``outcomes``: the same as for the emulated fleet, plus the autopilots' view):

- while the router is down the ground hears nobody and raises ``every agent stale`` within
  stale-after (3 s) + 2 s;
- within 5 s of the restarted router accepting connections the ground hears every agent again
  and the alarm clears;
- the fleet does not notice: each agent keeps its map and counts its telemetry through the outage,
  none holds in a failsafe, every agent process still runs, no PX4 logs a failsafe (ULog), and no
  vehicle goes more than 0.3 m beyond the wall by its agent's view (PX4's estimate,
  ``sitl_kit.MAX_EXCURSION_M``), nor more than that plus the estimator's error by SIH's ground truth
  (1.55 m, ``sitl_kit.TRUTH_EXCURSION_M``).
"""

from __future__ import annotations

import math

import pytest

from fisc_ground.fields.flight_score import score_track

from .evidence import read_evidence
from .lab import FaultLab, ground, listening, router_configs
from .outcomes import (REHEAR_S, cut_the_link, fleet_kept_map_and_counted, ground_hears_everyone_again,
                       ground_hears_nobody_and_alarms)
from .test_px4_kills import FAILSAFE_PARAMS, N
from ..e2e.conftest import poll
from ..e2e.sitl_kit import (MAP_ANCHOR, MAX_EXCURSION_M, TRUTH_EXCURSION_M, Px4Sitl, Track, px4_ulog,
                            truth_on_wall_clock, truth_pass, ulog_summary, view_excursion_m)

pytestmark = [pytest.mark.sitl, pytest.mark.slow, pytest.mark.timeout(300)]

SWARM = "px4linkloss"


@pytest.fixture(scope="module")
def outage(tmp_path_factory, shared_path) -> dict:
    lab = FaultLab(tmp_path_factory.mktemp("px4linkloss"), SWARM)
    lab.prepare()
    logs = [lab.dir / f"agent{i}.csv" for i in range(N)]
    port, router_cfg, client_cfg = router_configs(lab)
    zenoh = ("--zenoh-config", client_cfg)
    with Px4Sitl(shared_path("sitl", "px4"), lab.dir, N, spacing_m=3.0, params=FAILSAFE_PARAMS,
                 ready_timeout_s=120.0) as run:
        try:
            router = lab.start("router", ground("router", "--config", router_cfg))
            assert poll(lambda: listening(port), 30), lab.procs.report()
            recorder = lab.monitor("recorder", lab.dir / "recorder.mcap", *zenoh)
            lab.start("publisher", ground("publish", lab.map, "--swarm", SWARM, *zenoh))
            agents = lab.start_px4_agents(logs, MAP_ANCHOR, *zenoh)
            for agent in agents:
                lab.wait_in_air(agent, 120)
            assert poll(lambda: set(range(N)) <= lab.heard(client_cfg), 60, period_s=0.0), lab.procs.report()
            assert poll(lambda: "mission JOIN -> FLOW" in "".join(a.log_tail(400) for a in agents), 60,
                        period_s=0.2), lab.procs.report()
            kill, restarted_s = cut_the_link(lab, router, port, router_cfg)
            alive = [a.alive for a in agents]
            assert lab.interrupt(recorder) == 0, recorder.log_tail()
        finally:
            lab.stop_all()
        ulogs = [px4_ulog(run, i) for i in range(N)]
    return {"lab": lab, "kill": kill, "restarted_s": restarted_s, "ev": read_evidence(lab.dir / "recorder.mcap"),
            "alive": alive, "ulogs": ulogs, "logs": logs}


def test_while_the_router_is_down_the_ground_hears_nobody_and_alarms(outage):
    ground_hears_nobody_and_alarms(outage, range(N))


def test_after_the_restart_the_ground_hears_everyone_within_5_s_and_the_alarm_clears(outage):
    ground_hears_everyone_again(outage, range(N))


def test_the_fleet_and_its_autopilots_never_noticed_the_outage(outage):
    ev, kill, back = outage["ev"], outage["kill"], outage["restarted_s"]
    fleet_kept_map_and_counted(outage, range(N))
    assert all(outage["alive"]), outage["lab"].procs.report()
    for i in range(N):
        held = ev.agents[i].between(kill.t_s, back + REHEAR_S).failsafe_holds_s()
        assert not held.size, f"agent {i} held in a failsafe around the outage: {held[:5] - kill.t_s}"
        u = ulog_summary(outage["ulogs"][i])
        assert not u.failsafe_seen and u.gps_fused, (i, u)
    duct = outage["lab"].duct()
    ref, wall, scale = duct.ref, duct.wall, duct.scale
    excursion, view = {}, {}
    for i in range(N):
        track = Track.read(outage["logs"][i])
        view[i] = view_excursion_m(track, ref, scale, wall)
        truth = truth_on_wall_clock(outage["ulogs"][i], track, MAP_ANCHOR)
        assert truth.fit_rms_m < 0.1, (i, truth.fit_rms_m)  # the clocks matched: the truth is on the wall clock
        t, pos, vel, states = truth_pass(truth, track=track)
        excursion[i] = score_track(t, pos, vel, states, ref, scale, wall=wall).max_excursion_m
    print(f"largest distance beyond the wall in the pass [m] (nan: not in the duct), by the agent's view (PX4's "
          f"estimate): {view}; by SIH's ground truth: {excursion}")
    assert all(math.isnan(e) or e < MAX_EXCURSION_M for e in view.values()), view
    assert all(math.isnan(e) or e < TRUTH_EXCURSION_M for e in excursion.values()), excursion
    assert not all(math.isnan(e) for e in excursion.values()), "no vehicle entered the duct: nothing judged"
    in_duct_during = [i for i in range(N) if "FLOW" in ev.agents[i].between(kill.t_s - 2.0, kill.t_s).states()]
    print(f"in the duct when the link went: agents {in_duct_during}")
    assert in_duct_during, "no vehicle was in the duct when the link was cut: the outage tested nothing in flight"
