"""Fixtures for the autopilot emulator tests (helpers live in autopilot_testkit.py)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable, Iterator

import pytest

sys.path.insert(0, str(Path(__file__).parent))  # autopilot_testkit

from autopilot_testkit import Client  # noqa: E402

from sim.autopilot.server import AutopilotEmulator  # noqa: E402


@pytest.fixture
def make_emulator() -> Iterator[Callable[..., AutopilotEmulator]]:
    """Factory for started emulators on ``udpin:127.0.0.1:<free>``; all stopped at teardown."""
    started: list[AutopilotEmulator] = []

    def make(url: str | None = None, **kw: object) -> AutopilotEmulator:
        em = AutopilotEmulator(url or "udpin:127.0.0.1:0", **kw).start()  # type: ignore[arg-type]
        started.append(em)
        return em

    yield make
    for em in started:
        em.stop()


@pytest.fixture
def connect() -> Iterator[Callable[[AutopilotEmulator], Client]]:
    """Factory for clients connected (udpout) to an emulator listening on udpin."""
    clients: list[Client] = []

    def make(em: AutopilotEmulator) -> Client:
        c = Client(f"udpout:127.0.0.1:{em.local_address[1]}")
        clients.append(c)
        return c

    yield make
    for c in clients:
        c.close()
