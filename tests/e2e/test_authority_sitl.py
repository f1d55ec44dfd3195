"""Who flies the vehicle, on the real autopilots (issue 36 item 8; docs/deployment.md section 5 "Authority").

Each test runs real PX4 (SIH) or ArduCopter SITL from ``../shared/sitl`` and a ground station as
QGroundControl or MAVProxy would be one (``GroundStation``: udp 14550, ordinary COMMAND_LONGs), and
judges the agent by what the *autopilot* did: every HEARTBEAT mode the ground station received, PX4's
ULog (vehicle_status.nav_state, offboard_control_mode, SIH's ground truth) and ArduPilot's DataFlash
MODE messages.  The agent's own flight log and console only say where it was when something happened.

- a restart on an airborne vehicle: PX4 in Hold after the ground's take-off, ArduCopter landing in the
  ground's LAND: the agent (``--go``) changes no mode and sends no setpoint;
- no arming without a go, then a signed fleet ``go`` arms;
- the ground takes the vehicle in ARM, TAKEOFF, FLOW and a fleet hold: the agent is hands-off, a
  swarm-wide ``resume`` does not take the vehicle back, ``resume --agents 1`` does;
- PX4's offboard-loss failsafe lands the vehicle while the agent is frozen (SIGSTOP): when the agent
  comes back the vehicle keeps landing.
"""

from __future__ import annotations

import json
import math
import os
import re
import signal
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest

from fisc_agent.flight.control import MapGeometry
from fisc_agent.flight.flightlog import read_flight_log
from fisc_agent.map.codec import load_map
from fisc_agent.map.lookup import CommandField

from .conftest import Processes, cli, poll, run_cli
from .ground_station import (COPTER_BRAKE, COPTER_GUIDED, COPTER_LAND, PX4_HOLD, PX4_LAND, PX4_NAV_AUTO_LAND,
                             PX4_NAV_AUTO_LOITER, PX4_NAV_AUTO_TAKEOFF, PX4_NAV_OFFBOARD, PX4_OFFBOARD, PX4_TAKEOFF,
                             mode_name)
from .sitl_kit import (ArduPilotSitl, GroundStation, LinkCut, Px4Sitl, dataflash_log,
                       dataflash_modes_and_texts, dedup, ground, ok, px4_ulog, signed_map_on_zenoh, ulog_topic)

pytestmark = [pytest.mark.sitl, pytest.mark.slow]

SWARM = "authsitl"
WATCH_S = 25.0
"""How long a restarted agent is watched on an airborne vehicle (issue 36: 25 s)."""
MAX_HOLD_WANDER_M = 2.5
"""Bound on SIH's true displacement in PX4's own Hold over the 25 s (no agent input at all: no OFFBOARD,
no offboard_control_mode, the Hold's horizontal target fixed to 1 mm).  PX4's Hold alone wanders in SIH
(2026-12-05, this 2-core host under load, one vehicle): 0.88 m at 2.5 m with the stock gains, 1.46 and
1.80 m with tuned velocity gains (``MPC_XY_VEL_P_ACC`` 3.5, ``_I_ACC`` 1.5), 2.12 m at 5 m with the stock gains, as a slow 15-20 s swing of 1-1.5 m
about the fixed target that PX4's own estimate follows to within 0.4 m.  Issue 36's 1 m cannot be told
apart from that; the restarted agent of the issue flew the vehicle 11 m away."""
NO_WINDOWS = ("--entry-stagger", "off")
"""A lone vehicle needs no admission window (the map's admission period would make it wait up to ~20 s)."""
NO_GO_WATCH_S = 15.0
"""How long a vehicle whose agent has no ``go`` is watched, disarmed, before the signed ``go`` [s]."""
HANDS_OFF_WATCH_S = 3.0
"""How long the ground's mode must stay before and after a swarm-wide ``resume`` [s] (the agent's mode
requests repeat every second: three would be missed by none)."""


@pytest.fixture(scope="module")
def map_path(tmp_path_factory) -> Path:
    """The embedded default map (``fisc-ground fit cd_nozzle_inviscid``)."""
    path = tmp_path_factory.mktemp("map") / "tunnel.fiscmap"
    ok(run_cli(ground("fit", "cd_nozzle_inviscid", "-o", path)))
    return path


def _agent(procs: Processes, name: str, log: Path, autopilot: str, *extra, port: int = 14540):
    """``fisc-agent --id 1`` on the SITL's API link (udp ``port``), flight log ``log``, ``extra`` options."""
    return procs.start(name, cli("fisc-agent") + ["--mavlink", f"udpin:0.0.0.0:{port}", "--id", 1, "--autopilot",
                                                  autopilot, "--flight-log", log, *extra])


def _console(proc) -> str:
    try:
        return proc.log_path.read_text(errors="replace")
    except OSError:
        return ""


def _count(proc, pattern: str) -> int:
    """How often ``pattern`` (regex) occurs in the agent's console so far."""
    return len(re.findall(pattern, _console(proc)))


def _last_state(proc) -> str | None:
    """The state the agent's console says it entered last (``mission A -> B``)."""
    states = re.findall(r"mission \w+ -> (\w+)", _console(proc))
    return states[-1] if states else None


AGENT_LINE = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) \w+ \S+: "
                        r"(?:requesting set mode (\S+)|mission \w+ -> (\w+) \(([^:)]*))", re.M)
SELF_RESUMING = ("position jump", "position stale")
"""Hold reasons after which the agent resumes by itself (``fisc_agent.flight.mission_types.AUTO_RESUMING``): a hold
of this kind that outlasts ``hold_grace_s`` asks for the autopilot's hold mode, then for offboard/guided again."""


def _mode_requests(gcs, *agents) -> tuple[list[str], list[str]]:
    """Every mode the ground station and the ``agents`` asked for, by name, in time order (the agents' from their
    consoles' ``requesting set mode`` lines), with consecutive repeats removed; and the same without the modes the
    agents asked for in a hold that ends by itself (``SELF_RESUMING``) and for the flight that followed it."""
    every, scripted = list(gcs.mode_requests), list(gcs.mode_requests)
    for agent in agents:
        self_resuming = False
        for m in AGENT_LINE.finditer(_console(agent)):
            t = datetime.strptime(m[1], "%Y-%m-%d %H:%M:%S,%f").timestamp()
            if m[3] is not None:  # a state change: in a self-resuming hold, or the flight that follows one
                self_resuming = (m[3] == "HOLD" and m[4].startswith(SELF_RESUMING)) or (
                    self_resuming and m[4].startswith("position fix back"))
                continue
            every.append((t, m[2]))
            if not self_resuming:
                scripted.append((t, m[2]))
    return dedup(name for _, name in sorted(every)), dedup(name for _, name in sorted(scripted))


def _rows(log: Path) -> list[dict[str, str]]:
    try:
        return read_flight_log(log)
    except (OSError, KeyError):
        return []


def _setpoints(rows: list[dict[str, str]]) -> list[dict[str, str]]:
    """Flight-log rows in which the agent streamed a setpoint."""
    return [r for r in rows if r["sp_x_m_s"] != ""]


def _window(data: dict[str, np.ndarray] | None, boot0_s: float, boot1_s: float) -> np.ndarray:
    """Indices of a ULog topic's samples in ``[boot0_s, boot1_s]`` (PX4's clock)."""
    if data is None:
        return np.array([], dtype=int)
    t = data["timestamp"] / 1e6
    return np.flatnonzero((t >= boot0_s) & (t <= boot1_s))


def _horizontal_m(a, b) -> float:
    """Horizontal distance between two GLOBAL_POSITION_INT fixes [m]."""
    dn = (b.lat_deg - a.lat_deg) * 111_320.0
    de = (b.lon_deg - a.lon_deg) * 111_320.0 * math.cos(math.radians(a.lat_deg))
    return math.hypot(dn, de)


# ---- restart on an airborne vehicle ----------------------------------------------------------------
@pytest.mark.timeout(240)
def test_px4_restart_in_the_air_in_the_grounds_hold_changes_no_mode_and_sends_no_setpoint(shared_path, tmp_path,
                                                                                           map_path):
    """The ground station arms and takes off (AUTO.TAKEOFF, then PX4's own Hold); ``fisc-agent --go`` started
    then is ``not-ours``: for 25 s no mode change (every HEARTBEAT AUTO.LOITER, no OFFBOARD nav_state), no
    setpoint (no offboard_control_mode in PX4's log), and SIH's ground truth moves less than 1 m."""
    log = tmp_path / "agent1.csv"
    with Px4Sitl(shared_path("sitl", "px4"), tmp_path, 1) as run, GroundStation("px4") as gcs:
        procs = Processes(tmp_path / "logs")
        try:
            gcs.connect()
            gcs.arm()
            gcs.takeoff(2.5)
            gcs.wait(lambda: gcs.mode() == PX4_HOLD, 20.0, "PX4's own AUTO.LOITER after the take-off")
            started = time.monotonic()
            agent = _agent(procs, "agent1", log, "px4", "--go", "--map", map_path)
            assert poll(lambda: _count(agent, r"-> STANDBY") or not agent.alive, 30.0, 0.1) and agent.alive, \
                procs.report()
            standby_after_s = time.monotonic() - started
            boot0, t0 = gcs.local().boot_s, time.monotonic()
            time.sleep(WATCH_S)
            boot1, t1 = gcs.local().boot_s, time.monotonic()
            assert agent.alive, procs.report()
        finally:
            procs.stop_all()
        after_stop = time.monotonic()
        time.sleep(2.0)  # the agent's shutdown leaves a vehicle that is not its own alone
        modes = gcs.modes_between(started)
        ulog_path = px4_ulog(run, 0)
    status = ulog_topic(ulog_path, "vehicle_status")
    ocm = ulog_topic(ulog_path, "offboard_control_mode")
    truth = ulog_topic(ulog_path, "vehicle_local_position_groundtruth")
    nav_window = sorted(set(status["nav_state"][_window(status, boot0, boot1)].tolist()))
    k = _window(truth, boot0, boot1)
    pos = np.column_stack([truth["x"][k], truth["y"][k], truth["z"][k]])
    moved_m = float(np.max(np.linalg.norm(pos - pos[0], axis=1)))
    sp = ulog_topic(ulog_path, "vehicle_local_position_setpoint")   # PX4's own Hold target
    j = _window(sp, boot0, boot1)
    target_moved_m = float(np.max(np.hypot(sp["x"][j] - sp["x"][j[0]], sp["y"][j] - sp["y"][j[0]])))
    rows = _rows(log)
    report = {"modes_seen_by_ground": modes, "nav_states_in_window": nav_window,
              "nav_states_whole_log": dedup(status["nav_state"].tolist()), "watched_s": t1 - t0,
              "px4_clock_window_s": boot1 - boot0, "truth_moved_m": moved_m,
              "truth_moved_horizontal_m": float(np.max(np.hypot(*(pos[:, :2] - pos[0, :2]).T))),
              "truth_moved_vertical_m": float(np.max(np.abs(pos[:, 2] - pos[0, 2]))), "truth_samples": len(k),
              "hold_target_moved_m": target_moved_m,
              "offboard_control_mode_samples": 0 if ocm is None else len(ocm["timestamp"]),
              "agent_standby_after_s": standby_after_s, "agent_states": dedup(r["state"] for r in rows),
              "agent_setpoint_rows": len(_setpoints(rows))}
    print(json.dumps(report))
    assert t1 - t0 >= WATCH_S and after_stop > t1 and len(k) > 100, report
    assert modes == ["AUTO.LOITER"], report                       # the ground's Hold, every HEARTBEAT
    assert nav_window == [PX4_NAV_AUTO_LOITER], report
    assert PX4_NAV_OFFBOARD not in status["nav_state"], report    # never OFFBOARD, in the whole flight
    assert ocm is None or len(ocm["timestamp"]) == 0, report      # PX4 received no offboard setpoint
    assert target_moved_m < 0.05, report   # PX4's Hold target stayed put: nobody asked the vehicle to move
    assert moved_m < MAX_HOLD_WANDER_M, report
    assert report["agent_setpoint_rows"] == 0 and set(report["agent_states"]) <= {"WAIT_POSITION", "STANDBY"}, report
    assert rows[-1]["reason"].startswith("vehicle armed by someone else: not ours"), rows[-1]
    assert "-> not-ours" in _console(agent), _console(agent)[-2000:]


@pytest.mark.timeout(300)
def test_arducopter_restart_while_the_ground_lands_it_keeps_landing_where_the_ground_said(shared_path, tmp_path,
                                                                                           map_path):
    """The ground takes off in GUIDED and switches to LAND at 5 m; ``fisc-agent --go`` started then changes no
    mode: the DataFlash log has no GUIDED after LAND, the vehicle lands within 1 m of where LAND was
    commanded, and the withdrawn go does not re-arm it once landed."""
    log = tmp_path / "agent1.csv"
    with ArduPilotSitl(shared_path("sitl", "ardupilot"), tmp_path, 1) as run, GroundStation("ardupilot") as gcs:
        procs = Processes(tmp_path / "logs")
        try:
            gcs.connect()
            gcs.set_mode(COPTER_GUIDED)
            gcs.arm(timeout_s=60.0)  # ArduCopter arms once its EKF uses GPS (README: 36-41 s after start)
            gcs.takeoff(5.0)
            land_seen = gcs.set_mode(COPTER_LAND)
            at_land = gcs.global_fix()
            agent = _agent(procs, "agent1", log, "ardupilot", "--go", "--map", map_path)
            gcs.wait(lambda: not gcs.armed(), 60.0, "disarmed after the ground's LAND")
            landed, disarmed_at = gcs.global_fix(), time.monotonic()
            saw_not_ours = _count(agent, r"-> not-ours")
            time.sleep(5.0)  # on the ground, disarmed: the go was withdrawn, nothing re-arms it
            assert agent.alive, procs.report()
        finally:
            procs.stop_all()
        modes, texts = dataflash_modes_and_texts(dataflash_log(run, 0))
        ground_modes = gcs.modes_between(land_seen)
        rearmed = any(b.armed for b in gcs.beats_between(disarmed_at))
    rows = _rows(log)
    report = {"dataflash_modes": modes, "modes_seen_by_ground_after_land": ground_modes,
              "land_to_disarm_s": disarmed_at - land_seen, "landed_from_land_point_m": _horizontal_m(at_land, landed),
              "land_commanded_at_m": at_land.rel_alt_m, "agent_states": dedup(r["state"] for r in rows),
              "agent_setpoint_rows": len(_setpoints(rows)), "rearmed": rearmed}
    print(json.dumps(report))
    assert COPTER_LAND in modes and COPTER_GUIDED not in modes[modes.index(COPTER_LAND):], report
    assert ground_modes == ["LAND"] and not rearmed, report
    assert report["landed_from_land_point_m"] < 1.0, report
    assert saw_not_ours and report["agent_setpoint_rows"] == 0, (report, _console(agent)[-2000:])
    assert not any("Crash" in t for t in texts), texts


# ---- no arming without a go; the ground takes over in every state ----------------------------------
def _fleet(g, *args) -> None:
    ok(run_cli(ground("cmd", *args, "--swarm", SWARM, "--zenoh-config", g.member, "--key", g.ground_key,
                      "--ack-wait", 0)))


def _status(g) -> dict:
    out = ok(run_cli(ground("status", "--swarm", SWARM, "--zenoh-config", g.member, "--json", "--wait", 1.5)))
    agents = [a for a in json.loads(out)["agents"] if a["id"] == 1]
    return agents[0] if agents else {}


GIVEN_BACK_MODE = {"px4": PX4_OFFBOARD, "ardupilot": COPTER_GUIDED}
"""The mode in which the agent flies the vehicle again once given back (PX4 OFFBOARD, ArduCopter GUIDED)."""


def _hands_off_for_good(gcs: GroundStation, g, agent, state: str, ground_mode: int, changed_s: float) -> dict:
    """After the ground changed the mode (seen at ``changed_s``) while the agent was in ``state``: the agent
    says hands-off in that state, the ground's mode stays, a swarm-wide resume changes nothing, and
    ``resume --agents 1`` gives the vehicle back (``GIVEN_BACK_MODE`` of ``gcs.autopilot`` within 10 s).
    Returns the measurements."""
    name = mode_name(ground_mode, gcs.autopilot)
    given_back = GIVEN_BACK_MODE[gcs.autopilot]
    said = poll(lambda: re.search(rf"pilot override: mode changed to \w+ in {state}, hands off", _console(agent)),
                5.0, 0.1)
    assert said, f"the agent did not go hands-off in {state}: {_console(agent)[-2500:]}"
    time.sleep(HANDS_OFF_WATCH_S)
    n_resume = _count(agent, r"fleet command resume \(swarm-wide\)")
    _fleet(g, "resume")
    assert poll(lambda: _count(agent, r"fleet command resume \(swarm-wide\)") > n_resume, 10.0, 0.1), \
        _console(agent)[-2000:]
    time.sleep(HANDS_OFF_WATCH_S)
    before_given_back = time.monotonic()
    held = gcs.modes_between(changed_s, before_given_back)
    assert held == [name], (state, held)
    _fleet(g, "resume", "--agents", 1)
    back = gcs.wait(lambda: (lambda b: b if b and b.custom_mode == given_back else None)(gcs.last_beat()),
                    10.0, f"{mode_name(given_back, gcs.autopilot)} after resume --agents 1 (hands-off in {state})")
    return {"state": state, "ground_mode_kept": held, "kept_s": before_given_back - changed_s,
            "given_back_after_s": back.t_s - before_given_back}


def _no_go_then_the_ground_takes_over(gcs: GroundStation, g, procs: Processes, agent, waiting_mode: str,
                                      ground_hold: int, ground_land: int, report: dict) -> None:
    """The agent started without ``--go``: ``NO_GO_WATCH_S`` disarmed in ``waiting_mode`` (STANDBY, telemetry
    ``waiting``), a signed ``go`` arms it; then the ground takes the vehicle with ``ground_hold`` 3 m into the agent's
    take-off and in FLOW, and with ``ground_land`` in a fleet hold (``_hands_off_for_good`` each time).  Fills
    ``report``."""
    assert poll(lambda: _count(agent, r"-> STANDBY") or not agent.alive, 90.0, 0.1), procs.report()
    waited = time.monotonic()
    telemetry = _status(g)
    time.sleep(max(0.0, NO_GO_WATCH_S - (time.monotonic() - waited)))
    # HEARTBEAT comes at 1 Hz: the watch ends with the first one at or after NO_GO_WATCH_S
    gcs.wait(lambda: (lambda b: b if b and b.t_s >= waited + NO_GO_WATCH_S else None)(gcs.last_beat()),
             5.0, f"a HEARTBEAT {NO_GO_WATCH_S:.0f} s into the no-go watch")
    beats = gcs.beats_between(waited)
    gaps = np.diff([waited] + [b.t_s for b in beats])
    report["no_go"] = {"watched_s": beats[-1].t_s - waited, "longest_gap_s": float(gaps.max()),
                       "armed_beats": sum(b.armed for b in beats), "modes": gcs.modes_between(waited),
                       "state": telemetry.get("state"), "authority": telemetry.get("authority")}
    assert report["no_go"]["longest_gap_s"] < 2.5 and report["no_go"]["armed_beats"] == 0, report
    assert report["no_go"]["modes"] == [waiting_mode], report
    assert (telemetry.get("state"), telemetry.get("authority")) == ("STANDBY", "waiting"), telemetry
    go = time.monotonic()
    _fleet(g, "go")
    report["go_to_armed_s"] = gcs.wait(lambda: (lambda b: b if b and b.armed else None)(gcs.last_beat()),
                                       20.0, "armed after the signed go").t_s - go
    # -- TAKEOFF -----------------------------------------------------------------------------
    # taken above 3 m of the agent's 5, in TAKEOFF (PX4 detects a Hold just above the ground as landed
    # and disarms; near 2 m EKF2 resets its position once, which holds the agent for 2 s: a jump hold)
    gcs.wait(lambda: gcs.global_fix().rel_alt_m > 3.0 and _last_state(agent) == "TAKEOFF", 20.0,
             "3 m into the agent's take-off")
    report["takeoff"] = _hands_off_for_good(gcs, g, agent, "TAKEOFF", ground_hold, gcs.set_mode(ground_hold))
    # -- FLOW --------------------------------------------------------------------------------
    n_flow = _count(agent, r"-> FLOW")
    assert poll(lambda: _count(agent, r"-> FLOW") > n_flow, 90.0, 0.05), _console(agent)[-2000:]
    changed = gcs.set_mode(ground_hold)
    telemetry = poll(lambda: (lambda s: s if s.get("authority") == "hands-off" else None)(_status(g)), 10.0, 0)
    report["flow"] = _hands_off_for_good(gcs, g, agent, "FLOW", ground_hold, changed)
    report["flow"]["telemetry_authority"] = (telemetry or {}).get("authority")
    assert telemetry, "telemetry never said hands-off"
    # -- a fleet hold: the agent's own hold mode, then the ground lands --------------------------
    agent_hold = {"px4": PX4_HOLD, "ardupilot": COPTER_BRAKE}[gcs.autopilot]
    _fleet(g, "hold")
    gcs.wait(lambda: gcs.mode() == agent_hold, 15.0, "the agent's own hold mode in the fleet hold")
    report["hold"] = _hands_off_for_good(gcs, g, agent, "HOLD", ground_land, gcs.set_mode(ground_land))
    report["hold"]["height_given_back_m"] = gcs.global_fix().rel_alt_m
    assert agent.alive, procs.report()


@pytest.mark.timeout(480)
def test_px4_no_arming_without_a_go_and_the_ground_takes_over_in_arm_takeoff_flow_and_a_fleet_hold(shared_path,
                                                                                                  tmp_path):
    """One PX4 vehicle, agents on Zenoh with the signed map.

    ARM: an agent with ``--go``; the ground switches to AUTO.TAKEOFF while it arms: hands-off in ARM, the
    vehicle stays disarmed in the ground's mode, no resume arms it.  Then a fresh agent without ``--go``
    waits 15 s (disarmed, STANDBY, telemetry ``waiting``) until a signed ``go`` arms it.  TAKEOFF, FLOW and
    the fleet hold (after the agent's own AUTO.LOITER, the ground picks AUTO.LAND): each time hands-off,
    the ground's mode stays through a swarm-wide ``resume``, and ``resume --agents 1`` gives it back.
    PX4's ULog: the nav_state sequence is exactly the agent's and the ground's changes, nothing else."""
    d = tmp_path
    g = signed_map_on_zenoh(d)
    zenoh = ["--swarm", SWARM, "--zenoh-config", g.member, "--trusted-key", g.ground_pub]
    report: dict = {}
    with Px4Sitl(shared_path("sitl", "px4"), d, 1) as run, GroundStation("px4") as gcs:
        procs = Processes(d / "logs")
        try:
            procs.start("publisher", ground("publish", g.served, "--swarm", SWARM, "--zenoh-config", g.hub))
            gcs.connect()
            # -- ARM: the ground changes the mode while the agent arms ---------------------------------
            first = _agent(procs, "agent_arm", d / "agent_arm.csv", "px4", "--go", "--state-file", "off", *zenoh)
            assert poll(lambda: _count(first, r"mission \w+ -> ARM") or not first.alive, 90.0, 0.02), procs.report()
            changed = gcs.set_mode(PX4_TAKEOFF)
            said = poll(lambda: re.search(r"pilot override: mode changed to \w+ in (\w+), hands off",
                                          _console(first)), 5.0, 0.1)
            assert said, _console(first)[-2500:]
            time.sleep(HANDS_OFF_WATCH_S)
            _fleet(g, "resume")
            _fleet(g, "resume", "--agents", 1)
            assert poll(lambda: _count(first, r"fleet command resume \(addressed\)"), 10.0, 0.1), _console(first)
            time.sleep(HANDS_OFF_WATCH_S)
            beats = gcs.beats_between(changed)
            report["arm"] = {"hands_off_in": said.group(1), "modes": gcs.modes_between(changed),
                             "armed_beats": sum(b.armed for b in beats), "watched_s": beats[-1].t_s - changed}
            assert said.group(1) == "ARM" and report["arm"]["modes"] == ["AUTO.TAKEOFF"], report
            assert report["arm"]["armed_beats"] == 0, report
            procs.stop(first)
            gcs.set_mode(PX4_HOLD)  # the ground puts its vehicle back as it was
            # -- no arming without a go; TAKEOFF, FLOW, a fleet hold ----------------------------------
            agent = _agent(procs, "agent1", d / "agent1.csv", "px4", "--takeoff-alt", 5.0, *NO_WINDOWS, *zenoh)
            _no_go_then_the_ground_takes_over(gcs, g, procs, agent, "AUTO.LOITER", PX4_HOLD, PX4_LAND, report)
        finally:
            procs.stop_all(order=lambda p: 0 if p.name.startswith("agent") else 1)
        nav = dedup(ulog_topic(px4_ulog(run, 0), "vehicle_status")["nav_state"].tolist())
    every, scripted = _mode_requests(gcs, first, agent)
    report.update(nav_states=nav, mode_requests=every)
    print(json.dumps(report, default=str))
    # the requests: the ground's AUTO.TAKEOFF in ARM (no OFFBOARD before it) / the ground's Hold back / OFFBOARD
    # (the go) / the ground's Hold in TAKEOFF / given back / the ground's Hold in FLOW / given back / the agent's
    # fleet hold / the ground's Land / given back; and, anywhere, a self-resuming hold (EKF2 resets its position
    # once near 2 m in the take-off: a jump hold of about 2 s, hold_grace_s, that may ask for Hold and OFFBOARD)
    assert scripted == ["AUTO.TAKEOFF", "AUTO.LOITER", "OFFBOARD", "AUTO.LOITER", "OFFBOARD", "AUTO.LOITER",
                        "OFFBOARD", "AUTO.LOITER", "AUTO.LAND", "OFFBOARD"], report
    # PX4 logs from boot: Hold on the ground, then exactly the requests, then perhaps the shutdown hold (SIGTERM)
    nav_of = {"AUTO.LOITER": PX4_NAV_AUTO_LOITER, "OFFBOARD": PX4_NAV_OFFBOARD, "AUTO.TAKEOFF": PX4_NAV_AUTO_TAKEOFF,
              "AUTO.LAND": PX4_NAV_AUTO_LAND}
    expected = dedup([PX4_NAV_AUTO_LOITER] + [nav_of[name] for name in every])
    assert nav[:len(expected)] == expected and nav[len(expected):] in ([], [PX4_NAV_AUTO_LOITER]), report


@pytest.mark.timeout(420)   # up to 300 s waiting for the machine's SITL lock, then about 105 s
def test_arducopter_no_arming_without_a_go_and_the_ground_takes_over_in_takeoff_flow_and_a_fleet_hold(shared_path,
                                                                                                      tmp_path):
    """The ArduCopter twin of the PX4 test above, one vehicle, the agent on Zenoh with the signed map.

    The agent without ``--go`` waits 15 s (disarmed in STABILIZE, STANDBY, telemetry ``waiting``) until a signed
    ``go`` arms it.  The ground takes the vehicle with BRAKE 3 m into the agent's take-off and in FLOW (not
    LOITER: with no RC its throttle stick reads low and LOITER descends), and with LAND in a fleet hold after
    the agent's own BRAKE: each time hands-off, the ground's mode stays through a swarm-wide ``resume``, and
    ``resume --agents 1`` gives GUIDED back.  ArduCopter's DataFlash MODE sequence is exactly the agent's and
    the ground's changes, nothing else.

    The ARM-state takeover of the PX4 test is left out: ArduPilotSitl returns once the pre-arm checks pass,
    and the agent's ARM is then one GUIDED request and one arm command (accepted at once), too quick for a
    ground station to come between them reliably.

    Measured (2026-12-05, this 2-core host, other sessions' SITL runs queued on the lock): four runs, the first
    expecting a STABILIZE that DataFlash does not log (it opens at the go), the next three passing.  No arming
    over 14.5-14.6 s of HEARTBEATs in STANDBY; go to armed 0.54-1.55 s; the ground's BRAKE kept 6.5-6.6 s in TAKEOFF and
    8.2-8.6 s in FLOW, its LAND 6.4-6.6 s in the hold (given back at 6.8-7.0 m); GUIDED again 0.31-0.62 s after
    ``resume --agents 1``; DataFlash [4, 17, 4, 17, 4, 17, 9, 4, 17] each time.  About 105 s from the SITL start
    to the end (pre-arm checks passing 24 s after start), plus the wait for the lock."""
    d = tmp_path
    g = signed_map_on_zenoh(d)
    zenoh = ["--swarm", SWARM, "--zenoh-config", g.member, "--trusted-key", g.ground_pub]
    report: dict = {}
    with ArduPilotSitl(shared_path("sitl", "ardupilot"), d, 1) as run, GroundStation("ardupilot") as gcs:
        procs = Processes(d / "logs")
        try:
            procs.start("publisher", ground("publish", g.served, "--swarm", SWARM, "--zenoh-config", g.hub))
            gcs.connect()
            agent = _agent(procs, "agent1", d / "agent1.csv", "ardupilot", "--takeoff-alt", 5.0, *NO_WINDOWS, *zenoh)
            _no_go_then_the_ground_takes_over(gcs, g, procs, agent, "STABILIZE", COPTER_BRAKE, COPTER_LAND, report)
            flying_again = time.monotonic()   # given back after the ground's LAND: the agent flies on in GUIDED
            time.sleep(HANDS_OFF_WATCH_S)
            report["modes_after_the_last_give_back"] = gcs.modes_between(flying_again)
            assert report["modes_after_the_last_give_back"] == ["GUIDED"] and agent.alive, report
        finally:
            procs.stop_all(order=lambda p: 0 if p.name.startswith("agent") else 1)
        modes, texts = dataflash_modes_and_texts(dataflash_log(run, 0))
    every, scripted = _mode_requests(gcs, agent)
    report.update(dataflash_modes=modes, mode_requests=every)
    print(json.dumps(report, default=str))
    assert not any("Crash" in t for t in texts), texts
    # the requests: GUIDED (the go) / the ground's BRAKE in TAKEOFF / given back / the ground's BRAKE in FLOW /
    # given back / the agent's fleet hold (BRAKE) / the ground's LAND / given back; and, anywhere, a self-resuming hold
    assert scripted == ["GUIDED", "BRAKE", "GUIDED", "BRAKE", "GUIDED", "BRAKE", "LAND", "GUIDED"], report
    # DataFlash logs from the go on (the log opens as the agent asks for GUIDED and arms; STABILIZE before it is
    # the ground's view above): exactly the requests, then perhaps the shutdown hold
    number_of = {"GUIDED": COPTER_GUIDED, "BRAKE": COPTER_BRAKE, "LAND": COPTER_LAND}
    expected = [number_of[name] for name in every]
    assert modes[:len(expected)] == expected and modes[len(expected):] in ([], [COPTER_BRAKE]), report


# ---- a link loss during which PX4's failsafe lands ----------------------------------------------------
LOST_S = 6.0
"""How long the link is gone: longer than PX4's COM_OF_LOSS_T (0.5 s here) and the agent's --link-timeout (3 s)."""

LOST_AT_M = 6.0
"""Height above home at which the link is lost [m] (the agent joins the map 10 m above its start)."""


def _failsafe_land_flight(shared_path, tmp_path: Path, map_path: Path, how: str) -> dict:
    """Fly with PX4's offboard-loss action Land; in JOIN, lose the agent's link for ``LOST_S`` (``how``:
    ``cut``, a relay drops every datagram both ways while both ends run; ``freeze``, SIGSTOP the agent),
    then restore it and watch PX4 until it has landed and disarmed.  Returns the measurements."""
    log = tmp_path / "agent1.csv"
    params = {"COM_OBL_RC_ACT": 4, "COM_OF_LOSS_T": 0.5}  # 4: Land (PX4 commander params)
    with Px4Sitl(shared_path("sitl", "px4"), tmp_path, 1, params=params) as run, GroundStation("px4") as gcs, \
            LinkCut(14540) as link:
        procs = Processes(tmp_path / "logs")
        try:
            gcs.connect()
            agent = _agent(procs, "agent1", log, "px4", "--go", "--map", map_path, *NO_WINDOWS, port=link.agent_port)
            assert poll(lambda: _count(agent, r"-> JOIN") or not agent.alive, 90.0, 0.05) and agent.alive, \
                procs.report()
            # high enough that PX4's Land is still under way when the link returns (from 2.5 m it had landed)
            gcs.wait(lambda: gcs.global_fix().rel_alt_m > LOST_AT_M, 30.0, f"{LOST_AT_M} m in the agent's join")
            if how == "freeze":
                os.killpg(agent.popen.pid, signal.SIGSTOP)
            else:
                link.down = True
            lost = time.monotonic()
            landing = gcs.wait(lambda: (lambda b: b if b and b.custom_mode == PX4_LAND else None)(gcs.last_beat()),
                               10.0, "PX4's failsafe AUTO.LAND")
            time.sleep(max(0.0, LOST_S - (time.monotonic() - lost)))
            height_back_m, boot_back = gcs.global_fix().rel_alt_m, gcs.local().boot_s
            if how == "freeze":
                os.killpg(agent.popen.pid, signal.SIGCONT)
            else:
                link.down = False
            back, back_wall = time.monotonic(), time.time()

            def landed_or_taken_back():
                b = gcs.last_beat()
                if b is not None and not b.armed:
                    return b
                # OFFBOARD while armed after the link is back: the failsafe was overridden, no need to wait on
                return "offboard" if any(x.armed and x.custom_mode == PX4_OFFBOARD
                                         for x in gcs.beats_between(back)) else None

            ended = poll(landed_or_taken_back, 40.0, 0.05)
            disarmed = ended if ended != "offboard" else None
            end = disarmed.t_s if disarmed else time.monotonic()
            if disarmed:
                time.sleep(3.0)
            # the agent ends its flight once the vehicle is disarmed (DONE, exit 0); it must not have crashed
            assert agent.alive or agent.popen.returncode == 0, procs.report()
        finally:
            procs.stop_all()
        ground_modes = dedup(mode_name(b.custom_mode, "px4") for b in gcs.beats_between(landing.t_s, end) if b.armed)
        rearmed = bool(disarmed) and any(b.armed for b in gcs.beats_between(disarmed.t_s))
        ulog_path = px4_ulog(run, 0)
    status = ulog_topic(ulog_path, "vehicle_status")
    ocm = ulog_topic(ulog_path, "offboard_control_mode")
    nav = status["nav_state"]
    first_land = int(np.flatnonzero(nav == PX4_NAV_AUTO_LAND)[0])
    changes = [(round(float(t) / 1e6, 2), int(n)) for k, (t, n) in enumerate(zip(status["timestamp"], nav))
               if k == 0 or n != nav[k - 1]]
    back_rows = [r for r in _rows(log) if float(r["wall_time_s"]) > back_wall]
    return {"how": how, "nav_states": dedup(nav.tolist()), "nav_changes_px4_s": changes,
            "after_failsafe_armed": dedup(nav[first_land:][status["arming_state"][first_land:] == 2].tolist()),
            "ground_modes_armed_from_landing": ground_modes,
            "lost_to_land_s": landing.t_s - lost, "back_to_disarm_s": (disarmed.t_s - back) if disarmed else None,
            "height_when_back_m": height_back_m, "link_back_at_px4_s": boot_back, "rearmed": rearmed,
            "setpoints_after_back": 0 if ocm is None else int(np.sum(ocm["timestamp"] / 1e6 > boot_back + 0.5)),
            "agent_states_after_back": dedup(r["state"] for r in back_rows),
            "agent_reasons_after_back": dedup(r["reason"] for r in back_rows)[:3],
            "agent_setpoint_rows_after_back": len(_setpoints(back_rows)), "dropped_datagrams": link.dropped}


def _assert_kept_landing(r: dict) -> None:
    # from the failsafe to the disarm only AUTO_LAND (once disarmed PX4 itself shows the user's intention,
    # OFFBOARD, again: its offboard-loss Land is a mode fallback, Failsafe::checkModeFallback)
    assert r["after_failsafe_armed"] == [PX4_NAV_AUTO_LAND], r
    assert r["ground_modes_armed_from_landing"] == ["AUTO.LAND"] and r["back_to_disarm_s"] is not None, r
    assert not r["rearmed"], r
    assert r["setpoints_after_back"] == 0 and r["agent_setpoint_rows_after_back"] == 0, r
    assert r["height_when_back_m"] > 0.5, r   # the link came back while the vehicle was still in the air


@pytest.mark.timeout(240)
def test_px4_failsafe_land_during_a_link_cut_is_not_overridden_when_the_link_returns(shared_path, tmp_path,
                                                                                      map_path):
    """COM_OBL_RC_ACT = 4 (Land), COM_OF_LOSS_T = 0.5 s.  The link between agent and PX4 is cut for 6 s while
    the agent joins the map (both keep running): PX4 lands.  When the link returns the vehicle keeps landing:
    no OFFBOARD after the failsafe (ULog nav_state and every HEARTBEAT), no setpoint after the link is back
    (offboard_control_mode, the agent's log), disarmed on the ground and not re-armed."""
    r = _failsafe_land_flight(shared_path, tmp_path, map_path, "cut")
    print(json.dumps(r))
    _assert_kept_landing(r)


@pytest.mark.timeout(240)
def test_px4_failsafe_land_while_the_agent_is_frozen_is_not_overridden_when_it_runs_again(shared_path, tmp_path,
                                                                                           map_path):
    """As the link cut, but the agent itself stalls (SIGSTOP for 6 s, then SIGCONT): a companion computer
    that hangs.  PX4 lands; when the agent runs again the vehicle must keep landing."""
    r = _failsafe_land_flight(shared_path, tmp_path, map_path, "freeze")
    print(json.dumps(r))
    assert r["lost_to_land_s"] < 5.0 and r["height_when_back_m"] > 0.5, r   # the set-up itself
    # (this found the agent reading the UDP backlog of old OFFBOARD heartbeats as current: it now drops
    # what queued up while it stalled and waits for a fresh HEARTBEAT, Runner._tick)
    _assert_kept_landing(r)


# ---- vehicle health: a draining battery ends the laps at the exit -------------------------------------
MIN_BATTERY_PCT = 60.0
BATTERY_DRAIN_S = 80.0
"""PX4's battery simulator (``battery_simulator``, SIM_BAT_ENABLE) drains a full battery in SIM_BAT_DRAIN
seconds while armed, down to SIM_BAT_MIN_PCT: 80 s puts 60 % about 32 s after arming, inside the first
pass (flown 23-43 s after arming on this host)."""


@pytest.mark.timeout(240)
def test_px4_battery_below_min_battery_ends_the_laps_at_the_exit(shared_path, tmp_path, map_path):
    """``--exit-policy loop --laps 0`` (no limit) and ``--min-battery 60``; PX4's simulated battery drains
    (SIM_BAT_DRAIN 80 s, floor SIM_BAT_MIN_PCT 20 %).  The agent finishes the pass it is in, flies to its
    exit point and lands there (``--low-battery-action land``): PX4's ULog shows the agent's AUTO.LAND past
    the outlet with battery_status below 60 %, then the disarm; no pass starts below 60 %."""
    log = tmp_path / "agent1.csv"
    params = {"SIM_BAT_DRAIN": BATTERY_DRAIN_S, "SIM_BAT_MIN_PCT": 20.0}
    with Px4Sitl(shared_path("sitl", "px4"), tmp_path, 1, params=params) as run, GroundStation("px4") as gcs:
        procs = Processes(tmp_path / "logs")
        try:
            gcs.connect()
            agent = _agent(procs, "agent1", log, "px4", "--go", "--map", map_path, *NO_WINDOWS, "--exit-policy", "loop",
                           "--laps", 0, "--min-battery", MIN_BATTERY_PCT, "--low-battery-action", "land")
            assert poll(lambda: gcs.armed() or not agent.alive, 60.0, 0.1), procs.report()
            # the ground's 1 Hz HEARTBEAT view may lag the agent, which exits as soon as it sees the disarm
            disarmed = poll(lambda: (lambda b: b if b and not b.armed else None)(gcs.last_beat()), 150.0, 0.2)
            assert disarmed, procs.report()
            assert poll(lambda: not agent.alive, 10.0, 0.2), procs.report()  # its flight is over: DONE
        finally:
            procs.stop_all()
        ulog_path = px4_ulog(run, 0)
    status, battery = ulog_topic(ulog_path, "vehicle_status"), ulog_topic(ulog_path, "battery_status")
    truth = ulog_topic(ulog_path, "vehicle_local_position_groundtruth")
    nav, t_nav = status["nav_state"], status["timestamp"]
    first_land = int(np.flatnonzero(nav == PX4_NAV_AUTO_LAND)[0])

    def at(data, key, t_us):
        return float(data[key][min(np.searchsorted(data["timestamp"], t_us), len(data[key]) - 1)])

    console = _console(agent)
    low = re.search(r"battery (\d+) % below (\d+) % after lap (\d+): to the exit, then land", console)
    passes = len(re.findall(r"-> FLOW", console))
    report = {"nav_states": dedup(nav.tolist()), "agent_states": dedup(r["state"] for r in _rows(log)),
              "low_battery_line": low.group(0) if low else None, "passes_started": passes,
              "battery_at_land_pct": 100 * at(battery, "remaining", t_nav[first_land]),
              "x_at_land_m": at(truth, "x", t_nav[first_land]), "z_at_land_m": at(truth, "z", t_nav[first_land]),
              "land_to_disarm_s": (t_nav[-1] - t_nav[first_land]) / 1e6, "exit_code": agent.popen.returncode}
    print(json.dumps(report))
    assert low and int(low.group(3)) == passes, report            # the pass in progress finished, no new one
    assert report["nav_states"][-2:] == [PX4_NAV_OFFBOARD, PX4_NAV_AUTO_LAND] or \
        report["nav_states"][-3:-1] == [PX4_NAV_OFFBOARD, PX4_NAV_AUTO_LAND], report   # the agent's land
    assert report["battery_at_land_pct"] < MIN_BATTERY_PCT and report["x_at_land_m"] > 15.0, report  # at the exit
    assert report["agent_states"][-3:] == ["EXIT", "LAND", "DONE"] and report["exit_code"] == 0, report


AP_MIN_BATTERY_PCT = 75.0
AP_BATT_CAPACITY_MAH = 700.0
"""ArduCopter's reported battery (BATT_MONITOR 4, copter.parm) is 100 * (1 - used mAh / BATT_CAPACITY); its SITL
quad draws 23-31 A while flying (DataFlash BAT.Curr, 2026-12-05), about 7.8 mAh/s: 700 mAh, set at boot,
puts 75 % about 25 s after arming, inside the first pass (flown 15-35 s after arming on this host), and
leaves about 36 % at the disarm.  SIM_BATT_CAP_AH is not set: in this build the quad's simulated voltage
stayed at SIM_BATT_VOLTAGE (12.60 V) over 706 mAh with SIM_BATT_CAP_AH 1.0 set at boot, so only
BATT_CAPACITY drives the percentage (BATTERY_STATUS.battery_remaining, SYS_STATUS)."""


def _dataflash_series(path: Path) -> dict[str, list[tuple[float, float]]]:
    """(boot s, value) series of an ArduPilot DataFlash log: ``mode`` (MODE.Mode), ``battery_pct``
    (BAT.RemPct), ``north_m`` (XKF1.PN of the primary core) and ``armed`` (ARM.ArmState)."""
    from pymavlink import DFReader

    log = DFReader.DFReader_binary(str(path))
    out: dict[str, list[tuple[float, float]]] = {"mode": [], "battery_pct": [], "north_m": [], "armed": []}
    while True:
        m = log.recv_match(type=["MODE", "BAT", "XKF1", "ARM"])
        if m is None:
            return out
        t, kind = m.TimeUS / 1e6, m.get_type()
        if kind == "MODE":
            out["mode"].append((t, float(m.Mode)))
        elif kind == "BAT":
            out["battery_pct"].append((t, float(m.RemPct)))
        elif kind == "XKF1" and m.C == 0:
            out["north_m"].append((t, float(m.PN)))
        elif kind == "ARM":
            out["armed"].append((t, float(m.ArmState)))


def _at(series: list[tuple[float, float]], t_s: float) -> float:
    """The last value of ``series`` at or before ``t_s`` (the first one if none is)."""
    before = [v for t, v in series if t <= t_s]
    return before[-1] if before else series[0][1]


@pytest.mark.timeout(300)
def test_arducopter_battery_below_min_ends_the_laps_at_the_exit(shared_path, tmp_path, map_path):
    """``--exit-policy loop --laps 0`` (no limit) and ``--min-battery 75``; ArduCopter's reported battery drains
    (BATT_CAPACITY 700 mAh at boot).  The agent finishes the pass it is in, flies to its exit point and
    lands there: ArduCopter's DataFlash log shows GUIDED, then the agent's LAND past the outlet with BAT.RemPct
    below 75 %, then the disarm; no pass starts below 75 %; the agent exits 0.

    Measured (2026-12-05, this 2-core host, another SITL test run waiting on the lock): BAT.RemPct crossed 75 %
    about 25 s after arming, inside the first pass (FLOW 14.6-34.7 s after arming).  Run 1: "battery 64 % below
    75 % after lap 1", LAND at 61 % and x 16.78 m (outlet 15 m), disarm 22.8 s after LAND, arm to disarm
    59.9 s, 104 s from the SITL start to the end.  Run 2: 64 %, LAND at 61 % and x 16.77 m, 22.8 s, 60.0 s,
    104 s."""
    x_outlet_m = MapGeometry.from_field(CommandField.from_map(load_map(map_path))).x_outlet_m
    log = tmp_path / "agent1.csv"
    params = {"BATT_CAPACITY": AP_BATT_CAPACITY_MAH}
    with ArduPilotSitl(shared_path("sitl", "ardupilot"), tmp_path, 1, params=params) as run, \
            GroundStation("ardupilot") as gcs:
        procs = Processes(tmp_path / "logs")
        try:
            gcs.connect()
            agent = _agent(procs, "agent1", log, "ardupilot", "--go", "--map", map_path, *NO_WINDOWS,
                           "--exit-policy", "loop", "--laps", 0, "--min-battery", AP_MIN_BATTERY_PCT)
            assert poll(lambda: gcs.armed() or not agent.alive, 60.0, 0.1), procs.report()
            armed_at = time.monotonic()
            disarmed = poll(lambda: (lambda b: b if b and not b.armed else None)(gcs.last_beat()) or
                            (None if agent.alive else "agent exited"), 120.0, 0.2)
            assert disarmed and disarmed != "agent exited", procs.report()
            assert poll(lambda: not agent.alive, 10.0, 0.2), procs.report()  # its flight is over: DONE
        finally:
            procs.stop_all()
        df = _dataflash_series(dataflash_log(run, 0))
    modes = dedup(int(v) for _, v in df["mode"])
    lands = [t for t, v in df["mode"] if int(v) == COPTER_LAND]
    disarms = [t for t, v in df["armed"] if v == 0.0]
    console = _console(agent)
    low = re.search(r"battery (\d+) % below (\d+) % after lap (\d+): to the exit, then land", console)
    passes = len(re.findall(r"-> FLOW", console))
    t_land = lands[0] if lands else math.nan
    report = {"dataflash_modes": modes, "agent_states": dedup(r["state"] for r in _rows(log)),
              "low_battery_line": low.group(0) if low else None, "passes_started": passes,
              "battery_at_land_pct": _at(df["battery_pct"], t_land) if lands else None,
              "x_at_land_m": _at(df["north_m"], t_land) if lands else None, "x_outlet_m": x_outlet_m,
              "land_to_disarm_s": (disarms[-1] - t_land) if lands and disarms else None,
              "arm_to_disarm_s": disarmed.t_s - armed_at, "exit_code": agent.popen.returncode}
    print(json.dumps(report))
    assert low and int(low.group(3)) == passes, report            # the pass in progress finished, no new one
    assert modes[-2:] == [COPTER_GUIDED, COPTER_LAND] and len(lands) >= 1, report   # the agent's LAND, nothing after
    assert report["battery_at_land_pct"] < AP_MIN_BATTERY_PCT and report["x_at_land_m"] > x_outlet_m, report
    assert disarms and disarms[-1] > t_land, report               # landed and disarmed in LAND
    assert report["agent_states"][-3:] == ["EXIT", "LAND", "DONE"] and report["exit_code"] == 0, report


# ---- vehicle health: a GPS glitch makes the agent hold, then recover ------------------------------------
GLITCH_DEG = 0.0003
"""SIM_GPS1_GLTCH_X: ArduPilot's SITL adds it to the simulated fix's latitude in degrees (SIM_GPS.cpp): about
33 m north, beyond EKF3's EK3_GLITCH_RAD (25 m), so EKF3 reports the glitch ("GPS Glitch or Compass error")."""


@pytest.mark.timeout(300)
def test_arducopter_gps_glitch_makes_the_agent_hold_then_recover(shared_path, tmp_path, map_path):
    """One ArduCopter flown by ``fisc-agent --go``; in FLOW the ground sets SIM_GPS1_GLTCH_X (about 33 m) for
    5 s, then clears it.  The agent holds on the estimator's GNSS-glitch flag (EKF_STATUS_REPORT), and once
    the track is consistent again it flies on: DataFlash GUIDED, the hold (BRAKE), GUIDED again."""
    log = tmp_path / "agent1.csv"
    with ArduPilotSitl(shared_path("sitl", "ardupilot"), tmp_path, 1) as run, GroundStation("ardupilot") as gcs:
        procs = Processes(tmp_path / "logs")
        try:
            gcs.connect()
            agent = _agent(procs, "agent1", log, "ardupilot", "--go", "--map", map_path, *NO_WINDOWS)
            assert poll(lambda: _count(agent, r"-> FLOW") or not agent.alive, 150.0, 0.1), procs.report()
            time.sleep(2.0)
            glitched = time.monotonic()
            gcs.set_param("SIM_GPS1_GLTCH_X", GLITCH_DEG)
            time.sleep(5.0)
            gcs.set_param("SIM_GPS1_GLTCH_X", 0.0)
            held = poll(lambda: re.search(r"FLOW -> HOLD \(position jump: ([^)]*)\)", _console(agent)), 5.0, 0.1)
            after = held.end() if held else len(_console(agent))   # the resume comes after the hold
            n_ok = _count(agent, r"position integrity OK again")
            consistent = poll(lambda: _count(agent, r"position integrity OK again") > n_ok, 40.0, 0.2)
            recovered = poll(lambda: re.search(r"HOLD -> (FLOW|RETURN|JOIN|EXIT) ", _console(agent)[after:]), 10.0, 0.2)
            # the agent's GUIDED request reaches the ground's HEARTBEATs a moment after its transition
            poll(lambda: "GUIDED" in gcs.modes_between(glitched)[2:], 5.0, 0.1)
            ground_modes = gcs.modes_between(glitched)
            assert agent.alive, procs.report()
        finally:
            procs.stop_all()
        modes, _ = dataflash_modes_and_texts(dataflash_log(run, 0))
    report = {"hold_reason": held.group(1) if held else None, "integrity_ok_again": bool(consistent),
              "recovered_to": recovered.group(1) if recovered else None, "ground_modes_from_glitch": ground_modes,
              "dataflash_modes": modes, "agent_states": dedup(r["state"] for r in _rows(log))}
    print(json.dumps(report))
    assert held and "glitch" in held.group(1).lower(), report          # the hold: a real failure if missing
    assert consistent and ground_modes[:2] == ["GUIDED", "BRAKE"], report
    # (this found the escalated jump hold latched for good: a GPS-glitch hold now escalates without latching)
    assert recovered and "GUIDED" in ground_modes[2:], report
