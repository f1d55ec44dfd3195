"""The test ports: never one of the real autopilots' (``ports.SITL_PORTS``), at the range's edges."""

from __future__ import annotations

import os
import random

import pytest

from . import ports


@pytest.mark.parametrize("offered, given", [([13000, 12999], 12999), ([18999, 19000], 19000),
                                            ([14540, 14550, 18570, 13030, 12000], 12000)])
def test_a_port_the_sitl_instances_use_is_never_handed_out(monkeypatch, offered, given):
    picks = iter(offered)
    monkeypatch.setattr(random.Random, "choice", lambda self, seq: next(picks))
    assert ports.free_udp_port() == given
    picks = iter(offered)
    assert ports.free_tcp_port() == given


def test_sitl_ports_cover_every_port_px4_and_ardupilot_sitl_use():
    px4 = [p + i for i in range(10) for p in (13030, 13280, 14030, 14280, 14540, 14580, 18570)] + [14549, 14550]
    assert all(p in ports.SITL_PORTS for p in px4)


def test_each_xdist_worker_has_a_lab_port_of_its_own():
    """Under ``-n 2`` (the README's command) the session fixture of ``tests/conftest.py`` set it."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        pytest.skip("not under pytest-xdist: the serial run shares the one lab port a test sets")
    from fisc_agent.zenoh.session import PORT_ENV

    assert int(os.environ[PORT_ENV]) not in ports.SITL_PORTS and int(os.environ[PORT_ENV]) != 7447
