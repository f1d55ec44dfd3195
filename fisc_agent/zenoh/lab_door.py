"""The lab port's door: while a resident FISC process runs, the lab port is held by someone.

In the lab default (``fisc_agent.zenoh.session``) every process connects to the lab endpoint
(``tcp/127.0.0.1:7447``) and gossip scouting then links every pair of processes directly.  The
endpoint is only a meeting point: whoever listens there introduces newcomers.  ``LabDoor`` keeps
it open: a resident process checks every ``period_s`` whether the port is free and, if it is,
opens a small second Zenoh session (the *door*: peer mode, listening on the lab endpoint only,
declaring nothing) until the process closes.  Processes whose door-holder leaves keep their
direct links; the next resident to see the port free opens a new door, and every process's
connect (retried by Zenoh) reaches it within a second.

Doors carry a recognisable Zenoh id (``DOOR_ZID_PREFIX``) so that a process can tell the
processes it is connected to from the doors (``is_door``).

Not a separate Zenoh feature on purpose: Zenoh 1.x can retry a busy *listen* endpoint in the
background, but a session whose listen retry is still pending takes 10 s to close and then fails
("close operation timed out"), so every resident but the holder would hang at exit.

This module is onboard code: the standard library and zenoh only.
"""

from __future__ import annotations

import json
import logging
import secrets
import socket
import threading
from typing import Any

log = logging.getLogger(__name__)

DOOR_ZID_PREFIX = "f15cd0"
"""First hex digits of every door's Zenoh id (the rest is random)."""
DOOR_PERIOD_S = 0.5
"""How often a resident checks whether the lab port is free [s]."""


def is_door(zid: Any) -> bool:
    """The Zenoh id ``zid`` (a ``zenoh.ZenohId`` or its hex text) is a lab door's."""
    return str(zid).startswith(DOOR_ZID_PREFIX)


def door_config_json(endpoint: str) -> dict:
    """A door's config: peer mode, listening on ``endpoint`` only (failing at once if it is
    taken), connecting nowhere, multicast scouting off, gossip on (it introduces newcomers)."""
    return {
        "id": DOOR_ZID_PREFIX + secrets.token_hex(13),
        "mode": "peer",
        "listen": {"endpoints": [endpoint], "timeout_ms": 0, "exit_on_failure": True},
        "connect": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": True}},
    }


def port_free(host: str, port: int) -> bool:
    """Nobody listens on ``host:port`` (a bind test with SO_REUSEADDR, as Zenoh's listener binds:
    connections of a past holder waiting in TIME_WAIT do not count)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


class LabDoor:
    """Holds the lab endpoint open (a door session) whenever it is free, until ``close``."""

    def __init__(self, host: str, port: int, period_s: float = DOOR_PERIOD_S) -> None:
        self.host, self.port, self.period_s = host, port, period_s
        self.endpoint = f"tcp/{host}:{port}"
        self._door: Any = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def holds(self) -> bool:
        """This process holds the lab port (its door is open)."""
        return self._door is not None

    def try_open(self) -> bool:
        """Open the door if the port is free (False: someone else holds it, or took it first)."""
        import zenoh

        with self._lock:
            if self._door is not None or self._stop.is_set():
                return self._door is not None
            if not port_free(self.host, self.port):
                return False
            try:
                self._door = zenoh.open(zenoh.Config.from_json5(json.dumps(door_config_json(self.endpoint))))
            except zenoh.ZError as exc:  # another process bound it between the test and the open
                log.debug("lab door on %s not opened: %s", self.endpoint, exc)
                return False
        log.info("Zenoh lab default: holding %s (the lab port was free)", self.endpoint)
        return True

    def start(self) -> "LabDoor":
        """Try at once, then every ``period_s`` on a daemon thread."""
        self.try_open()
        self._thread = threading.Thread(target=self._run, name="fisc-lab-door", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                self.try_open()
            except Exception:  # noqa: BLE001 - the door is a convenience: never end the process for it
                log.exception("lab door on %s", self.endpoint)

    def close(self) -> None:
        """Stop trying and close the door (idempotent)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        with self._lock:
            door, self._door = self._door, None
        if door is not None:
            door.close()
