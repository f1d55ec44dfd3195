"""What the ground recorded during a fault-injection flight, read back from a monitor's MCAP log.

``read_evidence`` turns ``fisc-ground monitor --record FILE`` into per-agent telemetry series
(receive time, sequence, state, flags, map digest) and the ``/fisc/alarms`` changes; the checks
below are the outcomes the fault suite states (``tests/faults/test_kills.py`` and
``test_link_loss.py``): who was heard when, who alarmed, who lost a map or left the duct.
Times are UNIX seconds (the monitor's receive clock), the clock the tests log kills in.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fisc_agent.flight.mission_types import HoldCause
from fisc_agent.zenoh import telemetry_codec as tc
from fisc_ground.monitor import foxglove_scene as fs
from fisc_ground.monitor.recording import iter_messages, read_recording

EXCURSION_MAX_S = 15.0
"""Longest spell outside the CVs, the geofence returning the vehicle, that still counts as in the
duct [s]: without any fault, on this loaded 2-core machine, emulated vehicles spend up to ~11 s
outside the CVs in the geofence's RETURN (the strict rule "never outside" fails with no fault)."""

LOAD_CAUSES = ("position stale", "pilot override")
"""Hold causes a starved emulator produces (its position stream pauses; catching up its clock it
trips PX4's offboard-loss failsafe, which the agent obeys hands-off) and no killed Zenoh process can:
the emulated vehicles talk MAVLink to their own emulators, which no fault here touches."""
FLYING = frozenset({"TAKEOFF", "JOIN", "FLOW", "RETURN", "EXIT"})
"""States in which an agent flies its vehicle along its mission."""
FLEET_HOLD_CAUSE = HoldCause.FLEET.value
"""Reason text of a hold a ``fisc-ground cmd hold`` caused."""
STARVED_EMULATOR_S = 0.5
"""An emulator loop gap at least this long [s] (``emulation.json`` real_time) starves the
positions past the agents' stale timeout: only then are such holds put down to the machine."""


@dataclass
class AgentSeries:
    """One agent's telemetry as the monitor received it, in receive order."""

    recv_s: np.ndarray
    """Receive times [UNIX s]."""
    records: np.ndarray
    """``telemetry_codec.DTYPE`` rows."""

    def states(self) -> list[str]:
        """State names, one per message."""
        return tc.state_names(self.records["state"])

    def flagged(self, name: str) -> np.ndarray:
        """Bool per message: flag ``name`` (a key of ``telemetry_codec.FLAG_NAMES``) set."""
        return (self.records["flags"].astype(np.int64) & tc.FLAG_NAMES[name]) != 0

    def failsafe_holds_s(self) -> np.ndarray:
        """Receive times of the messages in a failsafe HOLD (link or position lost, mode taken...;
        the geofence's RETURN, also flagged ``failsafe``, is not one)."""
        held = np.array([s == "HOLD" for s in self.states()], dtype=bool)
        return self.recv_s[held & self.flagged("failsafe")]

    def excursions(self) -> list[tuple[float, float, bool, bool]]:
        """Spells outside the map's CVs (flag ``outside_map``): (first, last receive time, the
        geofence acts all along (state RETURN or HOLD, never FLOW), still outside at the last message).

        The state, not the ``failsafe`` flag, tells the geofence acts: a RETURN resumed after a
        position-stale hold reports no ``failsafe`` (its reason is then "position fix back")."""
        out, start = [], None
        outside = self.flagged("outside_map")
        acting = np.array([s in ("RETURN", "HOLD") for s in self.states()], dtype=bool)
        for k, flag in enumerate(outside.tolist() + [False]):
            if flag and start is None:
                start = k
            elif not flag and start is not None:
                out.append((float(self.recv_s[start]), float(self.recv_s[k - 1]), bool(acting[start:k].all()),
                            k == len(outside)))
                start = None
        return out

    def flying(self, exit_x_m: float | None = None) -> np.ndarray:
        """Bool per message: in a ``FLYING`` state, or (``exit_x_m`` given) in the exit's hold: HOLD,
        no ``failsafe``, at or past ``exit_x_m`` (the map's outlet) in the map frame."""
        states = self.states()
        out = np.array([s in FLYING for s in states], dtype=bool)
        if exit_x_m is not None:
            held = np.array([s == "HOLD" for s in states], dtype=bool) & ~self.flagged("failsafe")
            out |= held & (self.records["position_m"][:, 0] >= exit_x_m)
        return out

    def between(self, t0_s: float, t1_s: float) -> "AgentSeries":
        """The messages received in [t0_s, t1_s]."""
        sel = (self.recv_s >= t0_s) & (self.recv_s <= t1_s)
        return AgentSeries(self.recv_s[sel], self.records[sel])


@dataclass
class Evidence:
    """A monitor recording, decoded."""

    agents: dict[int, AgentSeries]
    """Telemetry by agent id."""
    alarms: list[tuple[float, list[str]]] = field(default_factory=list)
    """``/fisc/alarms`` changes: (time [UNIX s], the alarm lines then in force)."""
    truncated: bool = False
    """The MCAP file ends early (the monitor was killed)."""

    def max_gap_s(self, agent_id: int, t0_s: float, t1_s: float) -> float:
        """Longest silence of ``agent_id`` in [t0_s, t1_s], the window's edges counted (inf: never heard)."""
        series = self.agents.get(agent_id)
        if series is None:
            return float("inf")
        t = series.between(t0_s, t1_s).recv_s
        if t.size == 0:
            return t1_s - t0_s
        return float(np.max(np.diff(np.concatenate([[t0_s], t, [t1_s]]))))

    def gaps(self, ids, t0_s: float, t1_s: float, limit_s: float) -> dict[int, float]:
        """The agents among ``ids`` silent longer than ``limit_s`` somewhere in [t0_s, t1_s], with the gap."""
        out = {i: self.max_gap_s(i, t0_s, t1_s) for i in ids}
        return {i: round(g, 2) for i, g in out.items() if g > limit_s}

    def alarm_lines(self, t0_s: float, t1_s: float) -> list[str]:
        """Every alarm line in force at some change in [t0_s, t1_s]."""
        return [line for t, lines in self.alarms if t0_s <= t <= t1_s for line in lines]

    def duct_breaches(self, ids, max_excursion_s: float) -> dict[int, list]:
        """Agents among ``ids`` that left the duct: an excursion outside the CVs the geofence did
        not act on, or one longer than ``max_excursion_s`` that ended before the recording did."""
        out = {}
        for i in ids:
            bad = [(round(t0, 2), round(t1 - t0, 2), handled) for t0, t1, handled, open_end in
                   self.agents[i].excursions() if not handled or (t1 - t0 > max_excursion_s and not open_end)]
            if bad:
                out[i] = bad
        return out

    def first_heard_s_after(self, agent_id: int, t_s: float) -> float:
        """Receive time of the agent's first message at or after ``t_s`` (inf: none)."""
        series = self.agents.get(agent_id)
        t = series.recv_s[series.recv_s >= t_s] if series is not None else np.zeros(0)
        return float(t[0]) if t.size else float("inf")

    def first_heard_s(self, agent_id: int) -> float:
        """Receive time of the agent's first message (inf: never heard)."""
        series = self.agents.get(agent_id)
        return float(series.recv_s[0]) if series is not None and series.recv_s.size else float("inf")


def read_evidence(path: Path) -> Evidence:
    """Decode a monitor's MCAP flight log: telemetry per agent and the alarm changes."""
    rec = read_recording(path)
    rows: dict[int, list[tuple[float, bytes]]] = {}
    for recv_s, key_id, payload in iter_messages(rec):
        rows.setdefault(int(key_id), []).append((float(recv_s), payload))
    agents = {}
    for agent_id, msgs in rows.items():
        msgs.sort(key=lambda m: m[0])
        records, ok = tc.decode_many(p for _, p in msgs)
        recv = np.array([t for t, _ in msgs], dtype=float)
        agents[agent_id] = AgentSeries(recv[ok], records[ok])
    return Evidence(agents, _alarms(path), rec.truncated)


def _alarms(path: Path) -> list[tuple[float, list[str]]]:
    from mcap.exceptions import McapError
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    topics: dict[int, str] = {}
    out: list[tuple[float, list[str]]] = []
    with open(path, "rb") as fh:
        try:
            for rec in StreamReader(fh, skip_magic=False).records:
                if isinstance(rec, Channel):
                    topics[rec.id] = rec.topic
                elif isinstance(rec, Message) and topics.get(rec.channel_id) == fs.TOPIC_ALARMS:
                    msg = json.loads(rec.data)
                    out.append((float(msg["t_s"]), list(msg["alarms"])))
        except (McapError, EOFError, ValueError):
            pass  # a killed monitor's log ends early: what precedes is the evidence
    return out


def emulated_holds(emu_dir: Path, commanded=()) -> str:
    """Judge the HOLDs of ``fisc-sim emulate``'s agents (``emulation.json`` transitions): "" when
    none; the reason of an inconclusive case (to report as xfail) when every hold has a cause only
    a starved emulator makes and the emulate reports its emulator loop stalled that long; an
    assertion error otherwise (a hold a fault could have caused, or one without a stall).  The
    ids in ``commanded`` were sent a fleet hold: their holds for that cause are the command's."""
    emulation = json.loads((Path(emu_dir) / "emulation.json").read_text())
    holds = {}
    for agent in emulation["agents"]:
        got = [(round(t, 1), why) for t, _, to, why in agent["transitions"] if to == "HOLD"
               and not (agent["agent_id"] in commanded and why.startswith(FLEET_HOLD_CAUSE))]
        if got:
            holds[agent["agent_id"]] = got
    if not holds:
        return ""
    assert all(why.startswith(LOAD_CAUSES) for h in holds.values() for _, why in h), \
        f"emulated agents held for a cause a fault can reach: {holds}"
    gap = max(loop["gap_max_s"] for loop in emulation["real_time"]["emulator_loops"])
    assert gap >= STARVED_EMULATOR_S, f"emulated agents held though the emulator kept real time: {holds}"
    return (f"inconclusive: the machine starved the emulator (loop gap {gap:.2f} s); the emulated agents' "
            f"holds are its doing, not a fault's: {holds}")
