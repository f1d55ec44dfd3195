"""Zero-config lab discovery with real processes: every pair of FISC processes that exchange
something finds each other in either start order, with no Zenoh config file.

Each case gets its own free lab port through ``FISC_ZENOH_PORT`` (never 7447): the processes
run exactly the logic of the default, on that port.  A resident (agent, publish, monitor)
listens on the lab port whenever it is free; a visitor (status, cmd) only connects to it.  The
test starts the second process once the first is up (a resident listening on the port, a
visitor's session open).
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

from fisc_agent.zenoh.lab_door import door_config_json, is_door
from fisc_agent.zenoh.session import PORT_ENV, LabDiscovery, LabRole, lab_config_json, open_lab_session
from fisc_agent.map.codec import encode_map
from fisc_ground.maps.write import generate_keypair, read_signing_key

from .conftest import free_port, listening, map_parts, wait_for

pytestmark = pytest.mark.slow

SWARM = "lab"
AGENT_ID = 7
VISITORS = ("status", "cmd")
"""The short-lived commands: they never hold the lab port."""


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
        if first in VISITORS:
            assert wait_for(lambda: "visitor of" in lab.log(first), timeout_s=20), lab.log(first)
            assert not listening(lab.port), f"{first} holds the lab port"
        else:
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
        # the roles: status and cmd visit, the others reside
        for name in (first, second):
            role = "visitor" if name in VISITORS else "resident"
            assert f"{role} of tcp/127.0.0.1:{lab.port}" in lab.log(name), lab.log(name)
    finally:
        lab.close()


def test_lab_config_connects_to_the_lab_port_and_retries_for_ever():
    lab = LabDiscovery(port=45001)
    cfg = lab_config_json(lab)
    assert cfg["listen"]["endpoints"] == ["tcp/127.0.0.1:0"]  # the session never holds the lab port itself
    assert cfg["connect"]["endpoints"] == [lab.endpoint]
    assert cfg["connect"]["exit_on_failure"] is False and cfg["connect"]["timeout_ms"] == -1
    assert cfg["scouting"]["multicast"]["enabled"] is False and cfg["scouting"]["gossip"]["enabled"] is True
    door = door_config_json(lab.endpoint)
    assert door["listen"]["endpoints"] == [lab.endpoint] and door["connect"]["endpoints"] == []
    assert is_door(door["id"]) and not is_door(door_config_json(lab.endpoint)["id"][1:])
    assert door["id"] != door_config_json(lab.endpoint)["id"]
    with pytest.raises(ValueError):
        open_lab_session(lab, "hub")


def _processes(s) -> set[str]:
    """Zenoh ids of the (non-door) peers ``s`` is linked to."""
    return {str(z) for z in s.info.peers_zid() if not is_door(z)}


def test_mesh_survives_the_port_holder_leaving():
    """In-process: two residents and a visitor link pairwise; the first resident (it holds the
    lab port) closes: the other two stay linked, the other resident takes the port over within
    2 s, and a visitor opened after that meets both survivors.  A visitor alone never holds it."""
    lab = LabDiscovery(port=free_port())
    lone = open_lab_session(lab, LabRole.VISITOR)
    time.sleep(1.0)
    assert not listening(lab.port) and lone.door is None
    first = open_lab_session(lab)
    assert first.door.holds and listening(lab.port)
    second = open_lab_session(lab)
    assert not second.door.holds
    sessions = [lone, second]
    zid = lambda s: str(s.info.zid())  # noqa: E731
    try:
        everyone = (first, second, lone)
        assert wait_for(lambda: all(_processes(s) == {zid(o) for o in everyone if o is not s} for s in everyone),
                        timeout_s=10)
        first.close()
        t0 = time.monotonic()
        assert wait_for(lambda: second.door.holds, timeout_s=5)
        assert time.monotonic() - t0 < 2.0
        assert _processes(second) == {zid(lone)} and _processes(lone) == {zid(second)}
        late = open_lab_session(lab, LabRole.VISITOR)
        sessions.append(late)
        assert wait_for(lambda: _processes(late) == {zid(second), zid(lone)}, timeout_s=3)
    finally:
        for s in sessions:
            s.close()
    assert wait_for(lambda: not listening(lab.port), timeout_s=5)  # the last resident closed its door


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
