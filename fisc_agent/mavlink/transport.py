"""Byte transports of the MAVLink link (UDP datagrams, TCP and serial streams) that never raise.

Every transport has ``recv()`` (non-blocking; None when nothing is waiting), ``write(buf)`` (what a
pymavlink ``MAVLink`` encoder calls), ``failed`` / ``reopen()`` and ``close()``.  An ``OSError`` of
the socket or serial port (a serial re-enumeration, a TCP reset, a closed peer) is never raised: it
is counted in ``errors``, remembered in ``last_error``, marks the transport ``failed``, and the link
calls ``reopen()`` on a later poll (which again never raises; a failed reopen stays ``failed``).
"""

from __future__ import annotations

import errno
import logging
import os
import socket

from fisc_agent.mavlink.endpoints import Endpoint

log = logging.getLogger(__name__)

UDP_MAX_DATAGRAM = 65535
STREAM_CHUNK = 4096
UNREACHABLE = frozenset({errno.ENETUNREACH, errno.EHOSTUNREACH, errno.ENETDOWN, errno.EHOSTDOWN, errno.ECONNREFUSED})
"""Send errors that say the peer cannot be reached now, not that the socket is broken."""


class _Failures:
    """Error bookkeeping shared by the transports."""

    errors = 0
    """OSErrors of the transport itself (receive, send, reopen)."""
    send_drops = 0
    """Sends dropped without a transport fault (peer unreachable, send buffer full): not ``errors``."""
    last_error = ""
    """The newest error, in words."""
    failed = False
    """True after an error that needs ``reopen``."""

    def _fail(self, what: str, exc: BaseException, fatal: bool = True) -> None:
        self.last_error = f"{what}: {exc}"
        if fatal:
            self.errors += 1
            self.failed = True
        else:
            self.send_drops += 1


class UdpTransport(_Failures):
    """One non-blocking UDP socket that sends only to the autopilot's address.

    ``udpin``: bound to the endpoint; ``peer`` is None (nothing is sent) until the link locks on
    an autopilot and sets it.  ``udpout``: an ephemeral socket; ``peer`` is the endpoint (the
    agent talks first so that the autopilot learns its address)."""

    def __init__(self, endpoint: Endpoint) -> None:
        self.endpoint = endpoint
        self.listening = endpoint.kind == "udpin"
        self.peer: tuple[str, int] | None = None
        self._bound: tuple[str, int] | None = None
        self.sock = self._open()
        if not self.listening:
            try:
                host = socket.gethostbyname(endpoint.host)
            except OSError as exc:  # no DNS yet: sendto resolves the name on each send
                log.warning("cannot resolve %s (%s); will retry on every send", endpoint.host, exc)
                host = endpoint.host
            self.peer = (host, int(endpoint.port))

    def _open(self) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        if self.listening:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind(self._bound or (self.endpoint.host, int(self.endpoint.port)))
            self._bound = sock.getsockname()  # a reopen binds the same port (also when it was 0)
        return sock

    @property
    def local_address(self) -> tuple[str, int]:
        """The (host, port) this socket is bound to."""
        return self.sock.getsockname()

    def recv(self) -> tuple[bytes, tuple[str, int]] | None:
        """One datagram and its sender, or None when none is waiting (or the socket failed)."""
        try:
            return self.sock.recvfrom(UDP_MAX_DATAGRAM)
        except (BlockingIOError, InterruptedError):
            return None
        except ConnectionRefusedError:  # ICMP port unreachable from an earlier send (peer not up yet)
            return None
        except OSError as exc:
            self._fail("UDP receive", exc)
            return None

    def write(self, buf: bytes) -> None:
        """Send ``buf`` to the autopilot's address (dropped until the autopilot has been heard)."""
        if self.peer is None:
            return
        try:
            self.sock.sendto(buf, self.peer)
        except (ConnectionRefusedError, BlockingIOError, InterruptedError) as exc:  # peer not up, buffer full
            self._fail("UDP send", exc, fatal=False)
        except OSError as exc:
            # no route or host right now: the link timeout covers it; anything else is the socket's fault
            self._fail("UDP send", exc, fatal=exc.errno not in UNREACHABLE)

    def reopen(self) -> bool:
        """A fresh socket (same bound port for ``udpin``); True on success."""
        try:
            sock = self._open()
        except OSError as exc:
            self._fail("UDP reopen", exc)
            return False
        self.sock.close()
        self.sock, self.failed = sock, False
        return True

    def close(self) -> None:
        """Close the socket."""
        self.sock.close()


class TcpClientTransport(_Failures):
    """A non-blocking TCP client; a reset or a closed peer marks it failed (``reopen`` reconnects)."""

    listening = False
    peer = None

    def __init__(self, endpoint: Endpoint) -> None:
        self.endpoint = endpoint
        self.sock: socket.socket | None = None
        if not self.reopen():
            raise ConnectionError(f"MAVLink TCP {endpoint.host}:{endpoint.port}: {self.last_error}")

    def reopen(self) -> bool:
        """Connect again (non-blocking: a refused connection shows as a failure on the next receive)."""
        self.close()
        try:
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setblocking(False)
            err = sock.connect_ex((self.endpoint.host, int(self.endpoint.port)))
        except OSError as exc:
            self._fail("TCP connect", exc)
            return False
        if err not in (0, 115, 36, 10035):  # EINPROGRESS (Linux, macOS), WSAEWOULDBLOCK
            sock.close()
            self._fail("TCP connect", OSError(err, os.strerror(err)))
            return False
        self.sock, self.failed = sock, False
        return True

    def recv(self) -> bytes | None:
        """Bytes received, or None when none are waiting (or the connection failed)."""
        if self.sock is None:
            return None
        try:
            data = self.sock.recv(STREAM_CHUNK)
        except (BlockingIOError, InterruptedError):
            return None
        except OSError as exc:
            self._fail("TCP receive", exc)
            return None
        if not data:
            self._fail("TCP receive", ConnectionError("connection closed by the peer"))
            return None
        return data

    def write(self, buf: bytes) -> None:
        """Send ``buf`` (dropped while not connected)."""
        if self.sock is None or self.failed:
            return
        try:
            self.sock.sendall(buf)
        except (BlockingIOError, InterruptedError) as exc:  # send buffer full or still connecting: drop
            self._fail("TCP send", exc, fatal=False)
        except OSError as exc:
            self._fail("TCP send", exc)

    def close(self) -> None:
        """Close the socket."""
        if self.sock is not None:
            self.sock.close()
            self.sock = None


class MavutilStreamTransport(_Failures):
    """Serial ports and TCP servers through pymavlink's ``mavutil`` (bytes only; the link parses)."""

    listening = False
    peer = None

    def __init__(self, endpoint: Endpoint, mavutil) -> None:
        self.endpoint, self._mavutil = endpoint, mavutil
        self.conn = None
        self.conn = self._connect()  # the first open raises: a wrong device is a start-up error

    def _connect(self):
        kwargs = dict(source_system=255, source_component=191, autoreconnect=False)
        if self.endpoint.kind == "serial":
            kwargs["baud"] = self.endpoint.baud
        return self._mavutil.mavlink_connection(self.endpoint.device, **kwargs)

    def reopen(self) -> bool:
        """Open the port again (a serial adapter that re-enumerated); True on success."""
        self.close()
        try:
            self.conn = self._connect()
        except OSError as exc:
            self._fail("reopen", exc)
            return False
        self.failed = False
        return True

    def recv(self) -> bytes | None:
        """Bytes received, or None when none are waiting (or the port failed)."""
        if self.conn is None:
            return None
        try:
            data = self.conn.recv(STREAM_CHUNK)
        except OSError as exc:
            self._fail("receive", exc)
            return None
        return bytes(data) if data else None

    def write(self, buf: bytes) -> None:
        """Send ``buf`` (dropped while the port is closed)."""
        if self.conn is None:
            return
        try:
            self.conn.write(buf)
        except OSError as exc:
            self._fail("send", exc)

    def close(self) -> None:
        """Close the port."""
        if self.conn is not None:
            try:
                self.conn.close()
            except OSError:
                pass
            self.conn = None
