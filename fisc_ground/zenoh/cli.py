"""The Zenoh subcommands of ``fisc-ground``: publish, cmd, status, monitor, replay, router.

``add_parsers(subparsers)`` registers them on the ``fisc-ground`` argparse subparsers; each
sets ``func`` to its ``run_*(args)``.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path
from typing import Any

from fisc_agent.zenoh.fleet_commands import COMMANDS
from fisc_agent.common.names import prefix_arg, swarm_name_arg
from fisc_agent.map.chunks import DEFAULT_CHUNK_BYTES
from fisc_agent.zenoh.keys import DEFAULT_PREFIX

log = logging.getLogger(__name__)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--swarm", required=True, type=swarm_name_arg, metavar="NAME",
                   help="swarm name (key expressions <prefix>/NAME/...): 1-64 of A-Z a-z 0-9 _ - .")
    p.add_argument("--zenoh-config", type=Path, metavar="FILE",
                   help="standard Zenoh JSON5 config (default: the lab default, peer mode on loopback: meet "
                        "at tcp/127.0.0.1:7447, then link directly; port from FISC_ZENOH_PORT)")
    p.add_argument("--prefix", type=prefix_arg, default=DEFAULT_PREFIX,
                   help=f"key expression prefix: chunks of A-Z a-z 0-9 _ - . joined by / (default {DEFAULT_PREFIX})")


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def _agent_ids(text: str) -> tuple[int, ...]:
    """``--agents``: ``1,3,5`` or ``1-4,9`` (a usage error naming the bad part otherwise)."""
    from fisc_ground.zenoh.fleet import parse_agents

    try:
        return parse_agents(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _port(text: str) -> int:
    """A TCP port 0-65535 (0: any free port)."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"port {port} is outside 0-65535")
    return port


def _roster(text: str) -> Any:
    from fisc_ground.monitor.run import AgentRoster

    try:
        return AgentRoster.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def run_publish(args: Any) -> int:
    """Serve MAP until interrupted (or --duration); re-serve the file when it changes to a newer map."""
    from fisc_agent.map.codec import MapError, read_public_key
    from fisc_ground.zenoh.command_relay import CommandRelay
    from fisc_ground.zenoh.config import open_ground_session
    from fisc_ground.zenoh.publish import MapServer

    path = Path(args.map)
    trusted = [read_public_key(p) for p in args.trusted_key or []]
    session = open_ground_session(args.zenoh_config)
    try:
        server = MapServer(session, args.swarm, args.prefix, chunk_bytes=args.chunk_size,
                           announce_period_s=args.announce_period)
        relay = CommandRelay(session, args.swarm, args.prefix, trusted, allow_unsigned=args.allow_unsigned,
                             period_s=args.republish_period)
        cmap = server.serve_file(path)
        _trust_map_signer(relay, cmap)
        log.info("publishing %s (map_version %d) for swarm %s; Ctrl-C to stop", path, cmap.map_version, args.swarm)
        mtime = path.stat().st_mtime_ns
        end = time.monotonic() + args.duration if args.duration else float("inf")
        try:
            while time.monotonic() < end:
                time.sleep(min(1.0, max(0.0, end - time.monotonic())))
                if args.no_watch:
                    continue
                try:
                    now = path.stat().st_mtime_ns
                except OSError:
                    continue
                if now != mtime:
                    mtime = now
                    try:
                        new = server.serve_file(path)
                        _trust_map_signer(relay, new)
                        log.info("map file changed: now serving map_version %d", new.map_version)
                    except MapError as exc:
                        log.error("map file changed but was not served (%s); still serving map_version %d",
                                  exc, server.current.map_version)
        except KeyboardInterrupt:
            pass
        relay.close()
        server.close()
    finally:
        session.close()
    return 0


def _trust_map_signer(relay: Any, cmap: Any) -> None:
    """The key that signed the map served also signs the fleet commands the relay keeps."""
    if cmap.signed and cmap.public_key:
        relay.trust(bytes.fromhex(cmap.public_key))


def add_parsers(subparsers: Any) -> None:
    """Register publish, cmd, status, monitor, replay and router on ``fisc-ground``'s subparsers."""
    from fisc_ground.zenoh.fleet import run_cmd, run_status
    from fisc_ground.monitor.alarms import LOW_BATTERY_PCT
    from fisc_ground.monitor.aggregator import SAMPLE_PERIOD_S
    from fisc_ground.monitor.run import DEFAULT_MAX_AGENTS, run_monitor
    from fisc_ground.monitor.recording import run_replay
    from fisc_ground.zenoh.router import add_parser as add_router_parser

    p = subparsers.add_parser(
        "publish", help="serve a map to a swarm over Zenoh",
        description="Serve MAP on <prefix>/<swarm>/map: pushed to running agents, answered to agents that "
                    "start later, announced periodically. When the file is replaced by a newer map "
                    "(higher map_version) that map is served instead. Also keeps the latest signed go and "
                    "hold/resume/land of the swarm and of each addressed agent (as sent with `fisc-ground "
                    "cmd`) and re-publishes them on <prefix>/<swarm>/cmd/latest, so that an agent that starts "
                    "or reconnects later learns them. Without --zenoh-config the lab default "
                    "applies (meet at tcp/127.0.0.1:7447, then link directly; docs/zenoh.md).")
    p.add_argument("map", metavar="MAP", type=Path, help="the .fiscmap to serve (sign it: agents refuse unsigned maps)")
    _common(p)
    p.add_argument("--chunk-size", type=int, default=DEFAULT_CHUNK_BYTES, metavar="BYTES",
                   help=f"map chunk size (default {DEFAULT_CHUNK_BYTES})")
    p.add_argument("--announce-period", type=float, default=1.0, metavar="S", help="announcement period (default 1 s)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds (default: run)")
    p.add_argument("--no-watch", action="store_true", help="do not re-serve MAP when the file changes")
    p.add_argument("--trusted-key", type=Path, action="append", metavar="PUB",
                   help="re-publish fleet commands signed by this ground key (repeatable; the key that signed "
                        "MAP is always trusted)")
    p.add_argument("--allow-unsigned", action="store_true",
                   help="also re-publish unsigned fleet commands (lab only; agents refuse them unless they "
                        "run with --allow-unsigned)")
    p.add_argument("--republish-period", type=float, default=2.0, metavar="S",
                   help="re-publish the latest fleet commands every S seconds (default 2)")
    p.set_defaults(func=run_publish)

    p = subparsers.add_parser(
        "cmd", help="send a signed fleet command (go, takeover, hold, resume, land, start-at)",
        description="Publish a fleet command on <prefix>/<swarm>/cmd, signed with the ground key, to the whole "
                    "swarm or to the agents named by --agents. "
                    "go: permission to arm, take off and fly one flight. "
                    "takeover: fly a vehicle that is already armed or that someone else took (needs --agents). "
                    "hold: stop and hold position (on the ground: stay there). "
                    "resume: end a fleet hold (an agent that went hands-off needs a command naming it). "
                    "land: land where it is. "
                    "start-at UTC_TIME: a go that takes effect at UTC_TIME. "
                    "Agents refuse replayed, stale, foreign or badly signed commands (the refusal and its "
                    "reason show in `fisc-ground status`) and acknowledge accepted ones in their telemetry; "
                    "`fisc-ground publish` re-publishes the latest go and hold/land to agents that start later.")
    order = ("go", "takeover", "hold", "resume", "land", "start-at")
    assert sorted(order) == sorted(COMMANDS)
    p.add_argument("fleet_command", choices=order, metavar="{" + ",".join(order) + "}")
    p.add_argument("time", nargs="?", metavar="UTC_TIME", help="for start-at: ISO-8601 UTC, e.g. 2026-05-01T12:00:00Z")
    _common(p)
    p.add_argument("--agents", metavar="IDS", default=None, type=_agent_ids,
                   help="only these agent ids, e.g. 3 or 1,3,5 or 1-4,9 (default: the whole swarm; "
                        "takeover needs it)")
    p.add_argument("--key", type=Path, metavar="KEYFILE", help="ground Ed25519 key (from keygen) to sign with")
    p.add_argument("--wait", type=float, default=3.0, metavar="S", help="wait up to S s for subscribers (default 3)")
    p.add_argument("--ack-wait", type=float, default=3.0, metavar="S",
                   help="wait up to S s for acknowledgements in telemetry (default 3; 0: do not wait)")
    p.set_defaults(func=run_cmd)

    p = subparsers.add_parser("status", help="list the swarm's agents from their telemetry",
                              description="Listen to telemetry for a short window and print the fleet: each "
                                          "agent's state, authority, battery, landed state and health, and the "
                                          "alarms (low battery, unhealthy, hands-off, refused commands, stale).")
    _common(p)
    p.add_argument("--json", action="store_true",
                   help='print {"agents": [{"id", "state", "authority", "battery_pct", "landed", "health", '
                        '"map_sha256", "last_seen_s", ...}], "alarms": [...]}')
    p.add_argument("--wait", type=float, default=2.0, metavar="S",
                   help="listening window (default 2 s); with --expect N it ends as soon as N agents are heard")
    p.add_argument("--stale-after", type=float, default=3.0, metavar="S",
                   help="an agent not heard for S seconds is stale (default 3)")
    p.add_argument("--low-battery", type=float, default=LOW_BATTERY_PCT, metavar="PCT",
                   help=f"alarm below PCT %% battery (default {LOW_BATTERY_PCT:g})")
    p.add_argument("--expect", type=_positive_int, metavar="N",
                   help="exit 1 (and say how many answered, and which heard ids went silent) when fewer than N "
                        "agents answer (heard and not stale at the end of the window)")
    p.set_defaults(func=run_status)

    p = subparsers.add_parser(
        "monitor", help="live ground-station dashboard (density, pressure, fleet, alarms)",
        description="Aggregate telemetry into live per-CV swarm density and pressure (XZ heat maps), agent "
                    "counts by state, stale agents, map versions and alarms. --record writes an MCAP flight log "
                    "for `fisc-ground replay` and Foxglove; --foxglove serves the same channels live.")
    _common(p)
    p.add_argument("--map", type=Path, metavar="MAP", help="map for the CVs (default: fetched from the swarm)")
    p.add_argument("--trusted-key", type=Path, action="append", metavar="PUB",
                   help="require the map to be signed by this key (repeatable)")
    p.add_argument("--allow-unsigned", action="store_true",
                   help="accept an unsigned map (lab only; refused by default, like the agents do)")
    p.add_argument("--roster", type=_roster, metavar="IDS",
                   help="agent ids to accept telemetry from, e.g. 1-100,205 (default: any id, up to --max-agents)")
    p.add_argument("--max-agents", type=_positive_int, default=DEFAULT_MAX_AGENTS, metavar="N",
                   help=f"track at most N agent ids; further new ids are counted and shown, not tracked "
                        f"(default {DEFAULT_MAX_AGENTS})")
    p.add_argument("--record", type=Path, metavar="FILE",
                   help="record the telemetry stream and the Foxglove scene to FILE (MCAP) for `fisc-ground replay`")
    p.add_argument("--foxglove", type=_port, nargs="?", const=8765, default=None, metavar="PORT",
                   help="serve the swarm in 3-D on a Foxglove WebSocket on 127.0.0.1 (default port 8765; 0: a free "
                        "port; layout: docs/foxglove_layout.json)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds (default: run)")
    p.add_argument("--sample-period", type=float, default=SAMPLE_PERIOD_S, metavar="S",
                   help=f"fleet sampling period of the field average (default {SAMPLE_PERIOD_S:g} s: the agents' "
                        "telemetry period)")
    p.add_argument("--stale-after", type=float, default=3.0, metavar="S",
                   help="an agent not heard for S seconds is stale (default 3)")
    p.add_argument("--low-battery", type=float, default=LOW_BATTERY_PCT, metavar="PCT",
                   help=f"alarm below PCT %% battery (default {LOW_BATTERY_PCT:g})")
    p.add_argument("--map-timeout", type=float, default=5.0, metavar="S", help="wait for the swarm's map (default 5 s)")
    p.set_defaults(func=run_monitor)

    p = subparsers.add_parser(
        "replay", help="recording -> fields.csv, metrics.json, figures",
        description="Turn an MCAP flight log (`monitor --record`, `fisc-sim run/emulate --mcap`) into the "
                    "outputs of `fisc-sim run`.")
    p.add_argument("file", metavar="FILE", type=Path)
    p.add_argument("-o", "--output", required=True, type=Path, metavar="DIR")
    p.add_argument("--map", type=Path, metavar="MAP", help="map to use (default: the one recorded)")
    p.add_argument("--min-samples", type=int, default=10, help="agent samples a CV needs to be compared (default 10)")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.set_defaults(func=run_replay)

    add_router_parser(subparsers)
