"""Zenoh sessions: standard JSON5 config files, or the zero-config lab default.

**Lab default (no config file).**  Every FISC process (agent, ``fisc-ground publish``,
``monitor``, ``status``, ``cmd``, ``router`` aside, ``fisc-sim emulate``'s workers) opens its
session with ``open_lab_session``: peer mode, multicast scouting off, and

- it *listens* on the lab endpoint ``tcp/127.0.0.1:7447`` if that port is free (it is the hub);
- otherwise it listens on an ephemeral loopback port and *connects* to the lab endpoint.

The bind itself is the test (no probe-then-bind race): Zenoh refuses a second listener on the
port, and the process becomes a member.  Gossip scouting stays on, so members that meet at the
hub also connect directly; a member keeps retrying its connect endpoint, so when the hub exits
and another FISC process takes the port, the members find it again.  Any two FISC processes
therefore meet in any start order.  The port comes from ``LabDiscovery`` (environment
variable ``FISC_ZENOH_PORT``; tests use a free ephemeral port and the same logic).

**Field.**  Pass a standard Zenoh JSON5 file (router/client mode, TLS, access control;
``docs/zenoh.md``); ``fisc-ground router`` runs a Zenoh router without ``zenohd``.

This module is onboard code: the standard library and zenoh only.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any, Mapping

log = logging.getLogger(__name__)

DEFAULT_PORT = 7447
"""Zenoh's registered port: the lab hub's TCP port unless ``FISC_ZENOH_PORT`` says otherwise."""
PORT_ENV = "FISC_ZENOH_PORT"
"""Environment variable naming the lab port (inherited by child processes such as emulate's workers)."""


class ZenohSessionError(ValueError):
    """A Zenoh session could not be opened (endpoint busy or unreachable, bad TLS files...)."""


@dataclass(frozen=True)
class LabDiscovery:
    """Where the FISC processes of one machine meet when no Zenoh config file is given."""

    port: int = DEFAULT_PORT
    """TCP port of the lab hub (the first FISC process to start listens on it)."""
    host: str = "127.0.0.1"
    """Address of the hub endpoint (loopback: nothing leaves the machine)."""

    def __post_init__(self) -> None:
        if not isinstance(self.port, int) or not 1 <= self.port <= 65535:
            raise ValueError(f"lab Zenoh port {self.port!r} is not a TCP port (1-65535)")

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> "LabDiscovery":
        """The lab set-up: port from ``FISC_ZENOH_PORT`` if set, else 7447."""
        env = os.environ if environ is None else environ
        text = env.get(PORT_ENV, "").strip()
        if not text:
            return cls()
        try:
            port = int(text)
        except ValueError:
            raise ValueError(f"{PORT_ENV}={text!r} is not a TCP port number (1-65535)") from None
        try:
            return cls(port=port)
        except ValueError as exc:
            raise ValueError(f"{PORT_ENV}: {exc}") from None

    @property
    def endpoint(self) -> str:
        """The hub's Zenoh locator, e.g. ``tcp/127.0.0.1:7447``."""
        return f"tcp/{self.host}:{self.port}"


class LabRole(str, Enum):
    """What a process does in the lab default."""

    HUB = "hub"
    """Listens on the lab endpoint (the port was free)."""
    MEMBER = "member"
    """Listens on an ephemeral port and connects to the lab endpoint (the port was taken)."""


def peer_config_json(listen: list[str], connect: list[str]) -> dict:
    """Peer mode, multicast scouting off, the given endpoints (gossip scouting stays on)."""
    return {
        "mode": "peer",
        "listen": {"endpoints": list(listen)},
        "connect": {"endpoints": list(connect)},
        "scouting": {"multicast": {"enabled": False}},
    }


def lab_config_json(role: LabRole, lab: LabDiscovery) -> dict:
    """THE lab-default config of every FISC process, as JSON: the hub listens on the lab
    endpoint; a member listens on an ephemeral port of the same host and connects to it."""
    if role == LabRole.HUB:
        return peer_config_json([lab.endpoint], [])
    return peer_config_json([f"tcp/{lab.host}:0"], [lab.endpoint])


def config_from_json(cfg: Mapping[str, Any]) -> Any:
    """A ``zenoh.Config`` with each top-level entry of ``cfg`` inserted."""
    import zenoh

    config = zenoh.Config()
    for key, value in cfg.items():
        config.insert_json5(key, json.dumps(value))
    return config


def load_config(path: str | Path) -> Any:
    """A ``zenoh.Config`` from a standard Zenoh JSON5 file (errors name the file)."""
    import zenoh

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: Zenoh config file not found")
    try:
        return zenoh.Config.from_file(str(path))
    except Exception as exc:  # zenoh raises ZError with the JSON5 position
        raise ValueError(f"{path}: invalid Zenoh config ({exc})") from exc


def open_lab_session(lab: LabDiscovery | None = None) -> tuple[Any, LabRole]:
    """Open a session with the lab default: listen on the lab port if free, else connect to it.

    Returns the session and the role taken.  ``ZenohSessionError`` if neither works."""
    import zenoh

    lab = LabDiscovery.from_env() if lab is None else lab
    try:
        session = zenoh.open(config_from_json(lab_config_json(LabRole.HUB, lab)))
    except zenoh.ZError as hub_exc:
        log.debug("lab port %d taken (%s): joining as a member", lab.port, hub_exc)
        try:
            session = zenoh.open(config_from_json(lab_config_json(LabRole.MEMBER, lab)))
        except zenoh.ZError as exc:
            raise ZenohSessionError(f"cannot open a lab Zenoh session: listening on {lab.endpoint} failed "
                                    f"({hub_exc}) and so did connecting to it ({exc})") from exc
        log.info("Zenoh lab default: %s is taken, connected to it", lab.endpoint)
        return session, LabRole.MEMBER
    log.info("Zenoh lab default: listening on %s (first FISC process here)", lab.endpoint)
    return session, LabRole.HUB


def open_session(config: Any = None, lab: LabDiscovery | None = None) -> Any:
    """Open a Zenoh session from a ``zenoh.Config``, a config file path, or None (the lab
    default of ``open_lab_session``)."""
    import zenoh

    if config is None:
        return open_lab_session(lab)[0]
    where = str(config) if isinstance(config, (str, Path)) else "the given Zenoh config"
    if isinstance(config, (str, Path)):
        config = load_config(config)
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise ZenohSessionError(f"cannot open a Zenoh session with {where}: {exc}") from exc
