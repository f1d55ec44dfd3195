"""Wiring of an agent's Zenoh link to its ``Runner``: maps in, fleet commands in, telemetry out.

``connect_runner`` is what ``fisc-agent --swarm`` calls.  Every accepted fleet command reaches
``Runner.fleet_command`` as a ``FleetOrder`` (command, addressed, seq, key id); ``start-at T``
is a ``go`` delivered at T on the agent's clock (``CommandDispatcher``).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable, Mapping

from fisc_agent.flight.mission_types import FleetOrder, MissionCommand
from fisc_agent.zenoh.command_gate import STANDING_GO_S
from fisc_agent.zenoh.fleet_commands import CommandName, FleetCommand
from fisc_agent.zenoh.keys import DEFAULT_PREFIX
from fisc_agent.zenoh.link import AgentZenohLink
from fisc_agent.zenoh.neighbours import NeighbourTable

log = logging.getLogger(__name__)

CANCELS_START = frozenset({CommandName.HOLD, CommandName.LAND, CommandName.GO, CommandName.START_AT})
"""Commands that cancel a pending start-at (a resume or a takeover does not)."""


def order_of(cmd: FleetCommand) -> FleetOrder:
    """The mission's view of an accepted command (``start-at`` is a ``go``)."""
    command = MissionCommand.GO if cmd.name is CommandName.START_AT else MissionCommand(cmd.name.value)
    return FleetOrder(command=command, addressed=cmd.addressed, seq=int(cmd.seq), key_id=cmd.key_id)


class CommandDispatcher:
    """Accepted fleet commands -> ``runner.fleet_command(FleetOrder)``.  ``start-at T`` delivers a
    ``go`` once ``clock()`` (the agent's UNIX time: the autopilot's GNSS time when it has one)
    reaches T, checked every ``poll_s``; a later hold, land, go or start-at cancels it."""

    def __init__(self, runner: Any, clock: Callable[[], float], poll_s: float = 0.1) -> None:
        self.runner = runner
        """Anything with ``fleet_command(FleetOrder)``."""
        self.clock = clock
        """UNIX time [s] a start-at time is compared with."""
        self.poll_s = float(poll_s)
        """Period of the start-at check [s]."""
        self._lock = threading.Lock()
        self._pending: tuple[float, FleetOrder, threading.Event] | None = None

    @property
    def pending_start_unix_s(self) -> float | None:
        """The start-at time waiting to be delivered (None: none)."""
        with self._lock:
            return None if self._pending is None else self._pending[0]

    def __call__(self, cmd: FleetCommand) -> None:
        """Deliver ``cmd`` now, or schedule it (``start-at``)."""
        with self._lock:
            if cmd.name in CANCELS_START:
                self._cancel()
            if cmd.name is not CommandName.START_AT:
                self._deliver(order_of(cmd))
                return
            start = float(cmd.start_at_unix_s)
            stop = threading.Event()
            self._pending = (start, order_of(cmd), stop)
        log.info("start-at: go at %.3f (in %.1f s on the agent's clock)", start, start - self.clock())
        threading.Thread(target=self._wait_and_go, args=(start, stop), name="fisc-start-at", daemon=True).start()

    def _wait_and_go(self, start: float, stop: threading.Event) -> None:
        while not stop.wait(min(self.poll_s, max(0.0, start - self.clock()))):
            if self.clock() < start:
                continue
            with self._lock:
                if stop.is_set() or self._pending is None or self._pending[2] is not stop:
                    return
                order = self._pending[1]
                self._pending = None
                log.info("start-at: %.3f reached, go", start)
                self._deliver(order)
            return

    def _deliver(self, order: FleetOrder) -> None:
        self.runner.fleet_command(order)

    def _cancel(self) -> None:
        if self._pending is not None:
            log.info("start-at %.3f cancelled", self._pending[0])
            self._pending[2].set()
            self._pending = None

    def cancel(self) -> None:
        """Drop a pending start-at (the link closes)."""
        with self._lock:
            self._cancel()


def connect_runner(runner: Any, session_config: Any, swarm: str, trusted_keys: list[bytes] | None,
                   allow_unsigned: bool = False, telemetry_rate_hz: float = 5.0, prefix: str = DEFAULT_PREFIX,
                   session: Any = None, clock: Callable[[], float] = time.time,
                   command_floors: Mapping[str, int] | None = None,
                   standing_go_s: float = STANDING_GO_S) -> AgentZenohLink:
    """Start an ``AgentZenohLink`` for a ``fisc_agent.runner.Runner``: verified maps go to
    ``runner.offer_map`` (swapped at its next tick), fleet commands to ``runner.fleet_command`` as
    ``FleetOrder`` (``start-at``: a go at its time), and ``runner.snapshot()`` is published as
    telemetry at ``telemetry_rate_hz``.  With ``runner.cfg.safety_net`` the link also hears the other
    vehicles' telemetry into a ``NeighbourTable``, set as ``runner.neighbours``.

    ``clock``: the agent's UNIX time [s] (``runner.unix_time``: the autopilot's GNSS time when it
    reports one), on which command freshness and start-at times are judged.  ``command_floors``:
    the per-ground-key sequence floors kept from the last run (the state file); read the current
    ones from ``link.commands.floors``.  ``standing_go_s``: how old a re-published go may be and
    still launch this agent.  Close the returned link when the runner stops."""
    dispatcher = CommandDispatcher(runner, clock)
    neighbours = NeighbourTable() if runner.cfg.safety_net is not None else None
    link = AgentZenohLink(session_config, swarm, runner.cfg.agent_id, trusted_keys, allow_unsigned,
                          runner.offer_map, dispatcher, prefix=prefix, session=session, command_clock=clock,
                          command_floors=dict(command_floors or {}), standing_go_s=standing_go_s,
                          neighbours=neighbours)
    runner.neighbours = neighbours
    link.close_hooks.append(dispatcher.cancel)
    link.start()
    link.start_telemetry(runner.snapshot, telemetry_rate_hz)
    return link
