"""Socket transports of the autopilot emulator: UDP (listening or sending) and TCP (server or client).

Non-blocking; each peer is keyed so the emulator can give it a parser of its own.  Endpoints are
parsed by :func:`fisc_agent.mavlink.endpoints.parse_endpoint` (the one home of MAVLink URL syntax);
:func:`open_transport` serves the four kinds an autopilot offers:

* ``udpin`` (also ``udp:``): listen; reply to every peer that has sent something (at most
  ``PEER_LIMIT``, the oldest forgotten first);
* ``udpout``: send to that address; replies are read on the same socket;
* ``tcpin``: TCP server, any number of clients;
* ``tcp`` (also ``tcpout``): TCP client, reconnecting every second.
"""

from __future__ import annotations

import logging
import math
import socket
from typing import Callable

from fisc_agent.mavlink.endpoints import Endpoint, EndpointError, parse_endpoint

__all__ = ["PEER_LIMIT", "Transport", "open_transport", "parse_emulator_endpoint"]

_log = logging.getLogger(__name__)

PEER_LIMIT = 16
"""UDP peers a listening emulator replies to at once."""

EMULATOR_KINDS = ("udpin", "udpout", "tcpin", "tcp")
"""Endpoint kinds the emulator serves (no serial port, no broadcast)."""


def parse_emulator_endpoint(url: str) -> Endpoint:
    """Parse ``url`` with :func:`fisc_agent.mavlink.endpoints.parse_endpoint` and check that the emulator
    can serve it.  Raises :class:`~fisc_agent.mavlink.endpoints.EndpointError` (a ``ValueError``)."""
    ep = parse_endpoint(url)
    if ep.kind not in EMULATOR_KINDS:
        raise EndpointError(
            f"endpoint {url!r}: the autopilot emulator serves udpin:, udpout:, tcpin: or tcp: endpoints, not {ep.kind}"
        )
    return ep


class Transport:
    """Non-blocking datagram/stream I/O; peers are keyed so each gets its own parser."""

    def sockets(self) -> list[socket.socket]:
        """The sockets to wait on (``select``)."""
        raise NotImplementedError

    def receive(self) -> list[tuple[object, bytes]]:
        """Everything readable now, as (peer key, bytes) pairs; never blocks."""
        raise NotImplementedError

    def send(self, data: bytes) -> None:
        """Send ``data`` to every peer (never blocks; UDP may lose it, as a radio link would)."""
        raise NotImplementedError

    @property
    def has_peers(self) -> bool:
        """True if anything would receive what is sent now."""
        raise NotImplementedError

    def close(self) -> None:
        """Close every socket."""
        for s in self.sockets():
            s.close()

    @property
    def local_address(self) -> tuple[str, int]:
        """(host, port) the transport is bound to."""
        return self.sockets()[0].getsockname()[:2]


class _Udp(Transport):
    def __init__(self, ep: Endpoint) -> None:
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self._peers: dict[tuple[str, int], None] = {}
        if ep.kind == "udpin":
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._sock.bind((ep.host, ep.port))
        else:
            self._sock.bind(("0.0.0.0", 0))
            self._peers[(socket.gethostbyname(ep.host), ep.port)] = None
        self._fixed = ep.kind == "udpout"

    def sockets(self) -> list[socket.socket]:
        return [self._sock]

    @property
    def has_peers(self) -> bool:
        return bool(self._peers)

    def receive(self) -> list[tuple[object, bytes]]:
        out: list[tuple[object, bytes]] = []
        while True:
            try:
                data, addr = self._sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return out
            except ConnectionRefusedError:  # ICMP from an earlier send; harmless for UDP
                continue
            if not self._fixed and addr not in self._peers:
                if len(self._peers) >= PEER_LIMIT:
                    self._peers.pop(next(iter(self._peers)))
                self._peers[addr] = None
                _log.info("udp peer %s:%d", *addr)
            out.append((addr, data))

    def send(self, data: bytes) -> None:
        for addr in self._peers:
            try:
                self._sock.sendto(data, addr)
            except (BlockingIOError, ConnectionRefusedError, InterruptedError):
                pass  # UDP: a full buffer or an absent listener loses the datagram, as on a radio link


class _TcpServer(Transport):
    def __init__(self, ep: Endpoint) -> None:
        self._listen = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listen.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listen.bind((ep.host, ep.port))
        self._listen.listen(8)
        self._listen.setblocking(False)
        self._clients: list[socket.socket] = []
        self._out: dict[socket.socket, bytearray] = {}

    def sockets(self) -> list[socket.socket]:
        return [self._listen, *self._clients]

    @property
    def has_peers(self) -> bool:
        return bool(self._clients)

    def receive(self) -> list[tuple[object, bytes]]:
        while True:
            try:
                conn, addr = self._listen.accept()
            except (BlockingIOError, InterruptedError):
                break
            conn.setblocking(False)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._clients.append(conn)
            self._out[conn] = bytearray()
            _log.info("tcp client %s:%d", *addr)
        out: list[tuple[object, bytes]] = []
        for c in list(self._clients):
            out.extend(_read_stream(c, self._drop))
        return out

    def _drop(self, c: socket.socket) -> None:
        if c in self._clients:
            self._clients.remove(c)
        self._out.pop(c, None)
        c.close()

    def send(self, data: bytes) -> None:
        for c in list(self._clients):
            _write_stream(c, self._out[c], data, self._drop)

    @property
    def local_address(self) -> tuple[str, int]:
        return self._listen.getsockname()[:2]


class _TcpClient(Transport):
    def __init__(self, ep: Endpoint, clock: Callable[[], float]) -> None:
        self._ep = ep
        self._clock = clock
        self._sock: socket.socket | None = None
        self._out = bytearray()
        self._next_try = -math.inf
        self._connect()

    def _connect(self) -> None:
        if self._sock is not None or self._clock() < self._next_try:
            return
        self._next_try = self._clock() + 1.0
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.settimeout(1.0)
        try:
            s.connect((self._ep.host, self._ep.port))
        except OSError as exc:
            _log.info("tcp connect to %s:%d failed (%s); retrying", self._ep.host, self._ep.port, exc)
            s.close()
            return
        s.setblocking(False)
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = s
        self._out = bytearray()

    def _drop(self, c: socket.socket) -> None:
        c.close()
        self._sock = None

    def sockets(self) -> list[socket.socket]:
        return [] if self._sock is None else [self._sock]

    @property
    def has_peers(self) -> bool:
        return self._sock is not None

    def receive(self) -> list[tuple[object, bytes]]:
        self._connect()
        return [] if self._sock is None else _read_stream(self._sock, self._drop)

    def send(self, data: bytes) -> None:
        if self._sock is not None:
            _write_stream(self._sock, self._out, data, self._drop)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    @property
    def local_address(self) -> tuple[str, int]:
        return ("", 0) if self._sock is None else self._sock.getsockname()[:2]


def _read_stream(c: socket.socket, drop: Callable[[socket.socket], None]) -> list[tuple[object, bytes]]:
    out: list[tuple[object, bytes]] = []
    while True:
        try:
            data = c.recv(65536)
        except (BlockingIOError, InterruptedError):
            return out
        except OSError:
            drop(c)
            return out
        if not data:
            drop(c)
            return out
        out.append((id(c), data))


_STREAM_BACKLOG_BYTES = 1 << 20


def _write_stream(c: socket.socket, out: bytearray, data: bytes, drop: Callable[[socket.socket], None]) -> None:
    """Queue ``data`` behind what the socket has not taken yet and send what it takes now
    (never blocks; messages stay whole). A peer that stops reading is dropped after 1 MiB."""
    out += data
    if len(out) > _STREAM_BACKLOG_BYTES:
        _log.warning("tcp peer not reading (%d bytes queued); closing it", len(out))
        drop(c)
        return
    try:
        n = c.send(out)
    except (BlockingIOError, InterruptedError):
        return
    except OSError:
        drop(c)
        return
    del out[:n]


def open_transport(ep: Endpoint, clock: Callable[[], float]) -> Transport:
    """The transport of a parsed emulator endpoint (see :func:`parse_emulator_endpoint`)."""
    if ep.kind in ("udpin", "udpout"):
        return _Udp(ep)
    if ep.kind == "tcpin":
        return _TcpServer(ep)
    return _TcpClient(ep, clock)
