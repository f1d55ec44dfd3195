"""Shared fixtures for the agent tests: a small synthetic tunnel map and free UDP ports."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))  # agent_testkit

from fisc_agent.map.codec import decode_map  # noqa: E402


from agent_testkit import tunnel_arrays, tunnel_map_bytes  # noqa: E402,F401

from ..ports import free_udp_port  # noqa: E402


@pytest.fixture(scope="session")
def tunnel_map():
    return decode_map(tunnel_map_bytes())


@pytest.fixture()
def tunnel_map_path(tmp_path):
    p = tmp_path / "tunnel.fiscmap"
    p.write_bytes(tunnel_map_bytes())
    return p




@pytest.fixture()
def udp_port():
    return free_udp_port()
