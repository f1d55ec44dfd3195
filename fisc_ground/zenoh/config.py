"""Zenoh session opening for the ground tools (standard Zenoh JSON5 config files).

Without a config file the lab default applies (``fisc_agent.zenoh.session.open_lab_session``,
the one function every FISC process uses): peer mode on loopback, multicast off; every process
connects to ``tcp/127.0.0.1:7447`` (``FISC_ZENOH_PORT``), which one long-lived process at a time
listens on, and gossip links every pair directly, whatever the start order and whoever leaves.  For the field write a config
file: router or client mode, TLS/mTLS endpoints and access control (docs/zenoh.md);
``fisc-ground router`` is a router without ``zenohd``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fisc_agent.zenoh.keys import Keys
from fisc_agent.zenoh.session import PORT_ENV, LabDiscovery, LabRole, open_session


def open_ground_session(path: str | Path | None = None, role: LabRole = LabRole.RESIDENT) -> Any:
    """Open a Zenoh session for a ground tool from the config file ``path``, or the lab default
    (None) in ``role`` (``LabRole.VISITOR`` for the short-lived ``status`` and ``cmd``);
    ``ZenohSessionError`` or ``ValueError`` names the problem."""
    return open_session(None if path is None else Path(path), role=role)


SILENCE_HINT_AFTER_S = 5.0
"""The monitor explains itself when it has heard no agent for this long [s]."""


def zenoh_neighbours(session: Any) -> int:
    """Zenoh peers and routers this session is connected to (lab doors are not counted: they
    only introduce processes to each other)."""
    from fisc_agent.zenoh.lab_door import is_door

    info = session.info
    return sum(not is_door(z) for z in info.peers_zid()) + len(list(info.routers_zid()))


def silence_hint(agents_heard: int, silent_s: float, keys: Keys, config_path: str | Path | None,
                 neighbours: int) -> str | None:
    """Why a monitor hears nobody and what to start (None while agents are heard or for the
    first ``SILENCE_HINT_AFTER_S``).  ``neighbours``: Zenoh peers/routers connected."""
    if agents_heard > 0 or silent_s < SILENCE_HINT_AFTER_S:
        return None
    head = f"no telemetry on {keys.all_telemetry} for {silent_s:.0f} s: "
    start = (f"start agents of swarm {keys.swarm!r}, e.g. `fisc-sim emulate --agents 20 --swarm {keys.swarm} "
             f"--trusted-key ground.pub` or `fisc-agent --swarm {keys.swarm} ...`")
    if neighbours > 0:
        return (head + f"{neighbours} Zenoh peer(s)/router(s) are connected, but none publishes this swarm's "
                "telemetry: check the agents' --swarm and prefix (`fisc-ground status --swarm NAME` lists a "
                "swarm's agents), or they are still starting; otherwise " + start)
    if config_path is None:
        lab = LabDiscovery.from_env()
        where = (f"no other Zenoh process is connected; in the lab default every FISC process on this machine "
                 f"meets at {lab.endpoint} ({PORT_ENV}={lab.port}; every process must use the same port)")
    else:
        where = (f"no Zenoh peer or router is connected with {config_path}: the agents' config must reach "
                 "this one's endpoints (the same router, or listen/connect endpoints that match)")
    return head + where + "; " + start
