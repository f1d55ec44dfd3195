"""Zenoh sessions: standard JSON5 config files, or the zero-config lab default.

**Lab default (no config file): a mesh without a hub.**  Every FISC process opens its session
with ``open_lab_session``: peer mode, multicast scouting off, loopback only.  Its session
listens on its own ephemeral loopback port and connects to the lab endpoint
``tcp/127.0.0.1:7447`` (Zenoh retries that connect for ever, every 0.25-1 s); gossip scouting
then tells every pair of processes where the other listens, and they connect directly.  Each
process is one of two ``LabRole``s:

- a *resident* (agent, ``fisc-ground publish``, ``monitor``, ``fisc-sim emulate``'s workers)
  also runs a ``LabDoor``: whenever the lab port is free it opens a small door session listening
  there, which introduces newcomers;
- a *visitor* (``status``, ``cmd``: they exit after a few seconds) never holds the lab port.

The door only introduces: data flows on the direct links.  When the process holding the door
leaves, no link between the others is lost; within ``DOOR_PERIOD_S`` another resident opens a
new door and every process's connect reaches it within a second (a visitor started meanwhile
too).  The port comes from ``LabDiscovery`` (``FISC_ZENOH_PORT``; tests use a free port and
the same logic).

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
"""Zenoh's registered port: the lab port unless ``FISC_ZENOH_PORT`` says otherwise."""
PORT_ENV = "FISC_ZENOH_PORT"
"""Environment variable naming the lab port (inherited by child processes such as emulate's workers)."""


class ZenohSessionError(ValueError):
    """A Zenoh session could not be opened (endpoint busy or unreachable, bad TLS files...)."""


@dataclass(frozen=True)
class LabDiscovery:
    """Where the FISC processes of one machine meet when no Zenoh config file is given."""

    port: int = DEFAULT_PORT
    """TCP port where FISC processes meet (one resident at a time listens on it)."""
    host: str = "127.0.0.1"
    """Address of the lab endpoint (loopback: nothing leaves the machine)."""

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
        """The lab port's Zenoh locator, e.g. ``tcp/127.0.0.1:7447``."""
        return f"tcp/{self.host}:{self.port}"


class LabRole(str, Enum):
    """What a process is in the lab default (``open_lab_session``)."""

    RESIDENT = "resident"
    """Runs for the whole flight: holds the lab port (a ``LabDoor``) whenever it is free."""
    VISITOR = "visitor"
    """A short-lived command: connects to the lab port, never holds it."""


LAB_RETRY = {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}
"""Zenoh's retry of the connect to the lab port: 0.25 s, doubling up to 1 s, for ever."""


def peer_config_json(listen: list[str], connect: list[str]) -> dict:
    """Peer mode, multicast scouting off, the given endpoints (gossip scouting stays on)."""
    return {
        "mode": "peer",
        "listen": {"endpoints": list(listen)},
        "connect": {"endpoints": list(connect)},
        "scouting": {"multicast": {"enabled": False}},
    }


def lab_config_json(lab: LabDiscovery) -> dict:
    """THE lab-default config of every FISC process's session, as JSON: its own ephemeral
    loopback port, a connect to the lab endpoint retried for ever (never fatal), gossip
    scouting connecting peers directly, multicast off."""
    return {
        "mode": "peer",
        "listen": {"endpoints": [f"tcp/{lab.host}:0"]},
        "connect": {"endpoints": [lab.endpoint], "timeout_ms": -1, "exit_on_failure": False,
                    "retry": dict(LAB_RETRY)},
        "scouting": {"multicast": {"enabled": False},
                     "gossip": {"enabled": True, "multihop": False, "autoconnect": {"peer": ["router", "peer"]}}},
    }


class LabSession:
    """A lab-default session: every attribute is the ``zenoh.Session``'s; ``close`` also closes
    the resident's ``LabDoor``."""

    def __init__(self, session: Any, role: LabRole, door: Any = None) -> None:
        self._session, self.role, self.door = session, role, door

    def __getattr__(self, name: str) -> Any:
        return getattr(self._session, name)

    def close(self) -> None:
        """Close the session, then the door (if this process holds the lab port)."""
        try:
            self._session.close()
        finally:
            if self.door is not None:
                self.door.close()

    def __enter__(self) -> "LabSession":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


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


def open_lab_session(lab: LabDiscovery | None = None, role: LabRole = LabRole.RESIDENT) -> LabSession:
    """Open a session with the lab default (``lab_config_json``) in ``role`` (a resident also
    starts its ``LabDoor``).  ``ZenohSessionError`` if Zenoh refuses."""
    import zenoh

    from fisc_agent.zenoh.lab_door import LabDoor

    role = LabRole(role)
    lab = LabDiscovery.from_env() if lab is None else lab
    try:
        session = zenoh.open(config_from_json(lab_config_json(lab)))
    except zenoh.ZError as exc:
        raise ZenohSessionError(f"cannot open a lab Zenoh session ({role.value} of {lab.endpoint}): {exc}") from exc
    door = LabDoor(lab.host, lab.port).start() if role == LabRole.RESIDENT else None
    log.info("Zenoh lab default: %s of %s (%s)", role.value, lab.endpoint,
             "holds it whenever it is free" if door is not None else "connects to it, never holds it")
    return LabSession(session, role, door)


def open_session(config: Any = None, lab: LabDiscovery | None = None, role: LabRole = LabRole.RESIDENT) -> Any:
    """Open a Zenoh session from a ``zenoh.Config``, a config file path, or None (the lab
    default of ``open_lab_session`` in ``role``; a config file ignores ``role``)."""
    import zenoh

    if config is None:
        return open_lab_session(lab, role)
    where = str(config) if isinstance(config, (str, Path)) else "the given Zenoh config"
    if isinstance(config, (str, Path)):
        config = load_config(config)
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise ZenohSessionError(f"cannot open a Zenoh session with {where}: {exc}") from exc
