"""A fleet hold sent while the agent arms its PX4 (real PX4 SIH, stock parameters; docs/deployment.md, the
failsafe table's "fleet hold while arming").

The hold command is started as soon as the agent logs its arm request; it reaches the agent about 0.6 s
later, before PX4's answer (about 1 s after the request) on this host, so PX4 arms the vehicle just after the
hold (printed: the hold's state and how often PX4 armed; under load it may land after the answer, in
TAKEOFF).  Whichever way the race goes, judged from PX4's own console and the agent's flight log: PX4 never activates a failsafe (its offboard-loss failsafe took such a
vehicle, armed without setpoints, on 2026-12-07), the agent never goes hands-off, and a swarm-wide
``resume`` flies the vehicle (re-armed if PX4's pre-flight disarm disarmed it meanwhile).
"""

from __future__ import annotations

import subprocess
import time

import pytest

from .conftest import Processes, child_env, cli, poll, run_cli
from .sitl_kit import MAP_ANCHOR, Px4Sitl, ground, latest_states, mission_story, ok, signed_map_on_zenoh

pytestmark = [pytest.mark.sitl, pytest.mark.slow, pytest.mark.timeout(300)]

SWARM = "armhold"
HELD_S = 14.0
"""How long the vehicle is held on the ground: past PX4's pre-flight disarm (``COM_DISARM_PRFLT``, 10 s) [s]."""


def test_px4_fleet_hold_while_arming_leaves_no_failsafe_and_resume_flies(shared_path, tmp_path):
    d = tmp_path
    g = signed_map_on_zenoh(d)
    logs = [d / "agent0.csv"]
    sitl = Px4Sitl(shared_path("sitl", "px4"), d, 1)
    with sitl:
        procs = Processes(d / "logs")
        try:
            procs.start("publisher", ground("publish", g.served, "--swarm", SWARM, "--zenoh-config", g.hub))
            procs.start("agent0", cli("fisc-agent") + [
                "--go", "--swarm", SWARM, "--zenoh-config", g.member, "--trusted-key", g.ground_pub,
                "--mavlink", "udpin:0.0.0.0:14540", "--id", 0, "--autopilot", "px4",
                "--geodetic-anchor", MAP_ANCHOR, "--flight-log", logs[0]])
            agent_log = d / "logs" / "agent0.log"
            asked = poll(lambda: agent_log.exists() and "requesting arm" in agent_log.read_text(), 120.0, 0.02)
            assert asked, procs.report()
            hold = subprocess.run([str(a) for a in ground("cmd", "hold", "--swarm", SWARM, "--zenoh-config", g.member,
                                                          "--key", d / "ground.key", "--ack-wait", "8")],
                                  capture_output=True, text=True, timeout=60, env=child_env())
            assert hold.returncode == 0 and '"acked": [0]' in hold.stdout, (hold.stdout, hold.stderr)
            time.sleep(HELD_S)
            assert latest_states(logs) == ["HOLD"], mission_story(logs)
            ok(run_cli(ground("cmd", "resume", "--swarm", SWARM, "--zenoh-config", g.member,
                              "--key", d / "ground.key", "--ack-wait", "8")))
            flying = poll(lambda: latest_states(logs)[0] == "JOIN", 60.0, 0.2)
            story = mission_story(logs)
            assert flying, f"{procs.report()}\n{story}"
        finally:
            procs.stop_all(order=lambda p: 0 if p.name.startswith("agent") else 1)
    console = sitl.console(0)
    armed = console.count("Armed by external command")
    where = "in ARM" if "fleet hold (on the ground)" in story else "after the take-off began"
    print(f"\nthe hold landed {where}; PX4 armed {armed} time(s) (2: the arm landed after the hold and PX4's "
          f"pre-flight disarm came before the resume); {story}")
    assert "Failsafe activated" not in console, console[-3000:]
    assert "pilot override" not in story and "hands off" not in story, story
    assert armed in (1, 2), console[-3000:]
