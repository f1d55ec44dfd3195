"""A fleet of real PX4 vehicles (SITL, SIH) flown by fisc-agents that get their map over Zenoh.

``SITL_SPACING_M=3``: each vehicle starts 3 m east of the previous one with its own EKF origin,
so the agents share the map frame through a geodetic anchor (GLOBAL_POSITION_INT).  The ground
fits and signs the map and publishes it (``fisc-ground publish``); ``fisc-ground status --json``
must list every agent with the map's sha256; a fleet ``hold`` / ``resume`` is acknowledged and
flown; a newer map signed by a stranger, served mid-flight, is refused by every agent, which
keep flying.  The agents run with stock PX4 parameters and their default flags (issue 37): they are
admitted from the map's flux budget (``--entry-stagger auto``, windows on the shared clock), and learn
their vehicle's velocity gain in flight.  The vehicles must stay ``MIN_SEPARATION_M`` apart by SIH's ground
truth (not PX4's estimates, off by up to 0.5 m) over the whole flight: they wait for their
windows above their own launch points, fly ``LAPS`` passes (``--exit-policy loop``: a lap's return
flies back over the tunnel and waits above its launch point again, ``routes.lap_return_waypoints``)
and then hold after the outlet each at its own point (``control.hold_point``), reached over the
others (``routes.exit_waypoints``).  Every uninterrupted pass must score a ground-truth velocity
nRMSE of at most ``MAX_VELOCITY_NRMSE`` and stay within ``sitl_kit.MAX_EXCURSION_M`` (0.3 m) of the wall by
PX4's estimate, as the ground station sees it (``sitl_kit.TRUTH_EXCURSION_M`` by the truth: the estimator's
error added).  The agents' safety nets (``--safety-net on``, the default)
must hear each other on Zenoh.  ``FISC_SITL_FLEET`` sets the fleet size (default 3; six, issue
37's fleet, came within 1.38, 1.76 and 0.21 m in three runs: see below),
``FISC_SITL_FLEET_LAPS`` the passes (default 1).
"""

from __future__ import annotations

import itertools
import json
import os
import time

import numpy as np
import pytest

from fisc_agent.flight.flightlog import read_flight_log
from fisc_ground.maps.duct_wall import duct_wall_from_reference
from fisc_ground.fields.flight_score import score_track
from fisc_ground.reference.builtin import load_builtin

from .conftest import Processes, cli, poll, run_cli
from .sitl_kit import (MAP_ANCHOR, MAX_EXCURSION_M, TRUTH_EXCURSION_M, latest_states, mission_story, Px4Sitl, Track,
                       ground, ok, px4_ulog, signed_map_on_zenoh, truth_on_wall_clock, truth_pass, ulog_summary)

pytestmark = [pytest.mark.sitl, pytest.mark.slow, pytest.mark.timeout(600)]

N = int(os.environ.get("FISC_SITL_FLEET", "3"))
LAPS = int(os.environ.get("FISC_SITL_FLEET_LAPS", "1"))
"""``FISC_SITL_FLEET_LAPS=2`` flies two passes (measured: 1.11 m closest by the ground truth, 136 s)."""
FLEET_HOLD = os.environ.get("FISC_SITL_FLEET_HOLD", "1") != "0"
"""``FISC_SITL_FLEET_HOLD=0`` leaves out the fleet hold/resume (a clean pass, to measure crossings)."""
SWARM = "sitl"
# The history of the spacing: manual windows (``--entry-stagger``) of 2-4 s gave closest approaches
# of 0.16-0.41 m at times (PX4's estimates; SIH's ground truth, now the judge, put one at 0.27 m);
# with 4 s windows, waiting above the launch points and spaced hold points, three vehicles kept
# 0.93-1.38 m over the whole flight.  Six on a 1.5 m hold lattice reached straight from the outlet:
# 0.29 and 0.47 m (a leader climbing at the outlet, two neighbours in PX4's Hold); over the spots
# on the 3 m lattice: 1.02 m.  With the default flags (the map's admission windows of 2.89 s), 0.29-0.39 m
# at the staging points and the exit's climb; with the joins' arrival governor, the exit's corners flown
# through and the admission's 1 s timing tolerance (4.23 s windows): 1.38 and 1.76 m, then 0.21 m at the
# outlet (two vehicles that entered 0.9 s apart: each agent keeps its windows on its own PX4's GNSS time,
# and SITL instances' simulated clocks drift apart by seconds under load; not understood further).
MAX_VELOCITY_NRMSE = 0.20
"""A regression bound on every vehicle's axial-velocity nRMSE against the CFD (SIH's ground truth).
Issue 37 asks for 0.10: stock PX4 fleets on 2026-12-05 scored 0.063-0.157 over 27 passes (one of
five flights had every pass within 0.10), 0.2-0.4 m/s too fast in the diverging part by the ground
truth: the feed-forward gain learnt from PX4's catching-up integrator (1.1-1.3) overshot there.  With
the GNSS-velocity bias and the gain at 1 (2026-12-06) six vehicles scored 0.054-0.084 in two runs
(12 of 12 passes within 0.10); this bound stays a regression bound until more flights, with the
fleet hold this test flies, show the 0.10 holds."""
MIN_SEPARATION_M = 0.5


def safety_net_view(flight_log) -> dict:
    """What one agent's safety net saw (its flight log): the nearest neighbour it heard [m] and the
    ticks on which it acted, by state."""
    rows = read_flight_log(flight_log)
    near = [float(r["nearest_neighbour_m"]) for r in rows if r["nearest_neighbour_m"]]
    acted: dict[str, int] = {}
    for r in rows:
        if r["net_ids"]:
            acted[r["state"]] = acted.get(r["state"], 0) + 1
    return {"nearest_heard_m": min(near, default=float("inf")), "acting_ticks": acted}


def min_separation_m(tracks: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """Smallest distance between two vehicles at the same wall-clock instant.  ``tracks``:
    (wall_s, pos_m) pairs, interpolated onto a common 0.05 s grid."""
    best = np.inf
    for (wa, pa_m), (wb, pb_m) in itertools.combinations(tracks, 2):
        t0, t1 = max(wa[0], wb[0]), min(wa[-1], wb[-1])
        if t1 <= t0:
            continue
        grid = np.arange(t0, t1, 0.05)
        pa = np.column_stack([np.interp(grid, wa, pa_m[:, k]) for k in range(3)])
        pb = np.column_stack([np.interp(grid, wb, pb_m[:, k]) for k in range(3)])
        best = min(best, float(np.min(np.linalg.norm(pa - pb, axis=1))))
    return best


def test_px4_fleet_over_zenoh_with_anchors_status_hold_resume_and_a_strangers_map(shared_path, tmp_path):
    d = tmp_path
    g = signed_map_on_zenoh(d)
    served, good, hub, member = g.served, g.good, g.hub, g.member
    ok(run_cli(ground("keygen", "-o", d / "stranger")))
    logs = [d / f"agent{i}.csv" for i in range(N)]

    def status() -> dict[int, dict]:
        out = ok(run_cli(ground("status", "--swarm", SWARM, "--zenoh-config", member, "--json", "--wait", 1.0)))
        return {a["id"]: a for a in json.loads(out)["agents"] if a["last_seen_s"] < 2.5}

    def states() -> list[str]:
        return latest_states(logs)

    with Px4Sitl(shared_path("sitl", "px4"), d, N, spacing_m=3.0) as run:
        procs = Processes(d / "logs")
        try:
            procs.start("publisher", ground("publish", served, "--swarm", SWARM, "--zenoh-config", hub))
            for i in range(N):
                procs.start(f"agent{i}", cli("fisc-agent") + ["--go",
                    "--swarm", SWARM, "--zenoh-config", member, "--trusted-key", g.ground_pub,
                    "--mavlink", f"udpin:0.0.0.0:{14540 + i}", "--id", i, "--autopilot", "px4",
                    "--geodetic-anchor", MAP_ANCHOR, "--exit-policy", "loop", "--laps", LAPS, "--flight-log", logs[i]])
            # every agent got the signed map and reports it
            seen = poll(lambda: (lambda s: s if len(s) == N and all(a["map_sha256"] == good.sha256 for a in s.values())
                                 else None)(status()), 90.0, 0.0)
            assert seen, procs.report()
            # a fleet hold while they fly, then resume
            assert poll(lambda: sum(s in ("JOIN", "FLOW") for s in states()) >= 1, 120.0, 0.5), procs.report()
            out = None
            if FLEET_HOLD:
                out = json.loads(ok(run_cli(ground("cmd", "hold", "--swarm", SWARM, "--zenoh-config", member, "--key",
                                                   d / "ground.key", "--ack-wait", "8"))).strip().splitlines()[-1])
                assert sorted(out["acked"]) == list(range(N)), out
                assert poll(lambda: all(s in ("HOLD", "WAIT_POSITION", "ARM") for s in states()), 10.0, 0.2), states()
                time.sleep(4.0)
                ok(run_cli(ground("cmd", "resume", "--swarm", SWARM, "--zenoh-config", member, "--key",
                                  d / "ground.key", "--ack-wait", "8")))
            # a stranger's newer map, served mid-flight: refused by all, who keep flying the good one
            assert poll(lambda: any(s == "FLOW" for s in states()), 90.0, 0.2), states()
            ok(run_cli(ground("fit", "cd_nozzle_inviscid", "--max-speed", "3", "-o", d / "stranger.fiscmap",
                              "--sign", d / "stranger.key")))
            os.replace(d / "stranger.fiscmap", served)
            refused = poll(lambda: (lambda s: s if len(s) == N and all(a["maps_rejected"] >= 1 and
                                                                         a["map_sha256"] == good.sha256
                                                                         for a in s.values()) else None)(status()),
                           40.0, 0.0)
            assert refused, procs.report()
            # everyone through its laps and holding after the outlet
            done = poll(lambda: all(s == "HOLD" for s in states()) and all(
                any(r["state"] == "EXIT" for r in read_flight_log(p)) for p in logs), 240.0 + 90.0 * LAPS, 1.0)
            assert done, f"{procs.report()}\n{states()}\n{mission_story(logs)}"
        finally:
            procs.stop_all(order=lambda p: 0 if p.name.startswith("agent") else 1)
        ulog_paths = [px4_ulog(run, i) for i in range(N)]
    ulogs = [ulog_summary(p) for p in ulog_paths]
    ref = load_builtin("cd_nozzle_inviscid")
    wall = duct_wall_from_reference(ref)
    tracks = [Track.read(p) for p in logs]
    scores = [score_track(t.t_s, t.pos_m, t.vel_m_s, t.states, ref, good.scale, wall=wall) for t in tracks]
    truths = [truth_on_wall_clock(p, t, MAP_ANCHOR) for p, t in zip(ulog_paths, tracks)]
    sep = min_separation_m([(w.wall_s, w.pos_m) for w in truths])
    truth_scores = [score_track(*truth_pass(w, track=t), ref, good.scale, wall=wall) for w, t in zip(truths, tracks)]
    passes = [sum(1 for a, b in zip(t.states, t.states[1:]) if a == "JOIN" and b == "FLOW") for t in tracks]
    heard = [safety_net_view(p) for p in logs]
    report = {"hold_ack": out, "min_separation_m": sep, "passes": passes, "safety_net": heard,
              "min_separation_estimated_m": min_separation_m([(t.wall_s, t.pos_m) for t in tracks]),
              "clock_fit_rms_m": [w.fit_rms_m for w in truths], "scores": [s.as_dict() for s in scores],
              "crossing_s": [s.crossing_time_s for s in scores], "truth": [s.as_dict() for s in truth_scores]}
    print(json.dumps(report, default=str))
    for i, (s, tr) in enumerate(zip(scores, truth_scores)):
        assert s.max_excursion_m < MAX_EXCURSION_M and tr.max_excursion_m < TRUTH_EXCURSION_M, (i, s, tr)
        assert FLEET_HOLD or (s.crossed and not s.held), (i, s)
        assert s.n_samples > 50, (i, s)
        if not s.held:   # a pass the fleet hold did not interrupt
            assert tr.crossed and tr.velocity_nrmse <= MAX_VELOCITY_NRMSE, (i, tr, s)
    assert sum(not s.held for s in scores) >= N // 2, report   # the hold came early: most passes are whole
    assert passes == [LAPS] * N, report
    assert all(w.fit_rms_m < 0.1 for w in truths), report   # the clocks matched: the truth is on the wall clock
    assert sep >= MIN_SEPARATION_M, report
    assert all(h["nearest_heard_m"] < 20.0 for h in heard), report  # the nets heard their neighbours on Zenoh
    for u in ulogs:
        assert u.max_setpoint_gap_s < 0.5 and u.gps_fused and not u.failsafe_seen, u
