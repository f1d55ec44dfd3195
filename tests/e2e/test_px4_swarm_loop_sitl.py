"""Issue 37's real swarm: eight stock PX4 (SITL, SIH) looping laps with the swarm defaults while the
monitor records, judged by SIH's ground truth and the monitor's axial profile, with the emulator's
prediction beside it.

The flight: ``FISC_SITL_SWARM`` vehicles (default 8), stock parameters, the agents' default flags
(admission windows from the map's budget, the safety net, the map's recommended mode) with
``--exit-policy loop --laps 0``, for ``FISC_SITL_LOOP_S`` seconds (default 300) from the first entry.
``FISC_SITL_LOOP_MODE`` (unset: the defaults) gives the agents and the prediction an explicit ``--mode``, e.g.
``kinetic`` to fly the map's designed velocity spread, and ``FISC_SITL_LOOP_GEOFENCE`` an explicit ``--geofence``
(``return``: a vehicle that leaves the map rejoins the nearest CV instead of holding).
``fisc-ground monitor --record`` writes the MCAP; ``fisc-ground replay`` scores it.  Checked:

- closest approach by the ground truth >= ``MIN_SEPARATION_M`` over the whole flight;
- no vehicle more than ``MAX_EXCURSION_M`` outside the duct's wall while it flows by PX4's estimate (as the
  ground station sees it), nor more than ``TRUTH_EXCURSION_M`` (that plus the estimator's error) by SIH's ground
  truth: the project's bound of every real-autopilot test (docs/deployment.md section 4b);
- the axial profile of the monitor's recording against the CFD (``fisc_ground.fields.axial_profile``):
  density and pressure Pearson r printed with their 95 % intervals, and at least ``MIN_PROFILE_R_DENSITY``
  / ``MIN_PROFILE_R_PRESSURE`` (issue 37 asks 0.9 / 0.7);
- ``fisc-sim emulate --plant px4-sih-loop`` (stock PX4's velocity loop on SIH's linear drag, which flies the
  agents' drag feed-forward as PX4 does) with the same fleet, exit policy, safety net and duration, the agents'
  own mode resolution (``--fleet-mode``) and PX4's estimate error (``--estimate-error``), gives each profile
  figure within ``PREDICTION_TOLERANCE`` of the real one.

Measured 2026-12-05 (one run): closest approach 0.61 m, largest excursion 0.30 m, 3-4 laps each, but
the profile's density r 0.41 and pressure r -0.49 (the emulator: 0.45 and 0.54), so the profile and
prediction checks fail: issue 37 stays open on them (docs/status.md).  2026-12-06: 0.47 m before the
late-entry rule (``Navigator._late_at_staging``); with it and its learnt lead 1.14 m, but 1-5 laps each
(joins late at their staging points give their windows up) and density r 0.43, pressure r 0.13; with
the net's pass rule, the crossing rule and a join sure to be late turning back on its way (seventh run):
1.41 m, largest excursion 0.19 m, 3-5 laps each, density r 0.57, pressure r 0.20 (0.73 the run before).
2026-12-07, with the drag's acceleration feed-forward (``fisc_agent.flight.drag``): density r 0.87 and 0.81,
pressure r 0.40 and 0.82 (0.94 / 0.87 and 0.39 / 0.87 with the monitor's fleet sampled at 0.2 s, its default
since); closest approach 0.25 m (a lap's return came down through the inlet, since routed upstream of it) and
1.18 m; the emulator, which flies no feed-forward, predicted density r 0.63 and 0.70.  A third run, with the
return rerouted and the 0.2 s default: density r 0.87, pressure r 0.81, closest approach 0.70 m (predicted 0.75 / 0.80).
A fourth, with the join's final leg at the inlet's crawl (vehicles had crossed the inlet plane at 0.70 m/s for
0.42): density r 0.94, pressure r 0.73, closest approach 0.63 m, largest excursion 0.08 m, 2-4 laps; the
emulator with the ``px4-sih`` velocity plant (quadratic drag, on which the agents' linear feed-forward is three
times the drag at the inlet) predicted 0.66 / 0.81; the ``px4-sih-loop`` model, flown beside the same recording,
0.78 / 0.83.  A fifth: density r 0.91, pressure r 0.64 (below 0.7), closest approach 1.08 m, largest excursion
-0.03 m; ``px4-sih-loop`` predicted 0.71 / 0.90.  In both the final leg flew the crawl all the way; with the
final rule (``spacing.final_leg_speed_m_s``, a sixth run): density r 0.935, pressure r 0.40, closest approach
0.86 m, largest excursion -0.07 m, 3-5 laps; predicted 0.63 / 0.83.  Those emulations flew the kinetic
deviations (emulate gave its agents the map's recommendation explicitly) where the fleet flies the staggered
field: parcels 0.78 m from the axis against the fleet's 0.22 m, 200 crossings of the CVs' side against none.
With ``--fleet-mode`` the sixth run's emulation gives density r 0.925 (real 0.935), density nRMSE 0.137
(0.136), but pressure r -0.62 (0.40): see docs/emulation.md on what the fleet's pressure measures.  With PX4's
estimate error emulated too (``--estimate-error``) two more real runs (seventh, eighth): density r 0.965 and
0.964 (predicted 0.962 and 0.868: within 0.1), density nRMSE 0.110 and 0.109 (0.140, 0.192), pressure r 0.30 and
0.68 (predicted 0.80 and 0.29: not within 0.1; in the default mode the pressure the ground station sees is the
autopilots' velocity-estimate error, and it scatters from run to run), closest approach 0.77 and 1.04 m, largest
excursion by PX4's estimate 0.41 and 0.31 m inside the wall, by SIH's truth 0.42 and 0.47 m outside it (PX4's
estimate 0.9 m off vertically: within ``TRUTH_EXCURSION_M``), 2-6 laps.  A ninth run (this test as it stands):
density r 0.943 (predicted 0.917), pressure r 0.50 (predicted 0.54), pressure nRMSE 0.319 (0.438), closest approach
1.02 m, excursion 0.37 m inside by the estimate, 0.13 m outside by the truth: it fails on pressure r >= 0.7 alone.
Run 11 (2026-12-07): density r 0.962, pressure r 0.712, closest approach 0.82 m, but pressure r predicted 0.593:
in the default mode the pressure is PX4's estimate error, which scatters.  With ``FISC_SITL_LOOP_MODE=kinetic``
(the deviations turned across the stream, ``--kinetic-axes``' default): density r 0.900 and 0.929, pressure r 0.783
and 0.877, every figure predicted within 0.1, closest approach 0.93 and 0.99 m, excursions 0.07 and 0.01 m outside
by the truth: the second run passed this test, the first to (docs/status.md).  With the swarm defaults once the
recommended kinetic mode is flown with its deviations (the same day): passed, density r 0.941, pressure r 0.787,
all four predicted within 0.1, closest approach 1.19 m, excursion 0.23 m outside by the truth; a second: density r
0.926, pressure r 0.776, closest approach 0.97 m, but pressure r predicted 0.892 (0.116 off): failed on the prediction.

It takes about 12 minutes on two cores (the flight, then the emulation), so it is marked ``long``:
the default run (`.ci/run`) leaves it out (``-m "not long"`` in pyproject's addopts); run it with
``pytest -m long tests/e2e/test_px4_swarm_loop_sitl.py -s``.  Its JSON report is printed.
"""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest

from fisc_agent.config import AgentConfig
from fisc_ground.maps.duct_wall import duct_wall_from_reference
from fisc_ground.reference.builtin import load_builtin

from .conftest import Processes, cli, free_tcp_port, poll, run_cli
from .sitl_kit import (MAP_ANCHOR, MAX_EXCURSION_M, TRUTH_EXCURSION_M, Px4Sitl, Track, flowing_at, ground, latest_states, ok, px4_ulog,
                       signed_map_on_zenoh, truth_on_wall_clock)
from .test_px4_fleet_sitl import min_separation_m, safety_net_view

pytestmark = [pytest.mark.sitl, pytest.mark.slow, pytest.mark.long, pytest.mark.timeout(1800)]

N = int(os.environ.get("FISC_SITL_SWARM", "8"))
LOOP_S = float(os.environ.get("FISC_SITL_LOOP_S", "300"))
MODE = os.environ.get("FISC_SITL_LOOP_MODE", "")
"""An explicit ``--mode`` for the agents and the prediction (empty: the agents' defaults)."""
GEOFENCE = os.environ.get("FISC_SITL_LOOP_GEOFENCE", "")
"""An explicit ``--geofence`` for the agents and the prediction (empty: the agents' default, hold)."""
SWARM = "loop"
MIN_SEPARATION_M = 0.5
MIN_PROFILE_R_DENSITY = 0.9
MIN_PROFILE_R_PRESSURE = 0.7
PREDICTION_TOLERANCE = 0.1
FLEET_SPACING_M = 3.0
"""The SITL fleet's start spacing (``SITL_SPACING_M``), the emulated fleet's too (``--start-spacing``)."""


def flowing_excursion_m(truth, track: Track, wall) -> float:
    """Largest distance outside the wall [m] of the true positions (``truth``: ``wall_s`` and map-frame
    ``pos_m``; the track itself for the agent's estimated ones) while the agent's log says FLOW
    (``sitl_kit.flowing_at``)."""
    flowing = flowing_at(track, truth.wall_s)
    x, r = truth.pos_m[flowing, 0], np.hypot(truth.pos_m[flowing, 1], truth.pos_m[flowing, 2])
    inside = (x >= wall.x_m[0]) & (x <= wall.x_m[-1])
    return float(np.max(r[inside] - wall.radius_at(x[inside]), initial=-np.inf))


def profile(metrics: dict) -> dict:
    """The axial profile's figures of a metrics.json with their intervals."""
    a = metrics["axial_profile"]
    return {k: {f: a[k][f] for f in ("value", "lo", "hi")} for k in
            ("pearson_density", "pearson_pressure", "nrmse_density", "nrmse_pressure")}


def test_eight_stock_px4_loop_with_the_monitor_recording_and_the_emulator_predicting(shared_path, tmp_path,
                                                                                     monkeypatch):
    d = tmp_path
    g = signed_map_on_zenoh(d)
    logs = [d / f"agent{i}.csv" for i in range(N)]
    mcap = d / "flight.mcap"

    def states() -> list[str]:
        return latest_states(logs)

    with Px4Sitl(shared_path("sitl", "px4"), d, N, spacing_m=FLEET_SPACING_M) as run:
        procs = Processes(d / "logs")
        try:
            procs.start("publisher", ground("publish", g.served, "--swarm", SWARM, "--zenoh-config", g.hub))
            for i in range(N):
                procs.start(f"agent{i}", cli("fisc-agent") + ["--go",
                    "--swarm", SWARM, "--zenoh-config", g.member, "--trusted-key", g.ground_pub,
                    "--mavlink", f"udpin:0.0.0.0:{14540 + i}", "--id", i, "--autopilot", "px4",
                    "--geodetic-anchor", MAP_ANCHOR, "--exit-policy", "loop", "--laps", 0, "--flight-log", logs[i]]
                    + (["--mode", MODE] if MODE else []) + (["--geofence", GEOFENCE] if GEOFENCE else []))
            assert poll(lambda: any(s == "FLOW" for s in states()), 240.0, 0.5), procs.report()
            # the monitor records LOOP_S from the first entry and closes its MCAP itself
            monitor = procs.start("monitor", ground("monitor", "--swarm", SWARM, "--zenoh-config", g.member,
                                                    "--trusted-key", g.ground_pub, "--record", mcap,
                                                    "--duration", LOOP_S, "-q"))
            end = time.monotonic() + LOOP_S
            while time.monotonic() < end:
                time.sleep(5.0)
                # looping laps, nothing holds but a failsafe (a lost link, a stale fix): fail at once
                assert not any(s in ("HOLD", "DONE", "FAILSAFE") for s in states()), (states(), procs.report())
            assert poll(lambda: not monitor.alive, 60.0, 0.5), procs.report()
        finally:
            procs.stop_all(order=lambda p: 0 if p.name.startswith("agent") else 1)
        ulog_paths = [px4_ulog(run, i) for i in range(N)]
    ref = load_builtin("cd_nozzle_inviscid")
    wall = duct_wall_from_reference(ref)
    tracks = [Track.read(p) for p in logs]
    truths = [truth_on_wall_clock(p, t, MAP_ANCHOR) for p, t in zip(ulog_paths, tracks)]
    sep = min_separation_m([(w.wall_s, w.pos_m) for w in truths])
    excursions = [flowing_excursion_m(w, t, wall) for w, t in zip(truths, tracks)]
    laps = [sum(1 for a, b in zip(t.states, t.states[1:]) if a == "FLOW" and b != "FLOW") for t in tracks]
    ok(run_cli(ground("replay", mcap, "-o", d / "replay", "--min-samples", 3, "--no-figures"), timeout_s=300))
    real = json.loads((d / "replay" / "metrics.json").read_text())
    # the prediction: the emulator with the same fleet, admission, policy, net and duration, its workers meeting on
    # their own lab port (the lab default: no config file); averaged over the whole flight, as the monitor's
    # recording is (emulate's default window is its last 60 s: a fifth of the passes, another figure)
    monkeypatch.setenv("FISC_ZENOH_PORT", str(free_tcp_port()))
    ok(run_cli(cli("fisc-sim") + ["emulate", "--map", g.served, "--agents", N, "--plant", "px4-sih-loop",
                                  "--exit-policy", "loop", "--duration", LOOP_S, "--average-window", LOOP_S,
                                  "--swarm", "loopem",
                                  "--trusted-key", g.ground_pub, "--safety-net",
                                  # the fleet's own admission, start spacing, entry points and mode resolution
                                  # (fisc-agent's defaults: the staggered field, no kinetic deviations), not
                                  # emulate's source-rate launches from a 1 m grid flying fisc-sim run's deviations
                                  "--staggered-admission", "--start-spacing", FLEET_SPACING_M, "--fleet-mode",
                                  # PX4's estimate strays as on SIH, and the profile is what the vehicles
                                  # report, as the monitor scores the agents' published estimates
                                  "--estimate-error",
                                  "--entry-radius-fraction", AgentConfig.entry_radius_fraction,
                                  "--no-compare", "--no-figures", "-o", d / "emulate", "-q"]
                       + (["--mode", MODE] if MODE else []) + (["--geofence", GEOFENCE] if GEOFENCE else []),
                       timeout_s=LOOP_S + 300))
    predicted = json.loads((d / "emulate" / "metrics.json").read_text())
    report = {"min_separation_m": sep, "excursion_m": excursions, "laps": laps,
              # the same by the agents' own (PX4's estimated) positions: the truth's excess over it is PX4's error
              "excursion_estimate_m": [flowing_excursion_m(t, t, wall) for t in tracks],
              "safety_net": [safety_net_view(p) for p in logs],
              "real": {"profile": profile(real), "samples_per_cv": real.get("samples_per_cv"),
                       "closest_approach_m": real.get("closest_approach_m")},
              "predicted": {"profile": profile(predicted), "closest_approach_m": predicted.get("closest_approach_m")}}
    print(json.dumps(report, default=str))
    assert sep >= MIN_SEPARATION_M, report
    assert max(report["excursion_estimate_m"]) <= MAX_EXCURSION_M, report
    assert max(excursions) <= TRUTH_EXCURSION_M, report
    assert min(laps) >= 2, report
    rp, pp = report["real"]["profile"], report["predicted"]["profile"]
    assert rp["pearson_density"]["value"] >= MIN_PROFILE_R_DENSITY, report
    assert rp["pearson_pressure"]["value"] >= MIN_PROFILE_R_PRESSURE, report
    for k in rp:
        assert abs(rp[k]["value"] - pp[k]["value"]) <= PREDICTION_TOLERANCE, (k, report)
