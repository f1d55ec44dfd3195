"""fisc-agent on real ArduCopter SITL (``../shared/sitl/ardupilot``) in GUIDED.

One vehicle from the ground through the duct and out, then a BRAKE hold that keeps its altitude
with no pilot (LOITER would follow the absent throttle stick down); three vehicles with the map
over Zenoh and geodetic anchors.  The truth comes from ArduPilot's DataFlash log (pymavlink's
DFReader): the flight modes it went through and its messages.
"""

from __future__ import annotations

import json

import pytest

from fisc_agent.flight.flightlog import read_flight_log
from fisc_agent.map.codec import load_map
from fisc_ground.maps.duct_wall import duct_wall_from_reference
from fisc_ground.fields.flight_score import score_track
from fisc_ground.reference.builtin import load_builtin

from .conftest import Processes, cli, poll, run_cli
from .sitl_kit import (MAP_ANCHOR, ArduPilotSitl, Track, dataflash_log, dataflash_modes_and_texts, ground, ok,
                       signed_map_on_zenoh)

pytestmark = [pytest.mark.sitl, pytest.mark.slow, pytest.mark.timeout(600)]

GUIDED, BRAKE, LOITER = 4, 17, 5


def _exit_held(log, seconds: float) -> bool:
    try:
        rows = read_flight_log(log)
    except (OSError, KeyError):
        return False
    held = [float(r["time_s"]) for r in rows if r["state"] == "HOLD" and r["mode"] == "hold"]
    return any(r["state"] == "EXIT" for r in rows) and bool(held) and held[-1] - held[0] >= seconds


def _score(log, scale):
    ref = load_builtin("cd_nozzle_inviscid")
    tr = Track.read(log)
    return tr, score_track(tr.t_s, tr.pos_m, tr.vel_m_s, tr.states, ref, scale, wall=duct_wall_from_reference(ref))


def test_one_arducopter_from_the_ground_through_the_duct_and_out_then_brake_holds(shared_path, tmp_path):
    path = tmp_path / "tunnel.fiscmap"
    ok(run_cli(ground("fit", "cd_nozzle_inviscid", "-o", path)))
    log = tmp_path / "agent1.csv"
    with ArduPilotSitl(shared_path("sitl", "ardupilot"), tmp_path, 1) as run:
        procs = Processes(tmp_path / "logs")
        try:
            agent = procs.start("agent1", cli("fisc-agent") + [  # a lone vehicle: no admission windows to wait for
                "--go", "--entry-stagger", "off",
                "--map", path, "--mavlink", "udpin:0.0.0.0:14540", "--id", 1, "--autopilot", "ardupilot",
                "--flight-log", log])
            assert poll(lambda: _exit_held(log, 10.0) or not agent.alive, 180.0, 0.5) and agent.alive, \
                procs.report()
        finally:
            procs.stop_all()
        modes, texts = dataflash_modes_and_texts(dataflash_log(run, 0))
    tr, score = _score(log, load_map(path).scale)
    print(json.dumps({"score": score.as_dict(), "modes": modes}))
    assert score.crossed and not score.held, score
    assert score.max_excursion_m < 0.3 and score.velocity_nrmse <= 0.10, score
    alt_dev, hold_s = tr.hold_altitude_range_m()
    assert hold_s >= 10.0 and alt_dev < 0.5, (alt_dev, hold_s)
    assert GUIDED in modes and modes[-1] == BRAKE and LOITER not in modes, modes
    assert not any("Hit ground" in t or "Crash" in t for t in texts), texts


def test_three_arducopters_over_zenoh_with_geodetic_anchors(shared_path, tmp_path):
    n, d = 3, tmp_path
    g = signed_map_on_zenoh(d)
    served, good, hub, member = g.served, g.good, g.hub, g.member
    logs = [d / f"agent{i}.csv" for i in range(n)]
    with ArduPilotSitl(shared_path("sitl", "ardupilot"), d, n, spacing_m=3.0) as run:
        procs = Processes(d / "logs")
        try:
            procs.start("publisher", ground("publish", served, "--swarm", "apsitl", "--zenoh-config", hub))
            for i in range(n):
                procs.start(f"agent{i}", cli("fisc-agent") + ["--go", 
                    "--swarm", "apsitl", "--zenoh-config", member, "--trusted-key", g.ground_pub,
                    "--mavlink", f"udpin:0.0.0.0:{14540 + i}", "--id", i, "--autopilot", "ardupilot",
                    "--geodetic-anchor", MAP_ANCHOR, "--entry-stagger", 2.0, "--entry-slots", n, "--flight-log", logs[i]])

            def status():
                out = ok(run_cli(ground("status", "--swarm", "apsitl", "--zenoh-config", member, "--json",
                                        "--wait", 1.0)))
                agents = {a["id"]: a for a in json.loads(out)["agents"] if a["last_seen_s"] < 2.5}
                return agents if len(agents) == n and all(a["map_sha256"] == good.sha256 for a in agents.values()) \
                    else None

            assert poll(status, 90.0, 0.0), procs.report()
            assert poll(lambda: all(_exit_held(p, 5.0) for p in logs), 240.0, 1.0), procs.report()
        finally:
            procs.stop_all(order=lambda p: 0 if p.name.startswith("agent") else 1)
        modes = [dataflash_modes_and_texts(dataflash_log(run, i))[0] for i in range(n)]
    scores = [_score(p, good.scale)[1] for p in logs]
    print(json.dumps({"scores": [s.as_dict() for s in scores], "modes": modes}))
    for i, s in enumerate(scores):
        assert s.crossed and s.max_excursion_m < 0.3, (i, s)
    assert all(m[-1] == BRAKE for m in modes), modes
