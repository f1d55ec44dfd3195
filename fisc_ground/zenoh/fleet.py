"""Fleet commands and fleet status over Zenoh (``fisc-ground cmd`` and ``fisc-ground status``)."""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any

from fisc_agent.zenoh import telemetry_codec as tc
from fisc_agent.zenoh.fleet_commands import CommandName, FleetCommand, encode_command
from fisc_agent.zenoh.keys import Keys
from fisc_ground.monitor.alarms import LOW_BATTERY_PCT, fleet_alarms
from fisc_ground.monitor.run import DEFAULT_MAX_AGENTS

log = logging.getLogger(__name__)


def parse_utc(text: str) -> float:
    """ISO-8601 time (``2026-05-01T12:00:00Z``; naive times are UTC) -> UNIX seconds."""
    try:
        dt = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError as exc:
        raise ValueError(f"start-at: {text!r} is not an ISO-8601 UTC time such as 2026-05-01T12:00:00Z") from exc
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=timezone.utc)
    return dt.timestamp()


def parse_agents(text: str) -> tuple[int, ...]:
    """``"1,3,5"`` or ``"1-4,9"`` -> ascending distinct agent ids (``ValueError`` naming the bad part)."""
    ids: set[int] = set()
    for part in str(text).split(","):
        lo, sep, hi = part.strip().partition("-")
        try:
            a, b = int(lo), int(hi) if sep else int(lo)
        except ValueError:
            raise ValueError(f"--agents: {part.strip()!r} is not an agent id or a range like 1-4") from None
        if not 0 <= a <= b < 0xFFFFFFFF or b - a > 4096:
            raise ValueError(f"--agents: {part.strip()!r} is not a range of agent ids within 0..4294967294")
        ids.update(range(a, b + 1))
    return tuple(sorted(ids))


def make_command(name: str, swarm: str, targets: tuple[int, ...] = (), start_at_unix_s: float | None = None,
                 now_unix_s: float | None = None) -> FleetCommand:
    """A command stamped now, for the whole swarm (``targets`` empty) or the listed agents; its
    sequence number is the issue time in microseconds (strictly increasing per ground key across
    ground restarts as long as the ground clock is)."""
    now = time.time() if now_unix_s is None else now_unix_s
    return FleetCommand(name=CommandName(name), swarm=swarm, seq=int(now * 1e6), issued_unix_s=now,
                        targets=tuple(sorted(set(int(t) for t in targets))), start_at_unix_s=start_at_unix_s)


class TelemetryListener:
    """Collects the newest telemetry per agent of one swarm (for status and acknowledgements);
    at most ``max_agents`` ids (messages from further new ids are counted in ``over_cap``)."""

    def __init__(self, session: Any, keys: Keys, max_agents: int = DEFAULT_MAX_AGENTS) -> None:
        self.keys = keys
        self.latest: dict[int, tuple[tc.Telemetry, float]] = {}
        self.bad = 0
        self.max_agents = int(max_agents)
        self.over_cap = 0
        self._lock = threading.Lock()
        self.started_s = time.monotonic()
        """When the listener started listening (monotonic) [s]."""
        self._sub = session.declare_subscriber(keys.all_telemetry, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        now = time.time()
        key_id = self.keys.agent_of(str(sample.key_expr))
        try:
            t = tc.decode(sample.payload.to_bytes())
        except tc.TelemetryError as exc:
            self.bad += 1
            log.debug("bad telemetry on %s: %s", sample.key_expr, exc)
            return
        if key_id != t.agent_id:
            self.bad += 1
            log.warning("telemetry on %s claims agent %d: ignored", sample.key_expr, t.agent_id)
            return
        with self._lock:
            if t.agent_id not in self.latest and len(self.latest) >= self.max_agents:
                self.over_cap += 1
                return
            self.latest[t.agent_id] = (t, now)

    def snapshot(self) -> dict[int, tuple[tc.Telemetry, float]]:
        """Latest telemetry and its receive time per agent id (a copy)."""
        with self._lock:
            return dict(self.latest)

    def close(self) -> None:
        """Undeclare the subscriber."""
        self._sub.undeclare()


def status_report(latest: dict[int, tuple[tc.Telemetry, float]], now_unix_s: float, stale_after_s: float = 3.0,
                  low_battery_pct: float = LOW_BATTERY_PCT) -> dict:
    """The ``status --json`` object: ``{"agents": [{"id", "state", "authority", "battery_pct",
    "landed", "health", "map_sha256", "last_seen_s", ...}], "alarms": [...]}`` (``fisc_ground.monitor.alarms``)."""
    agents = []
    for aid in sorted(latest):
        t, seen = latest[aid]
        agents.append({
            "authority": t.authority, "battery_pct": t.battery_pct, "landed": t.landed,
            "health": sorted(t.health), "health_problems": t.health_count, "health_text": t.health_text,
            "commands_refused": t.commands_refused, "command_refusal": t.command_refusal,
            "refused_command": t.refused_command, "stale": now_unix_s - seen > stale_after_s,
            "id": aid, "state": t.state, "map_sha256": t.map_sha256, "last_seen_s": round(now_unix_s - seen, 3),
            "map_version": t.map_version, "cv_index": t.cv_index,
            "position_m": [round(v, 3) for v in t.position_m], "velocity_m_s": [round(v, 3) for v in t.velocity_m_s],
            "flags": sorted(t.flags), "maps_rejected": t.maps_rejected, "reject_reason": t.reject_reason,
            "ack_command": t.ack_command, "ack_seq": t.ack_seq,
        })
    return {"agents": agents, "alarms": status_alarms(latest, now_unix_s, stale_after_s, low_battery_pct)}


def status_alarms(latest: dict[int, tuple[tc.Telemetry, float]], now_unix_s: float, stale_after_s: float,
                  low_battery_pct: float = LOW_BATTERY_PCT) -> list[str]:
    """The monitor's health, authority and silence alarms for the agents ``status`` heard."""
    ids = sorted(latest)
    records, _ = tc.decode_many([tc.encode(latest[i][0]) for i in ids])
    live = [now_unix_s - latest[i][1] <= stale_after_s for i in ids]
    return fleet_alarms(ids, records, live, stale_after_s, low_battery_pct)


def expect_shortfall(report: dict, expected: int) -> str | None:
    """``status --expect N``: None when at least ``expected`` agents answered (heard and not
    stale at the end of the window), else the line that says how many did and which heard ids
    went silent (the ids never heard are not known to ``status``)."""
    answered = [a["id"] for a in report["agents"] if not a["stale"]]
    if len(answered) >= expected:
        return None
    silent = [a["id"] for a in report["agents"] if a["stale"]]
    return (f"only {len(answered)} of {expected} expected agents answered"
            + (f"; heard but silent since: {', '.join(str(i) for i in silent)}" if silent else "")
            + (f"; {expected - len(report['agents'])} never heard" if len(report["agents"]) < expected else ""))


def _wait_connected(session: Any, timeout_s: float) -> bool:
    from fisc_ground.zenoh.config import zenoh_neighbours

    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if zenoh_neighbours(session):  # a lab door only introduces: wait for a process
            return True
        time.sleep(0.05)
    return False


@dataclass(frozen=True)
class CommandResult:
    """Outcome of ``send_command``."""

    command: FleetCommand
    """The command sent."""
    matched: bool
    """True when at least one subscriber matched before sending."""
    acked: tuple[int, ...]
    """Agents whose telemetry acknowledged the command's sequence number."""


def matching(publisher: Any) -> bool:
    """True when subscribers match ``publisher`` (zenoh returns a ``MatchingStatus``)."""
    status = publisher.matching_status
    return bool(getattr(status, "matching", status))


def send_command(session: Any, keys: Keys, cmd: FleetCommand, signing_key: bytes | None,
                 match_timeout_s: float = 3.0, ack_timeout_s: float = 0.0,
                 listener: TelemetryListener | None = None, settle_s: float = 1.0) -> CommandResult:
    """Publish one command on ``<prefix>/<swarm>/cmd``; optionally wait for acknowledgements.

    The targets of a fleet-wide command are the agents the listener has heard; so that a fleet
    is not judged from the first agents heard, the wait for acknowledgements lasts at least
    until the listener has listened for ``settle_s`` (bounded by ``ack_timeout_s``).
    """
    pub = session.declare_publisher(keys.cmd)
    try:
        end = time.monotonic() + match_timeout_s
        while not matching(pub) and time.monotonic() < end:
            time.sleep(0.05)
        matched = matching(pub)
        pub.put(encode_command(cmd, signing_key))
        acked: set[int] = set()
        if listener is not None and ack_timeout_s > 0:
            end = time.monotonic() + ack_timeout_s
            while time.monotonic() < end:
                acked = {aid for aid, (t, _) in listener.snapshot().items() if t.ack_seq == cmd.seq}
                targets = set(cmd.targets) or set(listener.snapshot())
                if targets and targets <= acked and time.monotonic() - listener.started_s >= settle_s:
                    break
                time.sleep(0.05)
        return CommandResult(cmd, matched, tuple(sorted(acked)))
    finally:
        pub.undeclare()


# --------------------------------------------------------------------------------------------
# CLI bodies

def run_cmd(args: Any) -> int:
    """``fisc-ground cmd go|takeover|hold|resume|land|start-at [UTC_TIME] --swarm NAME [--agents IDS] [--key KEYFILE]``."""
    from fisc_ground.maps.write import read_signing_key
    from fisc_agent.zenoh.session import LabRole
    from fisc_ground.zenoh.config import open_ground_session

    start_at = None
    if args.fleet_command == "start-at":
        if not args.time:
            raise ValueError("cmd start-at needs a UTC time, e.g. 2026-05-01T12:00:00Z")
        start_at = parse_utc(args.time)
    elif args.time:
        raise ValueError(f"cmd {args.fleet_command} takes no time argument")
    targets = tuple(args.agents or ())
    if args.fleet_command == "takeover" and not targets:
        raise ValueError("cmd takeover needs --agents: a takeover is never swarm-wide")
    key = read_signing_key(args.key) if args.key else None
    if key is None:
        log.warning("sending an UNSIGNED command: agents refuse it unless started with --allow-unsigned")
    keys = Keys(args.prefix, args.swarm)
    session = open_ground_session(args.zenoh_config, LabRole.VISITOR)
    try:
        _wait_connected(session, args.wait)
        listener = TelemetryListener(session, keys)
        cmd = make_command(args.fleet_command, args.swarm, targets, start_at)
        res = send_command(session, keys, cmd, key, match_timeout_s=args.wait, ack_timeout_s=args.ack_wait,
                           listener=listener)
        listener.close()
    finally:
        session.close()
    print(json.dumps({"command": cmd.name.value, "seq": cmd.seq, "swarm": cmd.swarm,
                      "target": list(cmd.targets) or "all",
                      "subscribers_matched": res.matched, "acked": list(res.acked)}))
    return 0 if res.matched else 1  # no agent subscribed: a runtime failure (fisc_agent.common.cli_common)


def listen(listener: TelemetryListener, window_s: float, expect: int | None = None, stale_after_s: float = 3.0,
           poll_s: float = 0.02) -> dict[int, tuple[tc.Telemetry, float]]:
    """Listen for ``window_s`` seconds, or only until ``expect`` agents answer (heard within
    the last ``stale_after_s``); the snapshot."""
    end = time.monotonic() + window_s
    while True:
        latest = listener.snapshot()
        left_s = end - time.monotonic()
        if left_s <= 0.0:
            return latest
        if expect is not None:
            now_s = time.time()
            if sum(now_s - seen <= stale_after_s for _, seen in latest.values()) >= expect:
                return latest
        time.sleep(min(poll_s, left_s))


def run_status(args: Any) -> int:
    """``fisc-ground status --swarm NAME [--zenoh-config FILE] [--json] [--wait S] [--expect N]``
    (exit 1 when fewer than N agents answered)."""
    from fisc_agent.zenoh.session import LabRole
    from fisc_ground.zenoh.config import open_ground_session

    keys = Keys(args.prefix, args.swarm)
    expect = getattr(args, "expect", None)
    session = open_ground_session(args.zenoh_config, LabRole.VISITOR)
    try:
        listener = TelemetryListener(session, keys)
        latest = listen(listener, args.wait, expect, args.stale_after)
        listener.close()
    finally:
        session.close()
    report = status_report(latest, time.time(), args.stale_after, args.low_battery)
    shortfall = None if expect is None else expect_shortfall(report, expect)
    if shortfall is not None:
        log.error("status --expect %d: %s", expect, shortfall)
    code = 0 if shortfall is None else 1
    if args.json:  # strict JSON: a non-finite position or velocity is null, never NaN/Infinity
        from fisc_ground.fields.field_report import json_safe

        print(json.dumps(json_safe(report), allow_nan=False))
        return code
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"swarm {args.swarm}: {len(report['agents'])} agents")
    for col in ("id", "state", "authority", "battery", "landed", "health", "map", "cv", "position [m]", "flags",
                "refused maps", "refused cmds", "last seen [s]"):
        table.add_column(col)
    for a in report["agents"]:
        table.add_row(str(a["id"]), a["state"], a["authority"],
                      "-" if a["battery_pct"] is None else f"{a['battery_pct']:.0f} %", a["landed"],
                      (a["health_text"] or ",".join(a["health"])) if a["health_problems"] else "ok",
                      a["map_sha256"][:12] or "-", str(a["cv_index"]),
                      " ".join(f"{v:.1f}" for v in a["position_m"]), ",".join(a["flags"]),
                      f"{a['maps_rejected']} ({a['reject_reason']})" if a["maps_rejected"] else "0",
                      f"{a['commands_refused']} ({a['command_refusal']} {a['refused_command']})"
                      if a["commands_refused"] else "0",
                      f"{a['last_seen_s']:.1f}", style="red" if a["stale"] else "")
    console = Console()
    console.print(table)
    console.print("alarms: " + ("; ".join(report["alarms"]) if report["alarms"] else "none"),
                  style="bold red" if report["alarms"] else "green")
    if shortfall is not None:
        console.print(f"expected {expect}: {shortfall}", style="bold red")
    return code
