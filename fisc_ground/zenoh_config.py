"""Zenoh session opening for the ground tools (standard Zenoh JSON5 config files).

Without a config file the lab default applies (``fisc_agent.zenoh_link.default_config_json``):
peer mode, multicast scouting off, loopback only.  The map server (``fisc-ground publish``)
is the hub: it listens on ``tcp/127.0.0.1:7447``; agents, ``status``, ``cmd`` and ``monitor``
connect there (and find each other by gossip).  For the field write a config file: router or
client mode, TLS/mTLS endpoints and access control (docs/zenoh.md).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fisc_agent.zenoh_link import DEFAULT_PORT, load_config, open_session

HUB_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"


def ground_config(path: str | Path | None = None, hub: bool = False) -> Any:
    """``zenoh.Config`` from ``path``, or the lab default (``hub``: listen on 7447 instead of connecting)."""
    if path is not None:
        return load_config(path)
    if hub:
        return load_config(listen=[HUB_ENDPOINT], connect=[])
    return load_config()


def open_ground_session(path: str | Path | None = None, hub: bool = False) -> Any:
    """Open a Zenoh session for a ground tool (see ``ground_config``); ``ZenohSessionError`` names the problem."""
    return open_session(ground_config(path, hub) if path is None else Path(path))
