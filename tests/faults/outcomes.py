"""The stated outcomes both fault flights check (emulated: ``test_kills.py``; three real PX4:
``test_px4_kills.py``), with the timings they share.  A flight is any object with ``lab`` (a
``FaultLab``), ``ev`` (the recorder's ``Evidence``), ``restarted`` (the monitor started after the
monitor's kill), ``newcomer`` (the ``status`` started after the lab port's holder died) and
``survivors(t_s)`` (the agent ids that must be heard at ``t_s``)."""

from __future__ import annotations

import json
from typing import Any

from .evidence import read_evidence
from .lab import Kill

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


def keeps_map_and_flight(flight: Any, agent_id: int, t0_s: float, t1_s: float, flying_states=None) -> None:
    """Agent ``agent_id`` heard in [t0_s, t1_s] on the signed map, progressing, never in a failsafe
    hold (and only in ``flying_states`` when given)."""
    from fisc_agent.zenoh.telemetry_codec import sha_hex

    series = flight.ev.agents[agent_id].between(t0_s, t1_s)
    assert series.recv_s.size, f"agent {agent_id} not heard in [{t0_s}, {t1_s}]"
    assert set(sha_hex(series.records)) == {flight.lab.sha}, f"agent {agent_id} lost or changed its map"
    if flying_states is not None:
        assert set(series.states()) <= flying_states, \
            f"agent {agent_id} stopped flying: {sorted(set(series.states()))}"
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
