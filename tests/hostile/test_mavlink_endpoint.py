"""Issue 12, agent side: who the agent talks to and who it believes on a listening UDP endpoint.

Real processes: ``fisc-agent --mavlink udpin:127.0.0.1:P --map ...`` and ``fisc-sim autopilot
--mavlink udpout:127.0.0.1:P`` (PX4, hovering); the stranger is a UDP socket in this process.
"""

from __future__ import annotations

import os
import socket
import time

import pytest

from .conftest import agent_argv, free_udp_port, mav_encoder, poll, start_emulator, tunnel_map

pytestmark = [pytest.mark.slow, pytest.mark.timeout(90)]


@pytest.fixture()
def map_file(tmp_path, ground_keys):
    path = tmp_path / "tunnel.fiscmap"
    path.write_bytes(tunnel_map(100, ground_keys.seed))
    return path


@pytest.fixture()
def stranger():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(0.05)
    yield s
    s.close()


def received(sock: socket.socket, seconds: float) -> int:
    """Bytes that reach ``sock`` within ``seconds``."""
    total = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            data, _ = sock.recvfrom(65535)
            total += len(data)
        except socket.timeout:
            pass
    return total


def log_has(proc, text: str, timeout_s: float) -> bool:
    return bool(poll(lambda: text in proc.log_path.read_text(errors="replace"), timeout_s))


def test_replies_go_only_to_the_autopilot_not_to_every_sender(processes, map_file, ground_keys, stranger):
    """Finding 6: a stranger that sends the agent a few datagrams gets nothing back."""
    port = free_udp_port()
    agent = processes.start("agent", agent_argv(f"udpin:127.0.0.1:{port}", "--map", map_file,
                                                "--trusted-key", ground_keys.pub_path))
    start_emulator(processes, "autopilot", f"udpout:127.0.0.1:{port}", start="-3,0,0")  # on the ground: --go arms it
    assert log_has(agent, "mission ARM -> TAKEOFF", 30), processes.report()
    gcs = mav_encoder(200, 190)
    hb = gcs.heartbeat_encode(6, 8, 0, 0, 4).pack(gcs)  # a GCS heartbeat: MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID
    got = 0
    for _ in range(6):
        stranger.sendto(hb, ("127.0.0.1", port))
        stranger.sendto(os.urandom(40), ("127.0.0.1", port))
        got += received(stranger, 0.5)
    assert got == 0, f"the agent sent {got} bytes to a stranger that merely sent it datagrams"
    assert agent.alive and log_has(agent, "mission JOIN -> FLOW", 20), processes.report()


def test_a_heartbeat_from_another_system_before_the_autopilot_does_not_capture_the_agent(
        processes, map_file, ground_keys, stranger):
    """Finding 6: one HEARTBEAT from system 42 (PX4, disarmed) reaches the agent before the
    autopilot (system 1) starts; the agent must still find, arm and fly the autopilot."""
    port = free_udp_port()
    agent = processes.start("agent", agent_argv(f"udpin:127.0.0.1:{port}", "--map", map_file,
                                                "--trusted-key", ground_keys.pub_path))
    assert log_has(agent, "fisc-agent 1:", 15), processes.report()
    other = mav_encoder(42, 1)
    stranger.sendto(other.heartbeat_encode(2, 12, 0, 0, 3).pack(other), ("127.0.0.1", port))
    assert log_has(agent, "autopilot found: system 42", 5), processes.report()
    start_emulator(processes, "autopilot", f"udpout:127.0.0.1:{port}", start="-3,0,0")  # on the ground: --go arms it
    assert log_has(agent, "autopilot changed to: system 1", 15), processes.report()
    assert log_has(agent, "mission ARM -> TAKEOFF", 15), processes.report()
    assert log_has(agent, "mission JOIN -> FLOW", 25), processes.report()
    assert agent.alive
