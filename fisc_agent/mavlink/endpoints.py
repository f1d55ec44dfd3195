"""MAVLink endpoint URLs in the syntaxes pymavlink/MAVProxy and MAVSDK users write (pure).

Accepted forms (``HOST`` may be empty where listening; it then means ``0.0.0.0``)::

    udpin:HOST:PORT   udp:HOST:PORT       listen on UDP (pymavlink; ``udp:`` is listening too)
    udpout:HOST:PORT                      send to HOST:PORT (the peer learns our address)
    udpbcast:HOST:PORT                    UDP broadcast
    tcp:HOST:PORT     tcpin:HOST:PORT     TCP client / TCP server (``tcpout:`` = ``tcp:``)
    udp://[HOST]:PORT                     MAVSDK: listen on HOST:PORT (``udp://:14540``)
    udpin://HOST:PORT udpout://HOST:PORT  MAVSDK >= 2 explicit directions
    tcp://HOST:PORT   tcpout://HOST:PORT  MAVSDK TCP client; ``tcpin://`` = server
    serial:///dev/ttyUSB0[:BAUD]          MAVSDK serial (``serial://COM3:57600`` on Windows)
    /dev/ttyACM0[:BAUD] or [,BAUD]        a serial device (MAVProxy writes ``,BAUD``)
    COM3[:BAUD]                           a Windows serial port

``parse_endpoint`` turns any of them into what ``pymavlink.mavutil.mavlink_connection``
takes: a device string plus, for serial ports, a baud rate.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

DEFAULT_BAUD = 57600

_PYMAVLINK_PREFIX = {
    "udpin": "udpin", "udp": "udpin", "udpout": "udpout", "udpbcast": "udpbcast",
    "tcp": "tcp", "tcpout": "tcp", "tcpin": "tcpin",
}
_MAVSDK_SCHEME = {
    "udp": "udpin", "udpin": "udpin", "udpout": "udpout",
    "tcp": "tcp", "tcpout": "tcp", "tcpin": "tcpin",
}
_LISTENING = {"udpin", "tcpin"}


class EndpointError(ValueError):
    """An endpoint URL could not be understood; the message quotes it and says why."""


@dataclass(frozen=True)
class Endpoint:
    """A parsed MAVLink endpoint."""

    kind: str
    """One of ``udpin``, ``udpout``, ``udpbcast``, ``tcp``, ``tcpin``, ``serial``."""
    host: str
    """Host or address for network kinds; the device path for ``serial``."""
    port: int | None
    """UDP/TCP port; None for ``serial``."""
    baud: int | None
    """Serial baud rate; None for network kinds."""

    @property
    def device(self) -> str:
        """The device string ``pymavlink.mavutil.mavlink_connection`` expects."""
        if self.kind == "serial":
            return self.host
        return f"{self.kind}:{self.host}:{self.port}"

    @property
    def listening(self) -> bool:
        """True when this side waits for the peer (``udpin``/``tcpin``)."""
        return self.kind in _LISTENING

    def __str__(self) -> str:
        return f"{self.device}@{self.baud}" if self.kind == "serial" else self.device


def _port(url: str, text: str, listening: bool) -> int:
    low = 0 if listening else 1  # a listener may bind port 0 (any free port)
    if not text.isdigit() or not low <= int(text) < 65536:
        raise EndpointError(f"endpoint {url!r}: port {text!r} is not a number in {low}..65535")
    return int(text)


def _host_port(url: str, kind: str, rest: str) -> Endpoint:
    host, sep, port = rest.rpartition(":")
    if not sep:
        raise EndpointError(f"endpoint {url!r}: expected HOST:PORT after '{kind}:'")
    host = host.strip("[]")
    if not host:
        if kind not in _LISTENING:
            raise EndpointError(f"endpoint {url!r}: a host is required to connect/send ({kind})")
        host = "0.0.0.0"
    return Endpoint(kind=kind, host=host, port=_port(url, port, kind in _LISTENING), baud=None)


def _serial(url: str, rest: str) -> Endpoint:
    m = re.fullmatch(r"(.+?)(?:[:,@](\d+))?", rest)
    if not m or not m.group(1):
        raise EndpointError(f"endpoint {url!r}: expected a serial device, optionally ':BAUD'")
    baud = int(m.group(2)) if m.group(2) else DEFAULT_BAUD
    if baud <= 0:
        raise EndpointError(f"endpoint {url!r}: baud rate must be positive")
    return Endpoint(kind="serial", host=m.group(1), port=None, baud=baud)


def parse_endpoint(url: str) -> Endpoint:
    """Parse a pymavlink-, MAVProxy- or MAVSDK-style endpoint URL.  Raises ``EndpointError``."""
    text = url.strip()
    if not text:
        raise EndpointError("endpoint '': empty MAVLink URL")
    if "://" in text:
        scheme, rest = text.split("://", 1)
        scheme = scheme.lower()
        if scheme == "serial":
            return _serial(url, rest)
        if scheme not in _MAVSDK_SCHEME:
            raise EndpointError(
                f"endpoint {url!r}: unknown scheme {scheme!r}; use udp://, udpin://, udpout://, "
                "tcp://, tcpin:// or serial://")
        return _host_port(url, _MAVSDK_SCHEME[scheme], rest)
    if text.startswith("/") or re.match(r"(?i)^com\d+([:,@]\d+)?$", text):
        return _serial(url, text)
    prefix, sep, rest = text.partition(":")
    if sep and prefix.lower() in _PYMAVLINK_PREFIX:
        return _host_port(url, _PYMAVLINK_PREFIX[prefix.lower()], rest)
    raise EndpointError(
        f"endpoint {url!r}: not understood; examples: udpin:0.0.0.0:14540, udpout:HOST:14550, "
        "tcp:HOST:5760, udp://:14540, serial:///dev/ttyUSB0:921600, /dev/ttyACM0:57600")
