"""Fault injection, one emulated flight: kill -9 each kind of FISC process in turn, at a seeded
random moment, and check what must happen (issue 38, item 3).

Real processes on one free lab port (the Zenoh lab default, no config file):

    first      fisc-ground status --wait 600   started first: it holds the lab port
    recorder   fisc-ground monitor --record    the ground's witness, never killed
    publisher  fisc-ground publish MAP
    monitor    fisc-ground monitor --record    killed, then restarted
    vehicles   fisc-sim autopilot + fisc-agent --go, ids 100 and 101 (stand-alone, PX4 personality)
    emulate    fisc-sim emulate --agents N --swarm   (N from FISC_FAULT_AGENTS, default 20; ids 0..N-1)

Once both stand-alone vehicles fly and a ``status`` hears every agent, one fault every ``SLOT_S``
seconds, each at a random delay (seed ``FISC_FAULT_SEED``, default 38; every kill is printed and
written to kills.jsonl):

==========  =====================================================================================
fault        what must happen (checked on the recorder's MCAP log unless said otherwise)
==========  =====================================================================================
status       a running ``status`` killed: nobody notices; every agent heard without a gap > 3 s
             (the monitors' --stale-after; the same limit for every "heard throughout" below)
cmd          a running ``cmd hold --agents 0-2,999`` (signed; 999 is nobody, so it is still waiting
             for acknowledgements, or still starting, when killed): the hold reached every target
             or none (0-2 fly in one emulate worker, one Zenoh session: a sample arrives whole or
             not at all), all acting on one command, no agent refusing a command (no half command
             decoded); no other agent acknowledges it; a delivered hold is flown (HOLD within
             3 s, not a failsafe) and a completed ``cmd resume --agents 0-2`` afterwards, acknowledged
             by the three, has them flying again within 5 s; an undelivered one leaves them flying
             throughout; everyone heard throughout
publisher    every agent keeps its map (same sha256) and its flight; no gap > 3 s; nothing alarms
monitor      the recorder hears everyone throughout; the killed monitor's log is readable up to
             the kill; a monitor started right after hears every agent within 5 s
agent 100    its vehicle's autopilot fails safe (PX4 offboard loss: "Failsafe: offboard setpoints
             lost"); the ground alarms ``stale`` naming 100 within stale-after + 4 s; the others
             are heard throughout
autopilot    (the emulator of 101) agent 101 loses MAVLink, holds (failsafe, no ``mavlink_ok``) within
             5 s, keeps its map and keeps reporting (no gap > 3 s); the others are heard throughout
first        the holder of the lab port killed: every agent is still heard for 15 s, no gap > 3 s,
             and a ``status --wait 5`` started 8 s later lists every flying agent; whatever
             happens, a silence the ground suffers is alarmed
whole        no agent ever flies a map other than the signed one; the stand-alone agents hold in
flight       no failsafe before their own kill; an emulated agent never holds but for a delivered
             ``cmd hold`` (a hold for a cause only a starved emulator makes, position stale or PX4
             offboard loss, while the emulate reports an emulator loop stall >= 0.5 s, makes the
             case xfail "inconclusive" with the holds listed; any other hold fails); no vehicle
             leaves the duct (every spell outside the CVs is the geofence's RETURN or HOLD and
             ends within 15 s); emulate ends normally
==========  =====================================================================================
"""

from __future__ import annotations

import os
import subprocess
import time
from dataclasses import dataclass

import pytest

from .evidence import EXCURSION_MAX_S, Evidence, emulated_holds, read_evidence
from .lab import FaultLab, ground, listening
from .outcomes import (HUB_OBSERVE_S, NEWCOMER_AFTER_S, SLOT_S, cmd_acted, heard_throughout,
                       kill_a_running_cmd, keeps_map_and_flight, killed_cmd_reached_all_or_none,
                       lab_port_holder_loses_no_link, lab_port_holder_silence_is_alarmed,
                       lost_autopilot_agent_holds_and_reports, monitor_restart_hears_everyone,
                       nothing_stale_alarmed, stale_alarm_names)
from ..e2e.conftest import Proc, cli, poll

pytestmark = pytest.mark.slow

SWARM = "faults"
N_AGENTS = int(os.environ.get("FISC_FAULT_AGENTS", "20"))
"""Emulated vehicles (ids 0..N-1), the issue's 20.  Measured 2026-12-05 on the shared 2-core machine
(load 2-2.7 from other work): two 20-vehicle flights passed (seeds 38 and 42, 111-112 s each), the
emulate's loops keeping real time (largest emulator loop gap 0.03-0.06 s, agent loop 0.07-0.08 s;
0.34 of a core for the 20).  An earlier attempt, on the machine shared by five workers, starved the
emulator (gaps near 1 s, every position stale, the fleet holding hands-off): such a flight reports
the holds as xfail "inconclusive" (``evidence.emulated_holds``); ``FISC_FAULT_AGENTS=10`` flies fewer."""
DURATION_S = 100
"""``fisc-sim emulate --duration``: outlives the last observation window on this 2-core machine."""
KILLED_AGENT, KILLED_EMULATOR = 100, 101
CMD_TARGETS = (0, 1, 2)
"""The killed ``cmd hold``'s agents, in one emulate agent process (one per 300 agents,
``sim.emulate.config``): one Zenoh session receives the command for the three."""


@dataclass
class Flight:
    """The finished flight: the lab, the recorder's evidence and the processes to judge."""

    lab: FaultLab
    ev: Evidence
    restarted: Proc
    emulate: Proc
    emulate_ran_to_the_end: bool
    newcomer: subprocess.CompletedProcess
    """``fisc-ground status --json`` started after the lab port's holder was killed."""
    cmd_started_s: float
    """Wall-clock start of the killed ``cmd hold`` [UNIX s]."""
    resume: subprocess.CompletedProcess
    """The completed ``cmd resume --agents 0-2`` that follows it."""
    resume_sent_s: tuple[float, float]
    """Wall-clock start and end of that resume [UNIX s]."""

    def survivors(self, t_s: float) -> list[int]:
        """Agents that must be heard at ``t_s``: the emulated fleet, 101, and 100 until its kill."""
        ids = list(range(N_AGENTS)) + [KILLED_EMULATOR]
        return ids + ([KILLED_AGENT] if t_s < self.lab.kills.of("agent").t_s else [])

    def proc(self, name: str) -> Proc:
        return next(p for p in self.lab.procs.procs if p.name == name)


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Flight:
    lab = FaultLab(tmp_path_factory.mktemp("faults"), SWARM)
    try:
        return _fly(lab)
    finally:
        lab.stop_all()


def _fly(lab: FaultLab) -> Flight:
    d, kills = lab.dir, lab.kills
    lab.prepare()
    first = lab.start("first", ground("status", "--swarm", SWARM, "--wait", "600", "--json"))
    # it has opened its session first (today it listens on the lab port; a mesh may log it only)
    assert poll(lambda: listening(lab.port) or "lab default" in first.log_tail(), 30), lab.procs.report()
    recorder = lab.monitor("recorder", d / "recorder.mcap")
    publisher = lab.start("publisher", ground("publish", lab.map, "--swarm", SWARM))
    monitor = lab.monitor("monitor", d / "monitor.mcap")
    _, agent_100 = lab.start_vehicle(KILLED_AGENT, 0.0)
    autopilot_101, agent_101 = lab.start_vehicle(KILLED_EMULATOR, 1.5)
    emulate = lab.start("emulate", cli("fisc-sim") + [
        "emulate", "--map", lab.map, "--agents", N_AGENTS, "--duration", DURATION_S, "--swarm", SWARM,
        "--trusted-key", lab.pub, "--mode", "staggered", "--no-compare", "--no-figures", "-q", "-o", d / "emu"])
    lab.wait_in_air(agent_100, 90)
    lab.wait_in_air(agent_101, 30)
    everyone = set(range(N_AGENTS)) | {KILLED_AGENT, KILLED_EMULATOR}
    assert poll(lambda: everyone <= lab.heard(), 90, period_s=0.0), lab.procs.report()

    status = lab.start("status", ground("status", "--swarm", SWARM, "--wait", "30", "--json"))
    kills.kill_at("status", status, 1.5, 3.0)
    time.sleep(SLOT_S)
    cmd_run = kill_a_running_cmd(lab, CMD_TARGETS)
    kills.kill_at("publisher", publisher, 0.0, 2.0)
    time.sleep(SLOT_S)
    kills.kill_at("monitor", monitor, 0.0, 2.0)
    restarted = lab.monitor("monitor-restarted", d / "restarted.mcap", "--duration", "10")
    time.sleep(SLOT_S)
    kills.kill_at("agent", agent_100, 0.0, 2.0)
    time.sleep(SLOT_S)
    kills.kill_at("autopilot", autopilot_101, 0.0, 2.0)
    time.sleep(SLOT_S)
    hub_kill = kills.kill_at("first", first, 0.0, 2.0)
    time.sleep(NEWCOMER_AFTER_S)  # a newcomer asks who flies (it finds the lab port free)
    newcomer = lab.run(ground("status", "--swarm", SWARM, "--wait", "5", "--json"))
    (d / "newcomer.json").write_text(newcomer.stdout)
    (d / "newcomer.err").write_text(newcomer.stderr)
    time.sleep(max(0.0, hub_kill.t_s + HUB_OBSERVE_S - time.time()))

    ran_to_the_end = emulate.alive
    assert poll(lambda: not emulate.alive, DURATION_S + 60, period_s=0.5), lab.procs.report()
    assert poll(lambda: not restarted.alive, 30), lab.procs.report()
    assert lab.interrupt(recorder) == 0, recorder.log_tail()  # Ctrl-C: the monitor closes its MCAP log
    return Flight(lab, read_evidence(d / "recorder.mcap"), restarted, emulate, ran_to_the_end, newcomer,
                  *cmd_run)


def test_a_running_status_killed_disturbs_nobody(flight):
    heard_throughout(flight, flight.lab.kills.of("status"))


def test_a_running_cmd_killed_its_hold_reached_every_target_or_none_and_a_resume_restores_them(flight):
    killed_cmd_reached_all_or_none(flight, CMD_TARGETS)


def test_the_publisher_killed_every_agent_keeps_its_map_and_flight(flight):
    kill = flight.lab.kills.of("publisher")
    heard_throughout(flight, kill)
    for agent_id in (KILLED_AGENT, KILLED_EMULATOR):
        keeps_map_and_flight(flight, agent_id, kill.t_s, kill.t_s + SLOT_S - 1.0, flying=True)
    nothing_stale_alarmed(flight, kill.t_s, kill.t_s + SLOT_S)


def test_a_monitor_killed_and_restarted_picks_the_fleet_up_again(flight):
    monitor_restart_hears_everyone(flight)


def test_an_agent_killed_its_vehicle_fails_safe_and_the_ground_alarms(flight):
    kill = flight.lab.kills.of("agent")
    heard_throughout(flight, kill)
    autopilot = flight.proc(f"autopilot-{KILLED_AGENT}")
    assert "Failsafe: offboard setpoints lost" in autopilot.log_path.read_text(), autopilot.log_tail()
    stale_alarm_names(flight, kill, KILLED_AGENT)


def test_an_autopilot_killed_its_agent_holds_keeps_its_map_and_keeps_reporting(flight):
    agent = flight.proc(f"agent-{KILLED_EMULATOR}")
    assert agent.popen.returncode in (None, 0, -15), agent.log_tail()  # alive until the teardown's SIGTERM
    lost_autopilot_agent_holds_and_reports(flight, KILLED_EMULATOR)


def test_the_lab_port_holder_killed_loses_no_link(flight):
    lab_port_holder_loses_no_link(flight)


def test_the_lab_port_holder_killed_any_silence_is_alarmed(flight):
    lab_port_holder_silence_is_alarmed(flight)


def test_the_whole_flight_one_map_no_stray_failsafe_nobody_leaves_the_duct(flight):
    from fisc_agent.zenoh.telemetry_codec import sha_hex

    ev = flight.ev
    assert set(range(N_AGENTS)) | {KILLED_AGENT, KILLED_EMULATOR} <= set(ev.agents), sorted(ev.agents)
    for agent_id, series in ev.agents.items():
        shas = [s for s in sha_hex(series.records) if s]
        assert set(shas) <= {flight.lab.sha}, f"agent {agent_id} flew another map"
    for agent_id in (KILLED_AGENT, KILLED_EMULATOR):  # the stand-alone ones, before their own kill
        held = ev.agents[agent_id].failsafe_holds_s()
        held = held[held < flight.lab.kills.of("agent" if agent_id == KILLED_AGENT else "autopilot").t_s]
        assert not held.size, f"agent {agent_id} held in a failsafe at {held[:5]} ({flight.lab.kills.kills})"
    holds = emulated_holds(flight.lab.dir / "emu", commanded=CMD_TARGETS if cmd_acted(flight, CMD_TARGETS) else ())
    breaches = ev.duct_breaches(ev.agents, EXCURSION_MAX_S)
    assert not breaches, f"left the duct (start, duration, geofence acting): {breaches}"
    assert flight.emulate_ran_to_the_end, "fisc-sim emulate ended before the last fault was judged"
    assert flight.emulate.popen.returncode == 0, flight.emulate.log_tail()
    if holds:
        pytest.xfail(holds)
