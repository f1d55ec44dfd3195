"""Free local ports for tests that start real servers (one place for the helper).

The ports are chosen *outside* the kernel's ephemeral range.  A server port picked in advance is
only reserved by convention until the server binds it, and clients often start first: a client
that keeps retrying a TCP connect to 127.0.0.1:P is itself given ephemeral source ports, and when
it is given P it connects to itself (TCP simultaneous open) and holds the port; a listener on port
0 can be given P as well.  Both happened in CI ("Address already in use" for the Zenoh hub of the
fleet tests, whose agents start before the ground).  Outside the ephemeral range neither can.
"""

from __future__ import annotations

import random
import socket
from pathlib import Path

_RANGE_FILE = Path("/proc/sys/net/ipv4/ip_local_port_range")
SITL_PORTS = range(13000, 19000)
"""Never handed out: the ports PX4 SITL binds and sends to (13030+i, 13280+i, 14030+i, 14280+i, 14540-14549,
14550, 14580+i, 18570+i: ``../shared/sitl/px4/etc/init.d-posix/px4-rc.mavlink``; ArduPilot SITL sends to
14540+i and 14550).  Under ``pytest -n 2`` the real-autopilot tests fly on one worker while the other runs
the rest: a port of theirs given to another test would take a vehicle's link."""


def _candidates() -> range:
    """Unprivileged ports outside the ephemeral range (Linux default 32768-60999)."""
    try:
        lo, hi = (int(v) for v in _RANGE_FILE.read_text().split())
    except (OSError, ValueError):
        lo, hi = 32768, 60999
    return range(10000, lo) if lo - 10000 >= 1000 else range(hi + 1, 65536)


def _free_port(kind: int) -> int:
    ports = _candidates()
    rng = random.Random()  # seeded from the OS: parallel test processes pick different ports
    for _ in range(500):
        port = rng.choice(ports)
        if port in SITL_PORTS:
            continue
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError(f"no free port on 127.0.0.1 in {ports.start}-{ports.stop - 1}")


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that is free right now, outside the ephemeral range."""
    return _free_port(socket.SOCK_STREAM)


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that is free right now, outside the ephemeral range."""
    return _free_port(socket.SOCK_DGRAM)
