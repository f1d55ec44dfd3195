"""Wiring of an agent's Zenoh link to its ``Runner``: maps in, fleet commands in, telemetry out.

``connect_runner`` is what ``fisc-agent --swarm`` calls; ``start-at T`` becomes a hold on the
ground now and a resume at T.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable

from fisc_agent.zenoh.fleet_commands import FleetCommand
from fisc_agent.zenoh.keys import DEFAULT_PREFIX
from fisc_agent.zenoh.link import AgentZenohLink

log = logging.getLogger(__name__)


class _CommandDispatcher:
    """Fleet commands -> ``Runner.fleet_command``; ``start-at T`` = hold (on the ground) now,
    resume at T.  A later command cancels a pending start."""

    def __init__(self, runner: Any, clock: Callable[[], float]) -> None:
        self.runner = runner
        self.clock = clock
        self._timer: threading.Timer | None = None
        self._lock = threading.Lock()

    def __call__(self, cmd: FleetCommand) -> None:
        with self._lock:
            self.cancel()
            if cmd.name != "start-at":
                self.runner.fleet_command(cmd.name)
                return
            self.runner.fleet_command("hold")
            delay = float(cmd.start_at_unix_s) - self.clock()
            log.info("start-at: holding until %.3f (in %.1f s)", cmd.start_at_unix_s, delay)
            if delay <= 0:
                self.runner.fleet_command("resume")
            else:
                self._timer = threading.Timer(delay, self.runner.fleet_command, ("resume",))
                self._timer.daemon = True
                self._timer.start()

    def cancel(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None


def connect_runner(runner: Any, session_config: Any, swarm: str, trusted_keys: list[bytes] | None,
                   allow_unsigned: bool = False, telemetry_rate_hz: float = 5.0, prefix: str = DEFAULT_PREFIX,
                   session: Any = None, clock: Callable[[], float] = time.time) -> AgentZenohLink:
    """Start an ``AgentZenohLink`` for a ``fisc_agent.runner.Runner``: verified maps go to
    ``runner.offer_map`` (swapped at its next tick), fleet commands to ``runner.fleet_command``
    (``start-at``: hold until the time, then resume), and ``runner.snapshot()`` is published as
    telemetry at ``telemetry_rate_hz``.  Close the returned link when the runner stops."""
    dispatcher = _CommandDispatcher(runner, clock)
    link = AgentZenohLink(session_config, swarm, runner.cfg.agent_id, trusted_keys, allow_unsigned,
                          runner.offer_map, dispatcher, prefix=prefix, session=session, clock=clock)
    link.close_hooks.append(dispatcher.cancel)
    link.start()
    link.start_telemetry(runner.snapshot, telemetry_rate_hz)
    return link
