"""Issue 36 on both real autopilots (PX4 SITL with SIH, ArduCopter SITL): fleet commands that do not
depend on the companion's clock, and one vehicle per agent on a link that carries two.

- **Clock skew.** The agent runs with its companion clock 60 s behind (``skewed_agent.py``). On that
  clock every fleet command would be a minute in the future (the live window accepts 20 s): it is
  accepted because the agent judges freshness on the autopilot's GNSS time (SYSTEM_TIME; ArduCopter
  sends it once asked, from its GPS: BRD_RTC_TYPES default 1).  The ground's signed ``go`` arms the
  vehicle; its ``hold`` holds it; nothing is refused.  On ArduCopter its DataFlash log says the same:
  armed, GUIDED, then the hold's BRAKE.
- **The sysid pin.** Two vehicles (system ids 1 and 2) reach the agent through one UDP port, as
  on a shared radio or a router.  ``--target-system 2`` flies vehicle 2 only: vehicle 1 stays on the
  ground, disarmed, by its own log (PX4: its ULog; ArduCopter: no DataFlash log at all, which it starts
  on arming, while vehicle 2's says armed); the agent counted and ignored vehicle 1's messages.
"""

from __future__ import annotations

import json
import select
import socket
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from fisc_agent.flight.flightlog import read_flight_log

from .conftest import Processes, cli, free_udp_port, poll, run_cli
from .ground_station import COPTER_BRAKE, COPTER_GUIDED
from .sitl_kit import (MAP_ANCHOR, ArduPilotSitl, Px4Sitl, SitlRun, dataflash_log, dataflash_modes_and_texts, ground,
                       ok, px4_ulog, signed_map_on_zenoh)

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


def _dataflash_or_none(run: SitlRun, i: int) -> Path | None:
    """ArduCopter instance ``i``'s DataFlash log; None: it wrote none (with LOG_DISARMED 0, the SITL
    default, ArduCopter starts its log on arming)."""
    try:
        return dataflash_log(run, i)
    except FileNotFoundError:
        return None


def _dataflash_armed(path: Path | None) -> bool:
    """ArduCopter's own "Arming motors" message in its DataFlash log (no log: never armed).  Its ARM
    record is not there: the log starts on arming, after that record was due."""
    return path is not None and "Arming motors" in dataflash_modes_and_texts(path)[1]


@dataclass(frozen=True)
class Autopilot:
    """One real autopilot the tests run on."""

    name: str
    """Its ``fisc-agent --autopilot`` value."""
    sitl: Callable[..., object]
    """``sitl(shared_path, work, n, spacing_m)``: its SITL set, a context manager giving a ``SitlRun``."""
    own_log: Callable[[SitlRun, int], Path | None]
    """Instance ``i``'s own flight log, located while its SITL runs (None: it wrote none)."""
    armed_in: Callable[[Path | None], bool]
    """Whether that log shows the vehicle armed."""


PX4 = Autopilot("px4", lambda shared_path, d, n, spacing_m=None: Px4Sitl(shared_path("sitl", "px4"), d, n,
                                                                          spacing_m=spacing_m),
                px4_ulog, _ulog_armed)
ARDUCOPTER = Autopilot("ardupilot", lambda shared_path, d, n, spacing_m=None: ArduPilotSitl(
                           shared_path("sitl", "ardupilot"), d, n, spacing_m=spacing_m),
                       _dataflash_or_none, _dataflash_armed)
AUTOPILOTS = [pytest.param(PX4, id="px4"), pytest.param(ARDUCOPTER, id="arducopter")]


def _fleet_cmd(g, what: str) -> dict:
    """``fisc-ground cmd WHAT``, signed with the ground's key; its last JSON line (who acked)."""
    return json.loads(ok(run_cli(ground("cmd", what, "--swarm", SWARM, "--zenoh-config", g.member, "--key",
                                        g.ground_key, "--ack-wait", "8"))).strip().splitlines()[-1])


@pytest.mark.parametrize("ap", AUTOPILOTS)
def test_fleet_commands_are_judged_on_the_autopilots_clock_not_a_skewed_companion(ap, shared_path, tmp_path):
    t0 = time.monotonic()
    g = signed_map_on_zenoh(tmp_path)
    log = tmp_path / "agent.csv"
    with ap.sitl(shared_path, tmp_path, 1) as run:
        t_ready = time.monotonic()
        procs = Processes(tmp_path / "logs")
        try:
            procs.start("publisher", ground("publish", g.served, "--swarm", SWARM, "--zenoh-config", g.hub))
            agent = procs.start("agent", [sys.executable, SKEWED_AGENT, SKEW_S, "--swarm", SWARM, "--zenoh-config", g.member,
                                          "--trusted-key", g.ground_pub, "--mavlink", "udpin:0.0.0.0:14540", "--id", 1,
                                          "--autopilot", ap.name, "--entry-stagger", "off", "--flight-log", log])
            assert poll(lambda: _states(log)[-1:] == ["STANDBY"], 60.0, 0.5), procs.report()
            # no go yet: it waits, disarmed, and says so
            snap = _status(g.member).get(1)
            assert snap and snap["state"] == "STANDBY" and snap["authority"] == "waiting" and "armed" not in snap["flags"]
            t_go = time.monotonic()
            sent = _fleet_cmd(g, "go")
            assert sent["acked"] == [1], (sent, agent.log_tail(40))
            assert poll(lambda: "JOIN" in _states(log), 60.0, 0.5), procs.report()
            t_join = time.monotonic()
            sent = _fleet_cmd(g, "hold")
            assert sent["acked"] == [1], (sent, agent.log_tail(40))
            assert poll(lambda: _states(log)[-1:] == ["HOLD"], 15.0, 0.2), procs.report()
            t_hold = time.monotonic()
            snap = _status(g.member)[1]
            assert snap["commands_refused"] == 0 and snap["authority"] == "command", snap
            assert agent.alive, procs.report()
        finally:
            procs.stop_all(order=lambda p: 0 if p.name == "agent" else 1)
        found = ap.own_log(run, 0) if ap is ARDUCOPTER else None  # PX4: judged on the agent's view, as before
    measured = {"autopilot": ap.name, "skew_s": SKEW_S, "lock_wait_and_sitl_ready_s": round(t_ready - t0, 1),
                "go_to_join_s": round(t_join - t_go, 1), "hold_to_hold_s": round(t_hold - t_join, 1),
                "commands_refused": snap["commands_refused"], "test_s": round(time.monotonic() - t0, 1)}
    if ap is ARDUCOPTER:  # the autopilot's own view: armed by the go, GUIDED, then the hold's BRAKE
        modes, _ = dataflash_modes_and_texts(found)
        measured["dataflash_modes"] = modes
        assert ap.armed_in(found), "the go did not arm the vehicle (its DataFlash log)"
        assert COPTER_GUIDED in modes and modes[-1] == COPTER_BRAKE, modes
    print(json.dumps(measured))


class MergingRelay:
    """Two autopilots' API links (instance i of either SITL sends to udp 14540+i) merged onto one agent port,
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


@pytest.mark.parametrize("ap", AUTOPILOTS)
def test_target_system_flies_only_its_own_vehicle_on_a_shared_link(ap, shared_path, tmp_path, map_path):
    t0 = time.monotonic()
    log = tmp_path / "agent.csv"
    port = free_udp_port()
    with ap.sitl(shared_path, tmp_path, 2, spacing_m=3.0) as run:
        t_ready = time.monotonic()
        relay = MergingRelay([14540, 14541], port)
        procs = Processes(tmp_path / "logs")
        try:
            agent = procs.start("agent", cli("fisc-agent") + [
                "--go", "--map", map_path, "--mavlink", f"udpin:127.0.0.1:{port}", "--id", 2, "--autopilot", ap.name,
                "--target-system", 2, "--geodetic-anchor", MAP_ANCHOR, "--entry-stagger", "off",
                "--flight-log", log])
            assert poll(lambda: "FLOW" in _states(log), 120.0, 0.5), procs.report()
            t_flow = time.monotonic()
            assert agent.alive, procs.report()
            text = agent.log_path.read_text(errors="replace")
            assert "from system 1 ignored (this agent flies system 2 only)" in text, agent.log_tail(60)
        finally:
            procs.stop_all()
            relay.close()
        log_1, log_2 = ap.own_log(run, 0), ap.own_log(run, 1)
    print(json.dumps({"autopilot": ap.name, "lock_wait_and_sitl_ready_s": round(t_ready - t0, 1),
                      "agent_start_to_flow_s": round(t_flow - t_ready, 1),
                      "ignored_lines": text.count("from system 1 ignored"), "test_s": round(time.monotonic() - t0, 1)}))
    assert ap.armed_in(log_2), "vehicle 2 (the target) never armed"
    assert not ap.armed_in(log_1), "vehicle 1 armed: the agent flew a vehicle it was not given"


@pytest.fixture(scope="module")
def map_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("map") / "tunnel.fiscmap"
    out = run_cli(cli("fisc-ground") + ["fit", "cd_nozzle_inviscid", "-o", path])
    assert out.returncode == 0, out.stderr
    return path

