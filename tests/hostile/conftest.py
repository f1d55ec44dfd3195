"""Hostile-input harness: a real agent process, the real emulator, a real Zenoh session.

Topology of ``flight`` (one per test module; every box but the relay is its own OS process)::

    this test process                       fisc-agent (udpout)            fisc-sim autopilot
    Zenoh hub session  <--- tcp/127.0.0.1 ---> --swarm, --trusted-key
    (MapServer, TelemetryListener,           --mavlink udpout:relay.front
     the attacker's puts)                          |  UDP
                                            MavRelay front <-> back  ---- UDP ---->  udpin:127.0.0.1:P

``MavRelay`` forwards MAVLink both ways like a mavlink-router would, timestamps every
SET_POSITION_TARGET_LOCAL_NED the agent sends towards the emulator (the setpoint rate *at the
autopilot*), and lets a test inject datagrams to the agent *from the autopilot's address*
(``inject``) or from a stranger's (``stranger``).  The map is the built-in default tunnel
re-signed with a test ground key at any ``map_version``.

Process management, ports and polling come from ``tests/e2e/conftest.py``.
"""

from __future__ import annotations

import re
import select
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from ..e2e.conftest import (Processes, cli, free_tcp_port, free_udp_port, poll, processes,  # noqa: F401
                            write_zenoh_config)
from ..optional import require_module

zenoh = require_module("zenoh")

SWARM = "hostile"
AGENT_ID = 1
SETPOINT_MSG_ID = 84  # SET_POSITION_TARGET_LOCAL_NED
FLYING = {"TAKEOFF", "JOIN", "FLOW", "RETURN", "EXIT"}


# ---------------------------------------------------------------------------------- MAVLink
def mav_encoder(system: int, component: int):
    """A pymavlink MAVLink 2 encoder with a fixed identity (``.pack(msg)`` -> bytes)."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    return mavlink.MAVLink(None, srcSystem=system, srcComponent=component)


def msg_id(datagram: bytes) -> int | None:
    """Message id of the first frame of a datagram (MAVLink 2 or 1)."""
    if len(datagram) >= 10 and datagram[0] == 0xFD:
        return datagram[7] | (datagram[8] << 8) | (datagram[9] << 16)
    if len(datagram) >= 6 and datagram[0] == 0xFE:
        return datagram[5]
    return None


class MavRelay:
    """UDP relay agent <-> emulator that counts the agent's setpoints and injects datagrams."""

    def __init__(self, emulator_port: int) -> None:
        self.emulator = ("127.0.0.1", emulator_port)
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind(("127.0.0.1", 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.bind(("127.0.0.1", 0))
        self.agent: tuple[str, int] | None = None
        self.setpoint_t: list[float] = []
        self.forward_to_agent = True
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="mav-relay", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        return self.front.getsockname()[1]

    def _loop(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.front, self.back], [], [], 0.1)
            for s in ready:
                try:
                    data, addr = s.recvfrom(65535)
                except OSError:
                    continue
                if s is self.front:
                    self.agent = addr
                    if msg_id(data) == SETPOINT_MSG_ID:
                        self.setpoint_t.append(time.monotonic())
                    self.back.sendto(data, self.emulator)
                elif self.agent is not None and self.forward_to_agent:
                    self.front.sendto(data, self.agent)

    def inject(self, data: bytes) -> None:
        """One datagram to the agent from the autopilot's address (as a router merging streams)."""
        assert self.agent is not None, "the agent has not talked yet"
        self.front.sendto(data, self.agent)

    def setpoints_per_s(self, t0: float, t1: float) -> list[int]:
        """Setpoints forwarded to the emulator in each whole second of [t0, t1)."""
        ts = list(self.setpoint_t)
        n = int(t1 - t0)
        return [sum(1 for t in ts if t0 + k <= t < t0 + k + 1) for k in range(n)]

    def max_gap_s(self, t0: float, t1: float) -> float:
        ts = [t for t in list(self.setpoint_t) if t0 <= t < t1]
        edges = [t0] + ts + [t1]
        return max(b - a for a, b in zip(edges, edges[1:]))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.front.close()
        self.back.close()


# ---------------------------------------------------------------------------------- maps
@dataclass(frozen=True)
class Keys_:
    key_path: Path
    pub_path: Path
    seed: bytes


@pytest.fixture(scope="session")
def ground_keys(tmp_path_factory) -> Keys_:
    from fisc_ground.maps.write import generate_keypair, read_signing_key

    d = tmp_path_factory.mktemp("keys")
    key, pub = generate_keypair(d / "ground")
    return Keys_(Path(key), Path(pub), read_signing_key(key))


def tunnel_map(version: int, seed: bytes | None) -> bytes:
    """The built-in default tunnel (15 m, 560 CVs) as map bytes of ``map_version`` ``version``."""
    import field_maps
    from fisc_agent.map.codec import load_map
    from fisc_agent.map.codec import encode_map

    cm = load_map(Path(field_maps.__file__).parent / "default.fiscmap")
    meta = {k: v for k, v in cm.body.items() if k not in ("schema", "schema_version", "arrays")}
    meta["map_version"] = int(version)
    return encode_map(meta, dict(cm.arrays), seed)


# ---------------------------------------------------------------------------------- processes
def rss_mb(pid: int) -> float:
    """Resident memory of a process [MB] (Linux /proc)."""
    text = Path(f"/proc/{pid}/status").read_text()
    return int(re.search(r"VmRSS:\s+(\d+) kB", text).group(1)) / 1024.0


def start_emulator(procs: Processes, name: str, mavlink: str, start: str = "-3,0,-1.5", sysid: int = 1):
    """``fisc-sim autopilot`` (PX4 personality; D < 0: hovering, armed, in AUTO.LOITER: not the agent's
    vehicle until a signed takeover addressed to it)."""
    return procs.start(name, cli("fisc-sim") + ["autopilot", "--mavlink", mavlink, "--personality", "px4",
                                                f"--start={start}", "--sysid", sysid])


def agent_argv(mavlink: str, *extra) -> list:
    return cli("fisc-agent") + ["--go", "--mavlink", mavlink, "--id", AGENT_ID, "--origin", "0,0,-4",
                                "--exit-policy", "loop", "--join-speed", "3", *extra]


class LogCursor:
    """Text a process logged after a mark (``mark()`` then ``since()``)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.offset = 0

    def mark(self) -> None:
        self.offset = self.path.stat().st_size

    def since(self) -> str:
        with open(self.path, "rb") as f:
            f.seek(self.offset)
            return f.read().decode(errors="replace")


@dataclass
class Flight:
    """A flying agent under test and the handles the attacks need."""

    procs: Processes
    agent: object
    emulator: object
    relay: MavRelay
    hub: object
    server: object
    listener: object
    keys: Keys_
    member_cfg: Path
    map_version: int
    log: LogCursor
    notes: dict = field(default_factory=dict)

    def telemetry(self):
        got = self.listener.snapshot().get(AGENT_ID)
        return got[0] if got else None

    def state(self) -> str | None:
        t = self.telemetry()
        return t.state if t else None

    def alive(self) -> bool:
        return self.agent.alive

    def report(self) -> str:
        return self.procs.report(40)

    def serve(self, version: int) -> None:
        self.server.serve(tunnel_map(version, self.keys.seed))

    def wait_flying(self, timeout_s: float = 40.0, states=("FLOW", "JOIN")) -> None:
        ok = poll(lambda: self.state() in states, timeout_s)
        assert ok, f"agent not flying ({self.state()})\n{self.report()}"

    def put_map_key(self, payload: bytes) -> None:
        self.hub.put(f"fisc/{SWARM}/map", payload)

    def put_cmd_key(self, payload: bytes) -> None:
        self.hub.put(f"fisc/{SWARM}/cmd", payload)


@pytest.fixture(scope="module")
def flight(tmp_path_factory, ground_keys, request):
    """One agent flying loops through the tunnel (map version 100 over Zenoh)."""
    from fisc_agent.zenoh.keys import Keys
    from fisc_ground.zenoh.fleet import TelemetryListener, make_command, send_command
    from fisc_ground.zenoh.publish import MapServer

    d = tmp_path_factory.mktemp("flight")
    procs = Processes(d / "logs")
    relay = None
    hub = None
    try:
        port = free_tcp_port()
        hub_cfg = write_zenoh_config(d / "hub.json5", [f"tcp/127.0.0.1:{port}"], [])
        member_cfg = write_zenoh_config(d / "member.json5", ["tcp/127.0.0.1:0"], [f"tcp/127.0.0.1:{port}"])
        hub = zenoh.open(zenoh.Config.from_file(str(hub_cfg)))
        server = MapServer(hub, SWARM, announce_period_s=1.0)
        listener = TelemetryListener(hub, Keys("fisc", SWARM))
        emu_port = free_udp_port()
        emulator = start_emulator(procs, "autopilot", f"udpin:127.0.0.1:{emu_port}")
        relay = MavRelay(emu_port)
        agent = procs.start("agent", agent_argv(f"udpout:127.0.0.1:{relay.port}", "--swarm", SWARM,
                                                "--zenoh-config", member_cfg, "--trusted-key",
                                                ground_keys.pub_path, "--telemetry-rate", "10",
                                                "--entry-stagger", "off"))   # a lone agent: no admission windows
        f = Flight(procs, agent, emulator, relay, hub, server, listener, ground_keys, member_cfg, 100,
                   LogCursor(agent.log_path))
        f.serve(100)
        # the emulator starts hovering: not the agent's until the ground hands it over (signed, addressed)
        assert poll(lambda: f.state() == "STANDBY", 40.0), f"agent not standing by ({f.state()})\n{f.report()}"
        send_command(hub, Keys("fisc", SWARM), make_command("takeover", SWARM, (AGENT_ID,)), ground_keys.seed)
        f.wait_flying(60.0)
        yield f
    finally:
        procs.stop_all(order=lambda p: 0 if p.name == "agent" else 1)
        if relay is not None:
            relay.close()
        if hub is not None:
            hub.close()


def steady(flight: Flight, t0: float, t1: float) -> tuple[float, int, float]:
    """(mean setpoints/s, fewest in any whole second, longest gap [s]) at the emulator in [t0, t1)."""
    per_s = flight.relay.setpoints_per_s(t0, t1)
    count = sum(1 for t in list(flight.relay.setpoint_t) if t0 <= t < t1)
    mean = count / (t1 - t0)
    return mean, min(per_s) if per_s else count, flight.relay.max_gap_s(t0, t1)


def transitions(text: str) -> list[str]:
    """Mission transitions in a stretch of agent log."""
    return re.findall(r"mission \w+ -> \w+ \([^)]*\)", text)


