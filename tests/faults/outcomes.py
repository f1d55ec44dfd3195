"""The stated outcomes both fault flights check (emulated: ``test_kills.py``; three real PX4:
``test_px4_kills.py``), with the timings they share, and the ``cmd`` fault both inject
(``kill_a_running_cmd``).  A flight is any object with ``lab`` (a ``FaultLab``), ``ev`` (the
recorder's ``Evidence``), ``restarted`` (the monitor started after the monitor's kill),
``newcomer`` (the ``status`` started after the lab port's holder died), ``cmd_started_s``,
``resume`` and ``resume_sent_s`` (``kill_a_running_cmd``'s result) and ``survivors(t_s)`` (the
agent ids that must be heard at ``t_s``)."""

from __future__ import annotations

import json
import subprocess
import time
from typing import Any

import numpy as np

from .evidence import read_evidence
from .lab import FaultLab, Kill, ground, listening
from ..e2e.conftest import poll

SLOT_S = 6.0
"""Time between two faults [s]."""
HUB_OBSERVE_S = 15.0
"""Observation window after the last fault (the lab port's holder) [s]: the issue saw the lab
fall apart ~10 s after its hub left."""
NEWCOMER_AFTER_S = 8.0
"""A ``status --wait 5`` started this long after the holder's kill must list every flying agent
(the issue's "lists every flying agent within 5 s of asking"; its members' reconnection back-off
has grown by then) [s]."""
STALE_AFTER_S = 3.0
"""The monitors' ``--stale-after``: a survivor silent longer than this is a link lost (the
ground itself would call it stale) [s]."""
RE_HEARD_WITHIN_S = 5.0
"""A monitor started again hears every survivor within this long of its first message [s]."""
NOBODY = 999
"""An id no agent has: a ``cmd`` addressed to it too waits its whole ``--ack-wait``, so it is still
running when it is killed."""
HOLD_WITHIN_S = 3.0
"""A delivered hold is flown (telemetry HOLD) within this long of its acknowledgement [s]."""
RESUMED_WITHIN_S = 5.0
"""After a completed ``cmd resume`` every held target flies again within this long [s]."""
LOST_AUTOPILOT_HOLD_S = 5.0
"""An agent whose autopilot died holds (failsafe, no ``mavlink_ok``) from this long after the kill
on (its link timeout, then the hold) [s]."""


def heard_throughout(flight: Any, kill: Kill, after_s: float = SLOT_S - 1.0, limit_s: float = STALE_AFTER_S,
                     ignore=()) -> None:
    """Every survivor (but ``ignore``) heard from 1 s before the kill to ``after_s`` after it, no
    silence longer than ``limit_s``."""
    ids = [i for i in flight.survivors(kill.t_s + after_s) if i not in ignore]
    gaps = flight.ev.gaps(ids, kill.t_s - 1.0, kill.t_s + after_s, limit_s)
    assert not gaps, f"after the {kill.case} kill ({kill}), silent > {limit_s} s: {gaps}"


def monitor_restart_hears_everyone(flight: Any) -> None:
    """The killed monitor's log is readable up to its kill; the monitor started after it exits
    cleanly and hears every survivor within ``RE_HEARD_WITHIN_S`` of its first message."""
    kill = flight.lab.kills.of("monitor")
    heard_throughout(flight, kill)
    killed = read_evidence(flight.lab.dir / "monitor.mcap")  # readable up to the kill
    assert killed.agents and max(s.recv_s[-1] for s in killed.agents.values()) <= kill.t_s + 0.5
    assert flight.restarted.popen.returncode == 0, flight.restarted.log_tail()
    again = read_evidence(flight.lab.dir / "restarted.mcap")
    start = min(again.first_heard_s(i) for i in again.agents)
    due = flight.survivors(start + RE_HEARD_WITHIN_S)
    heard = {i: round(again.first_heard_s(i) - start, 2) for i in due}
    print(f"restarted monitor: first message {start - kill.t_s:.2f} s after the kill; each survivor after it {heard}")
    late = {i: t for i, t in heard.items() if t > RE_HEARD_WITHIN_S}
    assert not late, f"the restarted monitor took > {RE_HEARD_WITHIN_S} s (or never) to hear: {late}"


def lab_port_holder_loses_no_link(flight: Any) -> None:
    """The holder of the lab port killed: every survivor heard for ``HUB_OBSERVE_S``, and the
    ``status`` started ``NEWCOMER_AFTER_S`` later lists every one of them."""
    kill = flight.lab.kills.of("first")
    heard_throughout(flight, kill, after_s=HUB_OBSERVE_S)
    assert flight.newcomer.returncode == 0, flight.newcomer.stderr[-2000:]
    listed = {a["id"] for a in json.loads(flight.newcomer.stdout)["agents"] if a["last_seen_s"] < 2.5}
    missing = sorted(set(flight.survivors(kill.t_s)) - listed)
    assert not missing, f"a status started {NEWCOMER_AFTER_S} s after the holder's kill misses {missing}"


def lab_port_holder_silence_is_alarmed(flight: Any) -> None:
    """Whatever happens after the holder's kill, a silence the ground suffers is alarmed."""
    kill = flight.lab.kills.of("first")
    gaps = flight.ev.gaps(flight.survivors(kill.t_s), kill.t_s, kill.t_s + HUB_OBSERVE_S, STALE_AFTER_S)
    if gaps:  # the ground lost some agents: it must say so
        lines = flight.ev.alarm_lines(kill.t_s, kill.t_s + HUB_OBSERVE_S)
        assert any(line.startswith(("stale", "every agent stale")) for line in lines), (gaps, flight.ev.alarms)


def keeps_map_and_flight(flight: Any, agent_id: int, t0_s: float, t1_s: float, flying: bool = False,
                         exit_x_m: float | None = None) -> None:
    """Agent ``agent_id`` heard in [t0_s, t1_s] on the signed map, progressing, never in a failsafe
    hold (and, with ``flying``, always flying: ``AgentSeries.flying(exit_x_m)``)."""
    from fisc_agent.zenoh.telemetry_codec import sha_hex

    series = flight.ev.agents[agent_id].between(t0_s, t1_s)
    assert series.recv_s.size, f"agent {agent_id} not heard in [{t0_s}, {t1_s}]"
    assert set(sha_hex(series.records)) == {flight.lab.sha}, f"agent {agent_id} lost or changed its map"
    if flying:
        assert series.flying(exit_x_m).all(), f"agent {agent_id} stopped flying: {sorted(set(series.states()))}"
    assert not series.failsafe_holds_s().size, f"agent {agent_id} failed safe"
    assert series.records["seq"][-1] > series.records["seq"][0], f"agent {agent_id} stopped progressing"


def nothing_stale_alarmed(flight: Any, t0_s: float, t1_s: float) -> None:
    """No ``stale`` or ``every agent stale`` alarm in [t0_s, t1_s]."""
    assert not any(line.startswith(("stale", "every agent stale"))
                   for line in flight.ev.alarm_lines(t0_s, t1_s)), flight.ev.alarms


def stale_alarm_names(flight: Any, kill: Kill, agent_id: int, within_s: float = STALE_AFTER_S + 4.0) -> None:
    """The ground alarms ``stale`` naming ``agent_id`` within ``within_s`` of the kill (printed: how soon)."""
    lines = flight.ev.alarm_lines(kill.t_s, kill.t_s + within_s)
    stale = [t for t, got in flight.ev.alarms if kill.t_s <= t <= kill.t_s + within_s
             and any(line.startswith("stale") and str(agent_id) in line for line in got)]
    print(f"agent {agent_id} killed: stale alarm {stale[0] - kill.t_s if stale else None} s after")
    assert any(line.startswith("stale") and str(agent_id) in line for line in lines), flight.ev.alarms


def kill_a_running_cmd(lab: FaultLab, targets) -> tuple[float, subprocess.CompletedProcess, tuple[float, float]]:
    """The ``cmd`` fault: a signed ``cmd hold --agents TARGETS,NOBODY`` started and killed at a
    random moment while it starts, waits for subscribers or waits for NOBODY's acknowledgement;
    ``HOLD_WITHIN_S`` later a ``cmd resume --agents TARGETS`` run to completion, then
    ``RESUMED_WITHIN_S`` for it to be flown.  Returns (the hold's start [UNIX s], the resume,
    (the resume's start, its end) [UNIX s]): a flight's ``cmd_started_s``, ``resume`` and
    ``resume_sent_s``."""
    agents = ",".join(str(i) for i in targets)
    cmd_started_s = time.time()
    cmd = lab.start("cmd", ground("cmd", "hold", "--swarm", lab.swarm, "--key", lab.key, "--ack-wait", "30",
                                  "--agents", f"{agents},{NOBODY}"))
    lab.kills.kill_at("cmd", cmd, 0.5, 4.0)
    time.sleep(HOLD_WITHIN_S)  # a delivered hold is flown by now
    resume_sent_s = time.time()
    resume = lab.run(ground("cmd", "resume", "--swarm", lab.swarm, "--key", lab.key, "--ack-wait", "8",
                            "--agents", agents))
    resume_sent = (resume_sent_s, time.time())
    print(f"fault: resume after the killed cmd ({resume_sent[1] - resume_sent_s:.2f} s): {resume.stdout.strip()}")
    time.sleep(RESUMED_WITHIN_S)
    return cmd_started_s, resume, resume_sent


def hold_acks(flight: Any, agent_id: int) -> list[int]:
    """Sequence numbers of the holds ``agent_id`` acknowledged from the killed ``cmd``'s start until
    the resume has been flown (a hold's acknowledgement shows until the resume replaces it)."""
    from fisc_agent.zenoh.telemetry_codec import ACK_COMMANDS

    r = flight.ev.agents[agent_id].between(flight.cmd_started_s, flight.resume_sent_s[1] + RESUMED_WITHIN_S).records
    return sorted(set(r["ack_seq"][r["ack_command"] == ACK_COMMANDS.index("hold")].tolist()))


def cmd_acted(flight: Any, targets) -> bool:
    """The killed ``cmd``'s hold reached its targets (one acknowledged it)."""
    return any(hold_acks(flight, i) for i in targets if i in flight.ev.agents)


def killed_cmd_reached_all_or_none(flight: Any, targets, exit_x_m: float | None = None) -> None:
    """A ``cmd hold --agents TARGETS,NOBODY`` killed while it ran (``flight.cmd_started_s``), then a
    completed ``cmd resume --agents TARGETS`` (``flight.resume``, sent in ``flight.resume_sent_s``):
    every survivor heard throughout; the hold acknowledged by every target or by none, once, and
    refused by nobody; acknowledged, it is flown as a HOLD (not a failsafe) within
    ``HOLD_WITHIN_S``; not, the targets fly on; the resume is acknowledged by every target and
    each flies again within ``RESUMED_WITHIN_S`` of its end (flying: ``AgentSeries.flying(exit_x_m)``)."""
    from fisc_agent.zenoh.telemetry_codec import ACK_COMMANDS

    ev, kill = flight.ev, flight.lab.kills.of("cmd")
    t_resume, t_resumed = flight.resume_sent_s
    heard_throughout(flight, kill, after_s=t_resumed + RESUMED_WITHIN_S - kill.t_s)
    hold = ACK_COMMANDS.index("hold")
    acks, refused = {}, {}
    for i in flight.survivors(kill.t_s):
        before = ev.agents[i].between(0.0, flight.cmd_started_s).records
        during = ev.agents[i].between(flight.cmd_started_s, t_resumed + RESUMED_WITHIN_S).records
        acks[i] = hold_acks(flight, i)
        refused[i] = int(during["cmds_refused"].max(initial=0)) - int(before["cmds_refused"].max(initial=0))
    acted = {i for i, seqs in acks.items() if seqs}
    print(f"cmd killed {kill.t_s - flight.cmd_started_s:.2f} s after its start: hold acknowledged by {sorted(acted)}")
    assert acted in (set(), set(targets)), f"the killed cmd's hold reached only some: {acks}"
    assert len({s for seqs in acks.values() for s in seqs}) <= 1, f"more than one hold acknowledged: {acks}"
    assert not any(refused.values()), f"agents refused a command (a half command?): {refused}"
    for i in targets:
        s = ev.agents[i].between(flight.cmd_started_s, t_resume)
        if acted:  # the hold was flown: HOLD, not a failsafe, soon after its acknowledgement
            t_ack = s.recv_s[s.records["ack_command"] == hold][0]
            held = [t for t, st in zip(s.recv_s, s.states()) if st == "HOLD" and t <= t_ack + HOLD_WITHIN_S]
            assert held, f"agent {i} acknowledged the hold but did not hold: {s.states()}"
            assert not s.failsafe_holds_s().size, f"agent {i} held in a failsafe"
        else:  # nothing arrived: it flew on
            assert s.flying(exit_x_m).all(), f"agent {i} stopped flying: {sorted(set(s.states()))}"
    assert flight.resume.returncode == 0, flight.resume.stderr[-2000:]
    sent = json.loads(flight.resume.stdout.strip().splitlines()[-1])
    assert sorted(sent["acked"]) == sorted(targets), sent
    again = {}
    for i in targets:
        after = ev.agents[i].between(t_resume, float("inf"))
        again[i] = next((t - t_resume for t, f in zip(after.recv_s, after.flying(exit_x_m)) if f), float("inf"))
    print(f"cmd resume: ended {t_resumed - t_resume:.2f} s after its start; " + (
          f"the targets fly again {', '.join(f'{i}: {v:.2f}' for i, v in again.items())} s after its start"
          if acted else "nothing to resume"))
    for i in targets:
        t_check = t_resumed + RESUMED_WITHIN_S
        after = ev.agents[i].between(t_check, t_check + 1.0)
        assert after.recv_s.size and after.flying(exit_x_m).all(), \
            f"agent {i} not flying {RESUMED_WITHIN_S} s after the resume: {after.states()}"
        assert (ev.agents[i].records["ack_seq"] == sent["seq"]).any(), f"agent {i}: no resume acknowledged"


def lost_autopilot_agent_holds_and_reports(flight: Any, agent_id: int) -> None:
    """The autopilot of ``agent_id`` killed (``kills.of("autopilot")``): every survivor, the agent
    included, heard throughout; from ``LOST_AUTOPILOT_HOLD_S`` after the kill to the next slot the
    agent holds in a failsafe without ``mavlink_ok``, on its signed map."""
    from fisc_agent.zenoh.telemetry_codec import sha_hex

    kill = flight.lab.kills.of("autopilot")
    heard_throughout(flight, kill)
    after = flight.ev.agents[agent_id].between(kill.t_s + LOST_AUTOPILOT_HOLD_S, kill.t_s + SLOT_S)
    assert after.recv_s.size, f"agent {agent_id} silent after its autopilot died"
    assert set(after.states()) == {"HOLD"} and after.flagged("failsafe").all(), after.states()
    assert not after.flagged("mavlink_ok").any()
    assert set(sha_hex(after.records)) == {flight.lab.sha}


# ---- the Zenoh link between the ground and the fleet lost for 10 s (a router killed) --------------
# An outage is a dict: "ev" (the ground's Evidence), "kill" (the router's Kill), "restarted_s"
# (when the restarted router accepted connections again [UNIX s]) and "lab".
OUTAGE_S = 10.0
"""Time between the router's kill and its restart [s]."""
REHEAR_S = 5.0
"""Every agent heard again within this long after the router's restart [s]."""


def cut_the_link(lab: FaultLab, router: Any, port: int, router_cfg) -> tuple[Kill, float]:
    """The link fault: kill -9 the router (``lab.start``'d, listening on ``port``) at a random
    moment within 2 s, start it again ``OUTAGE_S`` after, then observe ``REHEAR_S`` + 4 s.
    Returns (the kill, when the restarted router accepted connections [UNIX s])."""
    kill = lab.kills.kill_at("router", router, 0.0, 2.0)
    time.sleep(max(0.0, kill.t_s + OUTAGE_S - time.time()))
    lab.start("router-restarted", ground("router", "--config", router_cfg))
    assert poll(lambda: listening(port), 30, period_s=0.05), lab.procs.report()
    restarted_s = time.time()  # the link is back when the router accepts connections again
    print(f"fault: router restarted, listening {restarted_s - kill.t_s:.2f} s after its kill")
    time.sleep(REHEAR_S + 4.0)
    return kill, restarted_s


def ground_hears_nobody_and_alarms(outage: dict, ids) -> None:
    """While the router is down the ground hears none of ``ids`` (the link is really cut) and
    raises ``every agent stale`` within stale-after + 2 s."""
    ev, kill, back = outage["ev"], outage["kill"], outage["restarted_s"]
    assert set(ids) <= set(ev.agents), sorted(ev.agents)
    during = {i: int(s.between(kill.t_s + 0.5, back).recv_s.size) for i, s in ev.agents.items()}
    assert not any(during.values()), f"telemetry crossed a dead router: {during}"
    lines = ev.alarm_lines(kill.t_s, kill.t_s + STALE_AFTER_S + 2.0)
    assert any(line.startswith("every agent stale") for line in lines), ev.alarms


def ground_hears_everyone_again(outage: dict, ids) -> None:
    """Within ``REHEAR_S`` of the restarted router accepting connections the ground hears each of
    ``ids`` again, and the alarms it then has name no stale agent."""
    ev, back = outage["ev"], outage["restarted_s"]
    again = ground_heard_again_s(outage, ids)
    print(f"router restarted: each agent heard again after {again} s")
    late = {i: t for i, t in again.items() if t > REHEAR_S}
    assert not late, f"not heard within {REHEAR_S} s of the router's restart (inf: never): {late}"
    settled = [lines for t, lines in ev.alarms if back < t <= back + REHEAR_S + 4.0]
    assert settled and not any(line.startswith(("every agent stale", "stale")) for line in settled[-1]), ev.alarms


def ground_heard_again_s(outage: dict, ids) -> dict[int, float]:
    """How long after the router's restart each of ``ids`` was first heard again [s]."""
    back = outage["restarted_s"]
    return {i: round(outage["ev"].first_heard_s_after(i, back) - back, 2) for i in ids}


def fleet_kept_map_and_counted(outage: dict, ids) -> None:
    """Each of ``ids`` flew the signed map on both sides of the outage and kept counting its
    telemetry through it: its sequence after the outage is past the one before by at least 3 Hz x
    the outage (it published into the void at its rate)."""
    from fisc_agent.zenoh.telemetry_codec import sha_hex

    ev, kill, back, lab = outage["ev"], outage["kill"], outage["restarted_s"], outage["lab"]
    for i in ids:
        s = ev.agents[i]
        assert set(x for x in sha_hex(s.records) if x) == {lab.sha}, f"agent {i} flew another map"
        before, after = s.records["seq"][s.recv_s < kill.t_s], s.records["seq"][s.recv_s > back]
        assert before.size and after.size, f"agent {i} not heard on both sides of the outage"
        assert int(np.int64(after[0]) - np.int64(before[-1])) >= 3 * (back - kill.t_s), \
            f"agent {i} stopped counting during the outage ({before[-1]} -> {after[0]})"
