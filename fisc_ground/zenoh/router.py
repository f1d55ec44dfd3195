"""``fisc-ground router``: a Zenoh router in Python, for field set-ups without ``zenohd``.

Agents and ground tools in client (or peer) mode connect to it; it routes map chunks,
commands and telemetry between them.  Without ``--config`` it listens on the lab endpoint
(``tcp/127.0.0.1:7447``, ``FISC_ZENOH_PORT``) or on the ``--listen`` endpoints given; lab-default
FISC processes started afterwards find the port taken and connect to the router.  With
``--config FILE`` (a standard Zenoh JSON5 file: listen endpoints, TLS, access control) the file's
``mode`` must be ``router`` or absent.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

from fisc_agent.zenoh.session import LabDiscovery, ZenohSessionError, config_from_json, load_config

log = logging.getLogger(__name__)


def router_config(path: str | Path | None = None, listen: list[str] | None = None,
                  lab: LabDiscovery | None = None) -> Any:
    """The router's ``zenoh.Config``: from ``path`` (mode ``router`` or absent, then set), or
    router mode listening on ``listen`` (default: the lab endpoint), multicast scouting off."""
    if path is not None:
        if listen:
            raise ValueError("give --listen or --config, not both (put the endpoints in the config file)")
        cfg = load_config(path)
        mode = cfg.get_json("mode")
        if mode not in ("null", '"router"'):
            raise ValueError(f"{path}: mode is {mode}; fisc-ground router needs mode \"router\" (or no mode)")
        cfg.insert_json5("mode", '"router"')
        return cfg
    lab = LabDiscovery.from_env() if lab is None else lab
    return config_from_json({"mode": "router", "listen": {"endpoints": list(listen or [lab.endpoint])},
                             "scouting": {"multicast": {"enabled": False}}})


def open_router(config: Any, where: str) -> Any:
    """Open the router session; ``ZenohSessionError`` names the config and Zenoh's reason."""
    import zenoh

    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise ZenohSessionError(f"cannot start a Zenoh router with {where}: {exc}") from exc


def run_router(args: Any) -> int:
    """``fisc-ground router [--config FILE | --listen ENDPOINT ...] [--duration S]``."""
    cfg = router_config(args.config, args.listen)
    where = str(args.config) if args.config else "listen " + ", ".join(args.listen or [LabDiscovery.from_env().endpoint])
    session = open_router(cfg, where)
    try:
        log.info("Zenoh router %s up (%s); Ctrl-C to stop", session.info.zid(), where)
        end = time.monotonic() + args.duration if args.duration else float("inf")
        try:
            while time.monotonic() < end:
                time.sleep(min(1.0, max(0.0, end - time.monotonic())))
        except KeyboardInterrupt:
            pass
    finally:
        session.close()
    return 0


def add_parser(subparsers: Any) -> None:
    """Register ``router`` on ``fisc-ground``'s subparsers."""
    p = subparsers.add_parser(
        "router", help="run a Zenoh router (field set-ups without zenohd)",
        description="A Zenoh router in this process. Without --config it listens on the lab endpoint "
                    "tcp/127.0.0.1:7447 (port from FISC_ZENOH_PORT) or on --listen; agents and ground tools "
                    "connect to it. --config takes a standard Zenoh JSON5 file (mode router or absent; listen "
                    "endpoints, TLS, access control: docs/zenoh.md).")
    p.add_argument("--config", type=Path, metavar="FILE", help="standard Zenoh JSON5 config of the router")
    p.add_argument("--listen", action="append", metavar="ENDPOINT",
                   help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable; default the lab endpoint)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds (default: run)")
    p.set_defaults(func=run_router)
