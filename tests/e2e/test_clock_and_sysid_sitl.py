"""Issue 36 on the real PX4 (SITL, SIH): fleet commands that do not depend on the companion's clock,
and one vehicle per agent on a link that carries two.

- **Clock skew.** The agent runs with its companion clock 60 s behind (``skewed_agent.py``). On that
  clock every fleet command would be a minute in the future (the live window accepts 20 s): it is
  accepted because the agent judges freshness on the autopilot's GNSS time (SYSTEM_TIME).  The
  ground's signed ``go`` arms the vehicle; its ``hold`` holds it; nothing is refused.
- **The sysid pin.** Two PX4 vehicles (system ids 1 and 2) reach the agent through one UDP port, as
  on a shared radio or a router.  ``--target-system 2`` flies vehicle 2 only: vehicle 1 stays on the
  ground, disarmed, by its own ULog; the agent counted and ignored vehicle 1's messages.
"""

from __future__ import annotations

import json
import select
import socket
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from fisc_agent.flight.flightlog import read_flight_log

from .conftest import Processes, cli, free_udp_port, poll, run_cli
from .sitl_kit import MAP_ANCHOR, Px4Sitl, ground, ok, px4_ulog, signed_map_on_zenoh

pytestmark = [pytest.mark.sitl, pytest.mark.slow, pytest.mark.timeout(300)]

SWARM = "clock"
SKEW_S = -60.0
"""The companion's clock against true time [s] (beyond the live window of 20 s into the future)."""
SKEWED_AGENT = Path(__file__).with_name("skewed_agent.py")


def _states(log: Path) -> list[str]:
    try:
        return [r["state"] for r in read_flight_log(log)]
    except (OSError, KeyError):
        return []


def _status(member: Path) -> dict[int, dict]:
    out = ok(run_cli(ground("status", "--swarm", SWARM, "--zenoh-config", member, "--json", "--wait", 1.0)))
    return {a["id"]: a for a in json.loads(out)["agents"]}


def _ulog_armed(path: Path) -> bool:
    from pyulog import ULog

    st = [d for d in ULog(str(path), ["vehicle_status"]).data_list if d.name == "vehicle_status"][0].data
    return bool(np.any(st["arming_state"] == 2))  # vehicle_status_s::ARMING_STATE_ARMED


def test_px4_fleet_commands_are_judged_on_the_autopilots_clock_not_a_skewed_companion(shared_path, tmp_path):
    g = signed_map_on_zenoh(tmp_path)
    log = tmp_path / "agent.csv"
    with Px4Sitl(shared_path("sitl", "px4"), tmp_path, 1):
        procs = Processes(tmp_path / "logs")
        try:
            procs.start("publisher", ground("publish", g.served, "--swarm", SWARM, "--zenoh-config", g.hub))
            agent = procs.start("agent", [sys.executable, SKEWED_AGENT, SKEW_S, "--swarm", SWARM, "--zenoh-config", g.member,
                                          "--trusted-key", g.ground_pub, "--mavlink", "udpin:0.0.0.0:14540", "--id", 1,
                                          "--autopilot", "px4", "--entry-stagger", "off", "--flight-log", log])
            assert poll(lambda: _states(log)[-1:] == ["STANDBY"], 60.0, 0.5), procs.report()
            # no go yet: it waits, disarmed, and says so
            snap = _status(g.member).get(1)
            assert snap and snap["state"] == "STANDBY" and snap["authority"] == "waiting" and "armed" not in snap["flags"]
            sent = json.loads(ok(run_cli(ground("cmd", "go", "--swarm", SWARM, "--zenoh-config", g.member, "--key",
                                                g.ground_key, "--ack-wait", "8"))).strip().splitlines()[-1])
            assert sent["acked"] == [1], (sent, agent.log_tail(40))
            assert poll(lambda: "JOIN" in _states(log), 60.0, 0.5), procs.report()
            sent = json.loads(ok(run_cli(ground("cmd", "hold", "--swarm", SWARM, "--zenoh-config", g.member, "--key",
                                                g.ground_key, "--ack-wait", "8"))).strip().splitlines()[-1])
            assert sent["acked"] == [1], (sent, agent.log_tail(40))
            assert poll(lambda: _states(log)[-1:] == ["HOLD"], 15.0, 0.2), procs.report()
            snap = _status(g.member)[1]
            assert snap["commands_refused"] == 0 and snap["authority"] == "command", snap
            assert agent.alive, procs.report()
        finally:
            procs.stop_all(order=lambda p: 0 if p.name == "agent" else 1)


class MergingRelay:
    """Two autopilots' API links (PX4 instance i sends to udp 14540+i) merged onto one agent port,
    as a shared radio or a MAVLink router does: every datagram of either vehicle goes to the agent,
    every datagram of the agent goes to both vehicles."""

    def __init__(self, vehicle_ports: list[int], agent_port: int) -> None:
        self.socks = []
        for p in vehicle_ports:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", p))
            self.socks.append(s)
        self.agent = ("127.0.0.1", agent_port)
        self.vehicles: dict[socket.socket, tuple[str, int]] = {}
        self.out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.out.bind(("127.0.0.1", 0))
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select(self.socks + [self.out], [], [], 0.1)
            for s in ready:
                data, addr = s.recvfrom(65535)
                if s is self.out:
                    for sock, vaddr in list(self.vehicles.items()):
                        sock.sendto(data, vaddr)
                else:
                    self.vehicles[s] = addr
                    self.out.sendto(data, self.agent)

    def close(self) -> None:
        self._stop.set()
        self._t.join(timeout=2)
        for s in self.socks + [self.out]:
            s.close()


def test_px4_target_system_flies_only_its_own_vehicle_on_a_shared_link(shared_path, tmp_path, map_path):
    log = tmp_path / "agent.csv"
    port = free_udp_port()
    with Px4Sitl(shared_path("sitl", "px4"), tmp_path, 2, spacing_m=3.0) as run:
        relay = MergingRelay([14540, 14541], port)
        procs = Processes(tmp_path / "logs")
        try:
            agent = procs.start("agent", cli("fisc-agent") + [
                "--go", "--map", map_path, "--mavlink", f"udpin:127.0.0.1:{port}", "--id", 2, "--autopilot", "px4",
                "--target-system", 2, "--geodetic-anchor", MAP_ANCHOR, "--entry-stagger", "off",
                "--flight-log", log])
            assert poll(lambda: "FLOW" in _states(log), 120.0, 0.5), procs.report()
            assert agent.alive, procs.report()
            text = agent.log_path.read_text(errors="replace")
            assert "from system 1 ignored (this agent flies system 2 only)" in text, agent.log_tail(60)
        finally:
            procs.stop_all()
            relay.close()
        ulog_1, ulog_2 = px4_ulog(run, 0), px4_ulog(run, 1)
    assert _ulog_armed(ulog_2), "vehicle 2 (the target) never armed"
    assert not _ulog_armed(ulog_1), "vehicle 1 armed: the agent flew a vehicle it was not given"


@pytest.fixture(scope="module")
def map_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("map") / "tunnel.fiscmap"
    out = run_cli(cli("fisc-ground") + ["fit", "cd_nozzle_inviscid", "-o", path])
    assert out.returncode == 0, out.stderr
    return path

