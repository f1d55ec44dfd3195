"""``fisc-sim emulate``: launch plan, ground-truth fields, real-time verdict, and one short
end-to-end run with real MAVLink over loopback UDP (autopilot emulators + fisc-agent runners)."""

from __future__ import annotations

import argparse
import csv
import json
import os

import numpy as np
import pytest

from fisc_agent.flight.control import MapGeometry
from fisc_agent.flight.frames import DeploymentTransform
from fisc_agent.map.lookup import CommandField
from fisc_ground.maps.build import build_default_map
from sim.emulate import (EmulateConfig, LaunchPlan, SwarmRun, entry_statistics, flowing, ground_truth_fields, launch_plan,
                         realtime_summary, sample_window)
from sim.scenarios import Reservoir, scale_for_agents

TF = DeploymentTransform()


@pytest.fixture(scope="module")
def cmap():
    return build_default_map()


@pytest.fixture(scope="module")
def field(cmap):
    return CommandField.from_map(cmap)


def test_launch_plan_starts_on_the_ground_upstream_of_the_inlet(field):
    plan = launch_plan(field, 30, TF)
    geom = MapGeometry.from_field(field)
    start_map = TF.ned_to_map(plan.start_ned_m)
    assert plan.start_ned_m.shape == (30, 3)
    assert np.all(plan.start_ned_m[:, 2] == 0.0)  # on the ground, D = 0
    assert np.all(start_map[:, 0] < geom.x_inlet_m - 1.5)  # upstream of the staging plane
    assert np.allclose(start_map[:, 2], -10.0)  # 10 m below the tunnel axis (map origin at NED (0, 0, -10))
    assert len({tuple(p) for p in np.round(plan.start_ned_m, 6)}) == 30  # no two vehicles on one spot


def test_launch_plan_arrivals_follow_the_population_scaled_source_rate(field):
    n = 20
    plan = launch_plan(field, n, TF)
    rate = Reservoir(field, population_scale=scale_for_agents(field, n)).rate_per_s
    assert plan.inflow_rate_per_s == pytest.approx(rate)
    assert np.allclose(np.diff(plan.arrival_time_s), 1.0 / rate)
    assert plan.start_time_s.min() == pytest.approx(0.0)
    assert np.all(plan.start_time_s <= plan.arrival_time_s)  # launch before arrival, by the travel time
    travel = plan.arrival_time_s - plan.start_time_s
    assert np.all(travel > 6.0)  # at least the launch overhead (arm, offboard, climb-out)


def test_launch_plan_raises_the_rate_when_the_run_is_too_short_to_launch_everyone(field):
    plan = launch_plan(field, 400, TF, duration_s=10.0)
    assert plan.inflow_rate_per_s == pytest.approx(400 / 5.0)
    assert plan.inflow_rate_per_s > plan.nominal_rate_per_s


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="agents"):
        EmulateConfig(agents=0)
    with pytest.raises(ValueError, match="personality"):
        EmulateConfig(personality="betaflight")
    with pytest.raises(ValueError, match="rate_hz"):
        EmulateConfig(rate_hz=1.0)
    assert EmulateConfig(agents=50).workers() == (1, 1)
    assert EmulateConfig(agents=400).workers() == (2, 2)
    if (os.cpu_count() or 1) >= 2:
        assert EmulateConfig(agents=200).workers() == (1, 1)  # one process of each per 200 vehicles
        assert EmulateConfig(agents=201).workers() == (2, 2)
    with pytest.raises(ValueError, match="geofence"):
        EmulateConfig(geofence="fly")
    with pytest.raises(ValueError, match="lookahead_s"):
        EmulateConfig(lookahead_s=-1.0)
    with pytest.raises(ValueError, match="entry_radius_fraction"):
        EmulateConfig(entry_radius_fraction=0.0)
    with pytest.raises(ValueError, match="reference_seeds"):
        EmulateConfig(reference_seeds=0)
    with pytest.raises(ValueError, match="plant 'px4'"):
        EmulateConfig(plant="px4")
    with pytest.raises(ValueError, match="px4-sih-loop is PX4's velocity loop"):
        EmulateConfig(plant="px4-sih-loop", personality="ardupilot")
    assert EmulateConfig(plant="px4-sih-loop").plant == "px4-sih-loop"
    with pytest.raises(ValueError, match="estimate_error is stock PX4's"):
        EmulateConfig(estimate_error=True, personality="ardupilot")
    assert EmulateConfig(estimate_error=True).estimate_error is True
    # agents fly the map's settings by default; the paper preset pins Algorithm 1
    s = EmulateConfig().agent_settings()
    assert (s.mode, s.lookahead_s) == (None, None) and EmulateConfig().agent_geofence() == "return"
    s = EmulateConfig(preset="paper").agent_settings()
    assert (s.mode, s.lookahead_s) == ("mean", 0.0)


def test_fleet_mode_lets_the_agents_resolve_the_recommended_mode_as_on_a_real_fleet(tmp_path, cmap):
    from fisc_agent.map.lookup import map_flight_settings
    from sim.emulate.outputs import _run_config

    assert map_flight_settings(cmap).mode == "kinetic"  # the default map recommends kinetic
    # the recommendation given explicitly (its deviations flown, as fisc-sim run), unless fleet_mode
    assert EmulateConfig().agent_settings("kinetic").mode == "kinetic"
    assert EmulateConfig(fleet_mode=True).agent_settings("kinetic").mode is None
    assert EmulateConfig(fleet_mode=True, mode="slot").agent_settings("kinetic").mode == "slot"
    assert EmulateConfig(fleet_mode=True, preset="paper").agent_settings("kinetic").mode == "mean"
    # the report and the reference run name what the agents fly: the staggered field with the deviations where the
    # map carries the duct's real wall (fisc-sim run's kinetic), without them where it does not
    import dataclasses

    from fisc_agent.map.wall import WALL_ARRAY

    m = tmp_path / "m.fiscmap"
    assert WALL_ARRAY in cmap.arrays
    assert _run_config(EmulateConfig(fleet_mode=True), m, cmap).mode == "kinetic"
    bare = dataclasses.replace(cmap, arrays={k: v for k, v in cmap.arrays.items() if k != WALL_ARRAY})
    assert _run_config(EmulateConfig(fleet_mode=True), m, bare).mode == "staggered"
    assert _run_config(EmulateConfig(), m, cmap).mode is None
    assert _run_config(EmulateConfig(fleet_mode=True, tracking=False), m, cmap).mode is None  # open loop: kinetic
    assert _run_config(EmulateConfig(fleet_mode=True, mode="slot"), m, cmap).mode == "slot"


def test_emulated_agents_track_their_streamline_unless_flown_open_loop():
    from fisc_agent.flight.tracking import TrackingConfig
    from sim.emulate.workers import _AgentJob, agent_config

    job = dict(agent_ids=(3,), ports=(14999,), start_time_s=(0.0,), map_path="m.fiscmap", personality="px4",
               mode="kinetic", lookahead_s=0.5, exit_policy="loop", geofence="return", rate_hz=20.0,
               position_rate_hz=20.0, telemetry="full", log_level="WARNING",
               entry_radius_fraction=EmulateConfig().entry_radius_fraction)
    agent = agent_config(_AgentJob(**job, tracking=EmulateConfig().tracking), 3, 14999)
    # fisc-agent's own default, as on a real vehicle, but for the deviations' axes (below)
    assert agent.tracking == TrackingConfig(kinetic_axes=agent.tracking.kinetic_axes)
    assert (agent.agent_id, agent.mode, agent.lookahead_s, agent.mavlink_url) == (
        3, "kinetic", 0.5, "udpout:127.0.0.1:14999")
    assert agent.entry_radius_fraction == 1.0  # entries over every inlet CV, as fisc-sim run injects
    # open loop, gain 0: the mission flies fisc_agent.map.lookup.flight_command at the vehicle
    # (tests/sim/test_command_agreement.py, tests/fisc_agent/test_agent_mission.py)
    assert agent_config(_AgentJob(**job, tracking=False), 3, 14999).tracking.gain_1_s == 0.0
    # the safety net only when asked for (fisc-sim run's law by default, fisc-agent's with --safety-net)
    from fisc_agent.flight.safety_net import SafetyNetConfig

    assert agent.safety_net is None
    assert agent_config(_AgentJob(**job, tracking=True, safety_net=True), 3, 14999).safety_net == SafetyNetConfig()
    # entries at emulate's source-rate launches by default; the map's admission budget, as fisc-agent's own
    # default (--entry-stagger auto), only when asked for
    assert agent.entry_stagger_s == 0.0
    assert agent_config(_AgentJob(**job, tracking=True, staggered_admission=True), 3, 14999).entry_stagger_s is None
    # kinetic deviations reflect at the CV staircase (fisc-sim run's agents), but at fisc-agent's own margin of
    # the map's real wall on a fleet
    from fisc_agent.config import AgentConfig

    assert agent.wall_margin_m is None
    fleet = agent_config(_AgentJob(**job, tracking=True, fleet_mode=True), 3, 14999)
    assert fleet.wall_margin_m == AgentConfig.wall_margin_m and fleet.wall_margin_m is not None
    # and their deviations isotropic (fisc-sim run's), but across the stream on a fleet (fisc-agent's default)
    from fisc_agent.flight.tracking import KineticAxes, TrackingConfig

    assert agent.tracking.kinetic_axes is KineticAxes.ISOTROPIC
    assert fleet.tracking.kinetic_axes is TrackingConfig.kinetic_axes is KineticAxes.CROSS_STREAM


def test_the_emulated_safety_net_needs_a_swarm_to_hear_the_others():
    with pytest.raises(ValueError, match="safety net"):
        EmulateConfig(out_dir="x", safety_net=True)


def test_comparison_takes_the_mean_and_spread_of_the_run_references():
    from types import SimpleNamespace

    from sim.emulate import compare_fields

    rng = np.random.default_rng(1)
    f = SimpleNamespace(samples=np.full(20, 50), u_axial_m_s=rng.random(20), p_dispersion_pa=rng.random(20),
                        rho_s_kg_m3=rng.random(20))
    emu = {"nrmse_velocity": 0.10, "nrmse_pressure": 0.60, "n_cv_compared": 600}
    runs = [{"nrmse_velocity": 0.08, "nrmse_pressure": 0.55, "n_cv_compared": 700},
            {"nrmse_velocity": 0.09, "nrmse_pressure": 0.65, "n_cv_compared": 710}]
    c = compare_fields(emu, runs, f, f, 10)["metrics"]
    assert c["nrmse_velocity"]["run"] == pytest.approx(0.085)
    assert c["nrmse_velocity"]["difference"] == pytest.approx(0.015)
    assert c["nrmse_pressure"]["run_sd"] == pytest.approx(np.std([0.55, 0.65], ddof=1))
    assert c["nrmse_pressure"]["run_seeds"] == [0.55, 0.65] and c["n_cv_compared"]["run"] == 705
    assert c["nrmse_density"]["run"] is None and c["nrmse_density"]["difference"] is None  # missing: not 0
    one = compare_fields(emu, runs[:1], f, f, 10)["metrics"]
    assert one["nrmse_velocity"]["run_sd"] is None and one["nrmse_velocity"]["difference"] == pytest.approx(0.02)
    with pytest.raises(ValueError, match="reference"):
        compare_fields(emu, [], f, f, 10)


def test_the_reference_flies_as_many_agents_in_the_tunnel_as_the_emulation_flew_vehicles():
    from types import SimpleNamespace

    from sim.emulate import flowing_vehicles, matched_population

    # 50 vehicles of which 30 flew the field on average; `fisc-sim run --agents 50` keeps 43 flowing
    assert flowing_vehicles(SimpleNamespace(count=np.array([10.0, 12.5, 7.5]))) == pytest.approx(30.0)
    assert matched_population(50, 30.0, 43.0) == 35  # 34.88 rounded
    assert matched_population(50, 43.0, 43.0) == 50
    assert matched_population(50, 0.0, 43.0) == 1  # never an empty reference
    assert matched_population(50, 30.0, 0.0) == 50  # nothing to scale by: the launched population
    assert matched_population(50, float("nan"), 43.0) == 50


def _flow_from(t_s: float, agent_id: int, until_s: float | None = None) -> dict:
    """An agent record whose mission entered FLOW at ``t_s`` (and left it for JOIN at ``until_s``)."""
    tr = [(0.0, "WAIT_POSITION", "JOIN", "test"), (t_s, "JOIN", "FLOW", "entered")]
    if until_s is not None:
        tr.append((until_s, "FLOW", "JOIN", "lap done"))
    return {"agent_id": agent_id, "transitions": tr}


def _swarm(pos_ned: np.ndarray, vel_ned: np.ndarray, t: np.ndarray, agents: list | None = None) -> SwarmRun:
    n = pos_ned.shape[1]
    agents = [_flow_from(0.0, i) for i in range(n)] if agents is None else agents
    return SwarmRun(agent_ids=np.arange(n), sample_t_s=t, pos_ned_m=pos_ned, vel_ned_m_s=vel_ned, agents=agents,
                    emulator_timing=[], agent_timing=[], setpoint_rate_hz=np.zeros(0), setpoint_rate_t_s=np.zeros(0),
                    duration_s=float(t[-1]) if t.size else 0.0, setup_s=0.0, messages={})


def test_ground_truth_fields_bin_true_states_into_cvs_in_the_map_frame(cmap, field):
    j = 100
    centre = field.centers_m[j]
    k, n = 5, 3
    pos = np.empty((k, n, 3))
    pos[:, 0] = TF.map_to_ned(centre[None])[0]  # vehicle 0 at the centre of CV j
    pos[:, 1] = (0.0, 0.0, 0.0)  # vehicle 1 on the ground, outside every CV
    pos[:, 2] = np.nan  # vehicle 2 never sampled
    vel = np.zeros((k, n, 3))
    vel[:, 0] = (2.0, 0.5, -1.0)  # NED: climbing at 1 m/s -> map v_z = +1
    ref = np.zeros((field.n_cv, 3))
    fields, cv = ground_truth_fields(_swarm(pos, vel, np.arange(k) * 0.1), cmap, TF, np.arange(k), ref)
    assert np.all(cv[:, 0] == j) and np.all(cv[:, 1:] == -1)
    assert fields.samples[j] == k and fields.samples.sum() == k
    assert np.allclose(fields.mean_velocity_m_s[j], (2.0, 0.5, 1.0))
    assert fields.rho_s_kg_m3[j] == pytest.approx(float(cmap.body.get("agent_mass_kg", 1.0)) / field.cell_size_m ** 3)


def test_only_vehicles_flying_the_field_are_counted(cmap, field):
    """A vehicle passing through a CV while its agent joins, returns or loops back is not part of the
    flow (``fisc-sim run`` counts agents flying the field): ``flowing`` follows each agent's transitions."""
    j = 100
    k = 6
    pos = np.repeat(TF.map_to_ned(field.centers_m[j][None])[None], k, axis=0).repeat(2, axis=1)  # both in CV j
    vel = np.zeros((k, 2, 3))
    t = np.arange(k) * 1.0
    agents = [_flow_from(2.0, 0, until_s=4.0), _flow_from(1e9, 1)]     # 0 flows over [2, 4) s, 1 never
    sw = _swarm(pos, vel, t, agents)
    assert np.array_equal(flowing(sw)[:, 0], [False, False, True, True, False, False])
    assert not flowing(sw)[:, 1].any()
    fields, cv = ground_truth_fields(sw, cmap, TF, np.arange(k), np.zeros((field.n_cv, 3)))
    assert fields.samples[j] == 2 and np.array_equal(cv[:, 0], [-1, -1, j, j, -1, -1])


def test_sample_window_keeps_the_last_seconds():
    t = np.arange(101) * 0.1
    assert np.array_equal(sample_window(t, 10.0, 100.0), np.arange(101))
    w = sample_window(t, 10.0, 2.0)
    assert w[0] == 80 and w[-1] == 100


def _timing(period: float, duration: float, drop_every: int = 0, lag: float = 0.001, cpu_cores: float = 0.1) -> dict:
    """A worker loop log: ticks every period (every ``drop_every``-th one missing), constant lag."""
    t = np.arange(0.0, duration, period)
    if drop_every:
        t = t[np.arange(t.size) % drop_every != 0]
    ct = np.arange(0.0, duration + 1.0, 1.0)
    return {"period_s": period, "tick_t_s": t, "lag_s": np.full(t.size, lag), "busy_s": np.full(t.size, period / 4),
            "cpu_t_s": ct, "cpu_s": cpu_cores * ct}


def test_realtime_verdict_needs_setpoint_rate_ticks_and_bounded_lag():
    def summary(rates, agent_timing, emu_timing, t_from=0.0):
        s = _swarm(np.zeros((1, 1, 3)), np.zeros((1, 1, 3)), np.array([0.0, 20.0]))
        s.setpoint_rate_hz = np.asarray(rates, dtype=float)
        s.setpoint_rate_t_s = np.linspace(1.0, 19.0, len(rates))
        s.agent_timing, s.emulator_timing = [agent_timing], [emu_timing]
        return realtime_summary(s, 20.0, 4, t_from)

    good_a, good_e = _timing(0.05, 20.0), _timing(0.02, 20.0)
    ok = summary([20, 20, 21, 19], good_a, good_e)
    assert ok["keeps_real_time"]
    assert ok["cpu_per_agent"] == pytest.approx(2 * 0.1 / 4)  # two processes at 0.1 core each, 4 vehicles
    assert not summary([17, 18, 18], good_a, good_e)["keeps_real_time"]  # setpoints arrive 10 % slow
    assert not summary([20], _timing(0.05, 20.0, drop_every=5), good_e)["keeps_real_time"]  # 20 % ticks lost
    assert not summary([20], good_a, _timing(0.02, 20.0, lag=0.06))["keeps_real_time"]  # lag > a control period
    stalled = _timing(0.02, 20.0)
    stalled["tick_t_s"] = np.arange(0.0, 20.0, 0.12)  # served every 120 ms: > 2 control periods
    stalled["lag_s"] = np.full(stalled["tick_t_s"].size, 0.001)
    stalled["busy_s"] = np.full(stalled["tick_t_s"].size, 0.001)
    assert not summary([20], good_a, stalled)["keeps_real_time"]
    # an emulator loop that skips a few of its 50 Hz ticks but serves every vehicle well within a
    # control period keeps real time (the agents' 20 Hz loop is what must not drop ticks)
    assert summary([20], good_a, _timing(0.02, 20.0, drop_every=5))["keeps_real_time"]
    assert not summary([], good_a, good_e)["keeps_real_time"]  # no vehicle ever flew offboard
    # only the window counts: slow setpoints before t_from are ignored
    assert summary([10, 10, 20, 20, 20, 20], good_a, good_e, t_from=8.0)["keeps_real_time"]


def test_entry_statistics_count_join_to_flow_transitions():
    plan = LaunchPlan(np.zeros((2, 3)), np.zeros(2), np.array([10.0, 11.0]), 1.0, 1.0)
    agents = [{"transitions": [(1.0, "WAIT_POSITION", "ARM", ""), (10.5, "JOIN", "FLOW", ""),
                               (18.0, "FLOW", "JOIN", ""), (30.0, "JOIN", "FLOW", "")]},
              {"transitions": [(12.5, "JOIN", "FLOW", "")]}]
    s = entry_statistics(agents, plan)
    assert s["vehicles_entered"] == 2 and s["entries_total"] == 3
    assert s["arrival_error_mean_s"] == pytest.approx(1.0)
    assert s["realised_first_entry_rate_per_s"] == pytest.approx(0.5)


def test_cli_parser_maps_options_to_the_config(tmp_path):
    from sim.emulate import cli as emulate_cli

    parser = argparse.ArgumentParser()
    emulate_cli.add_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["emulate", "--agents", "7", "--duration", "12", "--mode", "slot", "--autopilot",
                              "ardupilot", "--no-compare", "-o", str(tmp_path), "--mcap", "f.mcap", "--open-loop",
                              "--entry-radius-fraction", "0.8", "--flight-logs", "logs"])
    cfg = emulate_cli.config_from_args(args)
    assert (cfg.agents, cfg.duration_s, cfg.mode, cfg.personality, cfg.compare, cfg.out_dir, cfg.mcap, cfg.tracking,
            cfg.entry_radius_fraction, cfg.flight_logs) == (7, 12.0, "slot", "ardupilot", False, str(tmp_path),
                                                            "f.mcap", False, 0.8, "logs")
    assert (cfg.staggered_admission, cfg.start_spacing_m) == (False, EmulateConfig.start_spacing_m)
    cfg = emulate_cli.config_from_args(parser.parse_args(["emulate", "--agents", "8", "--staggered-admission",
                                                          "--start-spacing", "3", "--fleet-mode", "--estimate-error",
                                                          "-o", str(tmp_path)]))
    assert (cfg.staggered_admission, cfg.start_spacing_m, cfg.fleet_mode, cfg.estimate_error) == (True, 3.0, True, True)
    assert emulate_cli.config_from_args(parser.parse_args(["emulate", "--agents", "2", "-o", str(tmp_path)])).fleet_mode is False


@pytest.mark.parametrize("fleet_mode, given, flown", [(False, None, "return"), (True, None, "hold"),
                                                      (True, "return", "return"), (False, "hold", "hold")])
def test_the_geofence_is_fisc_agents_own_in_fleet_mode_unless_given(tmp_path, fleet_mode, given, flown):
    # a real fleet's agents hold a vehicle that leaves the map (AgentConfig.geofence); the prediction of such a
    # fleet must too, while fisc-sim run's comparison returns it, as the simulator's return policy does
    from fisc_agent.config import AgentConfig
    from sim.emulate import cli as emulate_cli

    assert AgentConfig.geofence.value == "hold"
    assert EmulateConfig(fleet_mode=fleet_mode, geofence=given).agent_geofence() == flown
    parser = argparse.ArgumentParser()
    emulate_cli.add_parser(parser.add_subparsers(dest="command"))
    argv = ["emulate", "--agents", "2", "-o", str(tmp_path)] + (["--fleet-mode"] if fleet_mode else []) + (
        ["--geofence", given] if given else [])
    assert emulate_cli.config_from_args(parser.parse_args(argv)).agent_geofence() == flown


@pytest.mark.slow
def test_emulate_end_to_end_agents_take_off_join_and_flow_through_cvs(tmp_path):
    from sim.emulate import run

    cfg = EmulateConfig(out_dir=str(tmp_path), agents=3, duration_s=22.0, figures=False, compare=True,
                        mcap=str(tmp_path / "flight.mcap"), flight_logs=str(tmp_path / "logs"))
    res = run(cfg)
    # the mission went through the Case 2 entry: ground -> arm -> takeoff -> join -> flow
    flown = [a for a in res.swarm.agents if any(dst == "FLOW" for _, _, dst, _ in a["transitions"])]
    assert flown, [a["transitions"] for a in res.swarm.agents]
    # each agent reports the drag it identified (none yet in 22 s: 20 windows and a spread of speeds needed)
    assert all(a["drag_1_s"] is None and a["drag_fed_forward"] is False for a in res.swarm.agents), res.swarm.agents
    states = iter(dst for _, _, dst, _ in flown[0]["transitions"])
    assert all(s in states for s in ("ARM", "TAKEOFF", "JOIN", "FLOW")), flown[0]["transitions"]  # in this order
    # each agent wrote its own flight log (fisc-agent --flight-log's CSV): the flown one has FLOW ticks
    # with a setpoint and its tracking parcel
    from fisc_agent.flight.flightlog import read_flight_log

    logs = {a["agent_id"]: read_flight_log(tmp_path / "logs" / f"agent_{a['agent_id']}.csv") for a in res.swarm.agents}
    assert all(len(rows) > 0 for rows in logs.values())
    flow_rows = [r for r in logs[flown[0]["agent_id"]] if r["state"] == "FLOW"]
    assert flow_rows and all(r["sp_x_m_s"] and r["parcel_x_m"] for r in flow_rows)
    # the ground truth saw vehicles inside CVs, moving downstream
    rows = list(csv.DictReader(open(tmp_path / "fields.csv")))
    assert len(rows) == res.run_result.cmap.n_cv
    assert {"cv_x", "cv_y", "cv_z", "target_u_axial", "target_pressure", "target_density", "swarm_u_axial",
            "swarm_pressure", "swarm_density", "swarm_temperature", "samples"} <= set(rows[0])
    sampled = [r for r in rows if int(r["samples"]) > 0]
    assert len(sampled) >= 5
    assert np.nanmean([float(r["swarm_u_axial"]) for r in sampled]) > 0.3
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["agents"]["injected"] >= 1 and "emulation" in metrics
    # MAVLink really was in the loop: setpoints arrived at the autopilots at the agents' rate
    assert res.realtime["setpoint_rate_samples"] > 0
    assert abs(res.realtime["setpoint_rate_mean_hz"] - 20.0) < 2.0
    comparison = json.loads((tmp_path / "comparison.json").read_text())
    assert set(comparison["metrics"]) >= {"nrmse_velocity", "nrmse_pressure", "nrmse_density"}
    assert comparison["run_reference"]["seeds"] == [0, 1, 2, 3, 4]
    assert len(comparison["metrics"]["nrmse_velocity"]["run_seeds"]) == 5
    # the reference's population matches the vehicles flowing; the launched population's run is kept beside
    ref = comparison["run_reference"]
    assert ref["launched_population"] == 3 and ref["population"] >= 1
    assert ref["flowing_vehicles"]["emulate"] == pytest.approx(float(res.run_result.fields.count.sum()))
    assert len(comparison["launched_population"]["nrmse_velocity"]["run_seeds"]) == 5
    assert (tmp_path / "run_reference" / "metrics.json").is_file()
    assert "Emulation (MAVLink in the loop)" in (tmp_path / "report.md").read_text()
    # closest approach over every emulated vehicle (issue 37): in metrics.json, comparison.json and report.md,
    # equal to the brute-force minimum over the fleet samples
    from fisc_ground.fields.separation_stats import brute_force_closest

    pos_map = [TF.ned_to_map(p) for p in res.swarm.pos_ned_m]
    want = min(brute_force_closest(res.swarm.agent_ids, p).distance_m for p in pos_map)
    assert metrics["closest_approach_m"] == pytest.approx(want, rel=1e-9)
    assert comparison["separation"]["closest_approach_m"] == pytest.approx(want, rel=1e-9)
    assert comparison["separation"]["d_min_m"] == pytest.approx(0.92, abs=0.01)
    assert set(comparison["axial_profile"]) == {"pearson_density", "pearson_pressure", "nrmse_density",
                                                "nrmse_pressure"}
    assert {"intervals", "axial_profile", "samples_per_cv"} <= set(metrics)
    assert "## Separation" in (tmp_path / "report.md").read_text()
    assert (tmp_path / "map.fiscmap").is_file()
    # the MCAP flight log opens with the mcap reader, every channel with its schema
    from mcap.reader import make_reader

    from fisc_ground.monitor import foxglove_scene as fs
    from fisc_ground.monitor.recording import aggregate, read_recording

    with open(tmp_path / "flight.mcap", "rb") as fh:
        summary = make_reader(fh).get_summary()
    topics = {ch.topic: summary.schemas[ch.schema_id] for ch in summary.channels.values()}
    assert set(topics) == {fs.TOPIC_AGENTS, fs.TOPIC_CVS, fs.TOPIC_SCENE, fs.TOPIC_FIDELITY, fs.TOPIC_STATES,
                           fs.TOPIC_TELEMETRY, fs.TOPIC_MAP, fs.TOPIC_SETTINGS, fs.TOPIC_ALARMS}
    assert topics[fs.TOPIC_AGENTS].name == "foxglove.PointCloud" and topics[fs.TOPIC_AGENTS].encoding == "protobuf"
    assert topics[fs.TOPIC_SCENE].name == "foxglove.SceneUpdate"
    assert all(sc.data for sc in topics.values())
    counts = summary.statistics.channel_message_counts
    assert all(counts.get(ch_id, 0) > 0 for ch_id in summary.channels), counts
    # replayed, the log gives the agents' flight: the emulators' true states as telemetry, with mission states
    agg = aggregate(read_recording(tmp_path / "flight.mcap"))
    assert len(agg.slots) == 3 and agg.fields().samples.sum() > 0
    # ... and exactly the estimate the log published last (its /fisc/fidelity series)
    from fisc_ground.fields.field_report import json_safe

    with open(tmp_path / "flight.mcap", "rb") as fh:
        series = [json.loads(m.data) for _, _, m in make_reader(fh).iter_messages(topics=[fs.TOPIC_FIDELITY])]
    fid = json_safe(agg.field_run(1).fidelity())
    assert series and all(series[-1][k] == fid[k] for k in ("nrmse_velocity", "nrmse_pressure", "nrmse_density",
                                                             "pearson_velocity", "n_cv_compared"))


def test_lean_telemetry_agents_still_take_off_and_flow(tmp_path):
    """``--telemetry lean`` (the emulate benchmark's setting) switches off every stream the agent does not
    need; the landed state (EXTENDED_SYS_STATE) is one it needs: without it no agent left TAKEOFF (the
    mission waits for the autopilot to say it is off the ground) and the benchmark measured agents stuck
    in take-off."""
    from sim.emulate import run
    from sim.emulate.workers import LEAN_OFF_MSG_IDS

    assert 245 not in LEAN_OFF_MSG_IDS  # MAVLINK_MSG_ID_EXTENDED_SYS_STATE
    cfg = EmulateConfig(out_dir=str(tmp_path), agents=1, duration_s=16.0, figures=False, compare=False,
                        telemetry="lean", physics_rate_hz=20.0, physics_dt_s=0.05)
    res = run(cfg)
    reached = [dst for _, _, dst, _ in res.swarm.agents[0]["transitions"]]
    assert "FLOW" in reached, res.swarm.agents[0]["transitions"]


def test_launch_plan_start_positions_are_finite_on_the_ground_for_many_vehicles():
    from fisc_agent.flight.frames import DeploymentTransform
    from fisc_agent.map.lookup import CommandField
    from fisc_ground.maps.build import load_shipped_default_map
    from sim.emulate import launch_plan

    field = CommandField.from_map(load_shipped_default_map())
    plan = launch_plan(field, 400, DeploymentTransform(yaw_deg=30.0), duration_s=60.0)
    assert plan.start_ned_m.shape == (400, 3)
    assert np.all(np.isfinite(plan.start_ned_m)) and np.all(plan.start_ned_m[:, 2] == 0.0)
    assert np.all(np.isfinite(plan.start_time_s)) and plan.start_time_s.min() == 0.0
