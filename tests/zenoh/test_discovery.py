"""Zero-config lab discovery with real processes: every pair of FISC processes that exchange
something finds each other in either start order, with no Zenoh config file.

Each case gets its own free lab port through ``FISC_ZENOH_PORT`` (never 7447): the processes
run exactly the listen-or-connect logic of the default, on that port.  The first process
started is the hub (it listens on the port; the test waits until it does), the second finds
the port taken and connects.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fisc_agent.zenoh.session import PORT_ENV, LabDiscovery, LabRole, lab_config_json, open_lab_session
from fisc_agent.map.codec import encode_map
from fisc_ground.maps.write import generate_keypair, read_signing_key

from .conftest import free_port, listening, map_parts, wait_for

pytestmark = pytest.mark.slow

SWARM = "lab"
AGENT_ID = 7


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A ground key pair and a signed map, shared by every case."""
    d = tmp_path_factory.mktemp("discovery")
    key, pub = generate_keypair(d / "ground")
    meta, arrays = map_parts(100)
    blob = encode_map(meta, arrays, read_signing_key(key))
    (d / "m.fiscmap").write_bytes(blob)
    from fisc_agent.map.codec import decode_map
    return {"dir": d, "key": key, "pub": pub, "map": d / "m.fiscmap", "sha": decode_map(blob, None).sha256}


class Lab:
    """Processes of one case, on one lab port; every process is killed at the end."""

    def __init__(self, files: dict, tmp: Path) -> None:
        self.files, self.tmp = files, tmp
        self.port = free_port()
        self.env = {**os.environ, PORT_ENV: str(self.port)}
        self.procs: dict[str, subprocess.Popen] = {}

    def argv(self, name: str, first: bool) -> list[str]:
        """``name``'s command line; the first process waits longer (the second starts after it)."""
        f, ground = self.files, [sys.executable, "-m", "fisc_ground.cli"]
        wait = "8" if first else "4"
        return {
            "publish": ground + ["publish", f["map"], "--swarm", SWARM, "--announce-period", "0.3", "--duration", "30"],
            "monitor": ground + ["monitor", "--swarm", SWARM, "--trusted-key", f["pub"], "--duration",
                                 "7" if first else "6", "--map-timeout", "0.5"],
            "status": ground + ["status", "--swarm", SWARM, "--json", "--wait", wait],
            "cmd": ground + ["cmd", "hold", "--swarm", SWARM, "--key", f["key"], "--wait", wait, "--ack-wait", "5"],
            "agent": [sys.executable, "-m", "fisc_agent.cli", "--go", "--swarm", SWARM, "--trusted-key", f["pub"],
                      "--mavlink", f"udpin:127.0.0.1:{free_port()}", "--id", str(AGENT_ID), "--max-duration", "30"],
        }[name]

    def start(self, name: str) -> None:
        argv = self.argv(name, first=not self.procs)
        with open(self.tmp / f"{name}.err", "w") as log:  # the child keeps its own copy of the descriptor
            self.procs[name] = subprocess.Popen([str(a) for a in argv], env=self.env, stdout=subprocess.PIPE,
                                                stderr=log, text=True)

    def finish(self, name: str, timeout_s: float = 40.0) -> str:
        """Wait for a process that ends by itself; its stdout (it must exit 0)."""
        out, _ = self.procs[name].communicate(timeout=timeout_s)
        assert self.procs[name].returncode == 0, (name, self.log(name))
        return out

    def log(self, name: str) -> str:
        return (self.tmp / f"{name}.err").read_text()

    def close(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.kill()
                p.communicate()


# (first, second, what proves they met): every pair that exchanges something
PAIRS = [("publish", "agent"), ("publish", "monitor"), ("agent", "monitor"), ("agent", "status"),
         ("agent", "cmd")]
CASES = [pytest.param(a, b, id=f"{a}-then-{b}") for a, b in PAIRS] + \
        [pytest.param(b, a, id=f"{b}-then-{a}") for a, b in PAIRS]


@pytest.mark.parametrize("first,second", CASES)
def test_two_processes_meet_in_either_order_without_config(first, second, files, tmp_path):
    lab = Lab(files, tmp_path)
    try:
        lab.start(first)
        assert wait_for(lambda: listening(lab.port), timeout_s=20), f"{first} never listened: {lab.log(first)}"
        lab.start(second)
        pair = {first, second}
        if pair == {"publish", "agent"}:
            assert wait_for(lambda: "accepted (map_version 100" in lab.log("agent"), timeout_s=20), lab.log("agent")
        elif pair == {"publish", "monitor"}:
            out = lab.finish("monitor")
            assert files["sha"][:12] in out, out  # the monitor fetched or followed the served map
            # nobody flies: after 5 s the monitor says so, and that a Zenoh process is connected
            assert "no telemetry on fisc/lab/agents/*/telemetry" in lab.log("monitor"), lab.log("monitor")
            assert "1 Zenoh peer(s)/router(s) are connected" in lab.log("monitor"), lab.log("monitor")
        elif pair == {"agent", "monitor"}:
            out = lab.finish("monitor")
            assert re.search(r"agents heard\s+1\b", out), out
        elif pair == {"agent", "status"}:
            report = json.loads(lab.finish("status"))
            assert [a["id"] for a in report["agents"]] == [AGENT_ID], report
        else:  # agent and cmd: the command reaches the agent and comes back acknowledged
            reply = json.loads(lab.finish("cmd").strip().splitlines()[-1])
            assert reply["acked"] == [AGENT_ID], reply
            assert wait_for(lambda: "fleet command hold" in lab.log("agent"), timeout_s=10), lab.log("agent")
        # the roles: the first listened on the lab port, the second found it taken and connected
        assert f"listening on tcp/127.0.0.1:{lab.port}" in lab.log(first), lab.log(first)
        assert wait_for(lambda: f"tcp/127.0.0.1:{lab.port} is taken, connected to it" in lab.log(second)), \
            lab.log(second)
    finally:
        lab.close()


def test_lab_role_and_config_come_from_one_function(tmp_path):
    """In-process: the first session on a free port is the hub, the second a member that
    connects; both configs are ``lab_config_json``'s."""
    lab = LabDiscovery(port=free_port())
    assert lab_config_json(LabRole.HUB, lab)["listen"]["endpoints"] == [lab.endpoint]
    assert lab_config_json(LabRole.MEMBER, lab)["connect"]["endpoints"] == [lab.endpoint]
    hub, role1 = open_lab_session(lab)
    member, role2 = open_lab_session(lab)
    try:
        assert (role1, role2) == (LabRole.HUB, LabRole.MEMBER)
        assert wait_for(lambda: hub.info.zid() in list(member.info.peers_zid()), timeout_s=10)
    finally:
        member.close()
        hub.close()


def test_lab_port_from_the_environment_is_checked():
    assert LabDiscovery.from_env({}).port == 7447
    assert LabDiscovery.from_env({PORT_ENV: "45001"}).endpoint == "tcp/127.0.0.1:45001"
    for bad in ("abc", "0", "70000"):
        with pytest.raises(ValueError, match=PORT_ENV):
            LabDiscovery.from_env({PORT_ENV: bad})


def test_emulated_fleet_and_monitor_meet_in_either_order(files, tmp_path):
    """The issue's done criterion at test size: ``monitor`` and ``fisc-sim emulate --swarm``,
    no publish, no config, either order: the monitor hears every emulated agent (20 agents
    and the 10 s figure: ``benchmarks/bench_discovery.py``)."""
    n = 4
    for order in (("monitor", "emulate"), ("emulate", "monitor")):
        port = free_port()
        env = {**os.environ, PORT_ENV: str(port)}
        emu = [sys.executable, "-m", "sim.cli", "emulate", "--agents", str(n), "--duration", "20", "--swarm", SWARM,
               "--trusted-key", files["pub"], "-o", tmp_path / f"emu-{order[0]}", "--no-compare", "--no-figures",
               "-q"]
        mon = [sys.executable, "-m", "fisc_ground.cli", "monitor", "--swarm", SWARM, "--duration", "15",
               "--map-timeout", "0.5"]
        procs = {}
        try:
            for name in order:
                procs[name] = subprocess.Popen([str(a) for a in (emu if name == "emulate" else mon)], env=env,
                                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                time.sleep(0.5)
            out, err = procs["monitor"].communicate(timeout=60)
            assert procs["monitor"].returncode == 0, err
            assert re.search(rf"agents heard\s+{n}\b", out), (order, out, err)
        finally:
            for p in procs.values():
                if p.poll() is None:
                    p.kill()
                    p.communicate()


def test_silence_hint_says_why_and_what_to_start():
    from fisc_agent.zenoh.keys import Keys
    from fisc_ground.zenoh.config import silence_hint

    keys = Keys("fisc", "demo")
    assert silence_hint(0, 4.9, keys, None, 0) is None          # not yet
    assert silence_hint(3, 60.0, keys, None, 0) is None         # agents heard
    alone = silence_hint(0, 5.0, keys, None, 0)
    assert "no other Zenoh process is connected" in alone and "tcp/127.0.0.1:" in alone
    assert "fisc-sim emulate --agents 20 --swarm demo" in alone
    peers = silence_hint(0, 6.0, keys, None, 2)
    assert "2 Zenoh peer(s)/router(s) are connected" in peers and "--swarm" in peers
    with_file = silence_hint(0, 6.0, keys, "field.json5", 0)
    assert "field.json5" in with_file and "same router" in with_file
