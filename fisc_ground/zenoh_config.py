"""Zenoh session opening for the ground tools (standard Zenoh JSON5 config files).

Without a config file the lab default applies (``fisc_agent.zenoh_session.open_lab_session``,
the one function every FISC process uses): peer mode on loopback, multicast off; the first
FISC process listens on ``tcp/127.0.0.1:7447`` (``FISC_ZENOH_PORT``), the others connect
there and find each other by gossip, whatever the start order.  For the field write a config
file: router or client mode, TLS/mTLS endpoints and access control (docs/zenoh.md);
``fisc-ground router`` is a router without ``zenohd``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fisc_agent.zenoh_session import open_session


def open_ground_session(path: str | Path | None = None) -> Any:
    """Open a Zenoh session for a ground tool from the config file ``path``, or the lab default
    (None); ``ZenohSessionError`` or ``ValueError`` names the problem."""
    return open_session(None if path is None else Path(path))
