"""Issue 36 item 6, link side: a ``MavlinkLink`` never raises on a socket or TCP error; it counts the
error, reopens the transport on a later poll and goes on (real sockets on loopback)."""

from __future__ import annotations

import select
import socket
import struct
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from fisc_agent.mavlink.link import REOPEN_PERIOD_S, MavlinkLink

AP = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)


def heartbeat() -> bytes:
    return mavlink.MAVLink_heartbeat_message(2, 12, 1, 0, 3, 3).pack(AP)


class SimClock:
    def __init__(self) -> None:
        self.t = 50.0

    def __call__(self) -> float:
        return self.t


def poll_until(link: MavlinkLink, cond, timeout_s: float = 3.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        link.poll()
        if cond():
            return True
        time.sleep(0.01)
    return False


def test_udp_socket_failure_is_counted_and_the_socket_reopened_on_the_same_port():
    clock = SimClock()
    link = MavlinkLink("udpin:127.0.0.1:0", clock=clock)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        port = link.udp.local_address[1]
        tx.sendto(heartbeat(), ("127.0.0.1", port))
        assert poll_until(link, lambda: link.heartbeats == 1)
        link.udp.sock.close()                         # the socket dies under the link (EBADF on every call)
        link.send_velocity_ned(1.0, 0.0, 0.0)         # a send on the dead socket: counted, not raised
        assert link.errors == 1 and not link.transport_ok
        assert link.poll() == 0                       # receive fails too: counted, reopened at once (first time)
        assert link.errors == 2 and "UDP receive" in link.last_error and link.transport_ok
        assert link.udp.local_address[1] == port
        tx.sendto(heartbeat(), ("127.0.0.1", port))
        assert poll_until(link, lambda: link.heartbeats == 2)
        link.udp.sock.close()
        link.poll()                                   # fails again within REOPEN_PERIOD_S: stays failed
        assert not link.transport_ok and link.errors == 3
        clock.t += REOPEN_PERIOD_S
        link.poll()                                   # the period has passed: reopened
        assert link.transport_ok
        tx.sendto(heartbeat(), ("127.0.0.1", port))
        assert poll_until(link, lambda: link.heartbeats == 3)
    finally:
        tx.close()
        link.close()


@pytest.fixture()
def server():
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)
    srv.settimeout(3.0)
    yield srv
    srv.close()


def accept(link: MavlinkLink, srv: socket.socket) -> socket.socket:
    conn, _ = srv.accept()
    link.poll()
    return conn


@pytest.mark.parametrize("how", ["reset", "close"])
def test_a_tcp_reset_or_close_is_counted_and_the_link_reconnects(server, how):
    clock = SimClock()
    link = MavlinkLink(f"tcp:127.0.0.1:{server.getsockname()[1]}", clock=clock)
    try:
        conn = accept(link, server)
        conn.sendall(heartbeat())
        assert poll_until(link, lambda: link.heartbeats == 1) and link.target_system == 1
        if how == "reset":
            conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        else:  # read what the link sent (its stream requests) first, or closing resets the connection
            while select.select([conn], [], [], 0.2)[0] and conn.recv(65536):
                pass
        conn.close()
        assert poll_until(link, lambda: link.errors >= 1)      # never raised
        assert ("reset" in link.last_error.lower()) if how == "reset" else ("closed" in link.last_error)
        link.send_velocity_ned(0.0, 0.0, 0.0)                   # sending meanwhile is harmless
        clock.t += REOPEN_PERIOD_S
        link.poll()
        conn2 = accept(link, server)
        assert link.transport_ok
        conn2.sendall(heartbeat() + b"\x00garbage" + heartbeat())
        assert poll_until(link, lambda: link.heartbeats == 3)
        link.send_heartbeat()
        assert select.select([conn2], [], [], 2.0)[0] and conn2.recv(4096)   # our bytes reach the new connection
        conn2.close()
    finally:
        link.close()


def test_a_tcp_server_that_is_down_at_first_is_retried():
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()                                                   # nobody listens on ``port`` now
    clock = SimClock()
    link = MavlinkLink(f"tcp:127.0.0.1:{port}", clock=clock)
    srv = None
    try:
        assert poll_until(link, lambda: link.errors >= 1)       # refused: counted
        srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        srv.bind(("127.0.0.1", port))
        srv.listen(1)
        srv.settimeout(3.0)
        clock.t += REOPEN_PERIOD_S
        link.poll()
        conn, _ = srv.accept()
        conn.sendall(heartbeat())
        assert poll_until(link, lambda: link.heartbeats == 1)
        conn.close()
    finally:
        link.close()
        if srv is not None:
            srv.close()


def test_an_unreachable_udp_peer_is_no_transport_error():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()                                         # nobody listens: ICMP port unreachable
    link = MavlinkLink(f"udpout:127.0.0.1:{port}")
    try:
        for _ in range(20):
            link.send_heartbeat()
            link.poll()
            time.sleep(0.005)
        assert link.errors == 0 and link.transport_ok
    finally:
        link.close()


def test_a_serial_port_that_vanishes_is_counted_and_retried_without_raising():
    """A pseudo-terminal stands in for a USB serial adapter; closing its master side is the adapter
    going away (reads on the port fail with EIO, and the port cannot be opened again)."""
    import os

    master, slave = os.openpty()
    path = os.ttyname(slave)
    clock = SimClock()
    link = MavlinkLink(f"{path}:57600", clock=clock)
    try:
        os.write(master, heartbeat())
        assert poll_until(link, lambda: link.heartbeats == 1) and link.target_system == 1
        os.close(master)
        os.close(slave)
        master = None
        assert poll_until(link, lambda: link.errors >= 1)       # never raised
        link.send_velocity_ned(0.0, 0.0, 0.0)
        for _ in range(3):                                      # reopen attempts fail quietly, once a period
            clock.t += REOPEN_PERIOD_S
            link.poll()
        assert not link.transport_ok and link.errors >= 2
    finally:
        if master is not None:
            os.close(master)
        link.close()
