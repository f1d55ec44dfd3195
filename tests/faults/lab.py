"""Running a fault-injection flight: real FISC processes on one lab port, killed with SIGKILL at
seeded random moments, every kill logged.

- ``FaultLab``: a directory, a signed map and its key pair, a free lab port (``FISC_ZENOH_PORT``,
  set for every child, never 7447), the children (``tests/e2e/conftest.Processes``) and the
  ``KillLog``;
- ``start_vehicle``: a stand-alone ``fisc-sim autopilot`` (PX4 personality, on the ground) and
  the ``fisc-agent`` flying it (``--go``: it arms, takes off and joins the tunnel by itself);
- ``KillLog.kill_at``: waits a random delay drawn from the lab's seeded generator, then
  ``kill -9`` the process (its pid, not its group: the kill of one process is the fault),
  records the wall-clock moment (the monitor's receive clock) and prints the line, so a failure
  can be replayed with ``FISC_FAULT_SEED``.
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import signal
import socket
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fisc_agent.zenoh.session import PORT_ENV

from ..e2e.conftest import Proc, Processes, cli, free_tcp_port, free_udp_port, poll, run_cli

SIGINT_DEFAULT = [sys.executable, "-c", "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); "
                  "os.execv(sys.argv[1], sys.argv[1:])"]
"""argv prefix: exec the command with SIGINT at its default (a shell's background job inherits it
ignored, and Python then installs no KeyboardInterrupt handler)."""
SEED_ENV = "FISC_FAULT_SEED"
"""Environment variable overriding the kill moments' seed (the default seed is fixed)."""
DEFAULT_SEED = 38


def ground(*args) -> list[str]:
    """argv of ``fisc-ground ARGS``."""
    return cli("fisc-ground") + [str(a) for a in args]


def ok(out) -> str:
    """stdout of a finished command (its stderr in the failure message otherwise)."""
    assert out.returncode == 0, f"{out.args}: exit {out.returncode}\nstdout:\n{out.stdout}\nstderr:\n{out.stderr}"
    return out.stdout


def listening(port: int) -> bool:
    """Something accepts TCP connections on 127.0.0.1:port."""
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


@dataclass(frozen=True)
class Kill:
    """One injected fault."""

    case: str
    """The kind of process killed (the test that judges it)."""
    process: str
    """The child's name."""
    pid: int
    """Its pid."""
    delay_s: float
    """The random delay drawn before the kill [s]."""
    t_s: float
    """Wall-clock moment of the SIGKILL [UNIX s]."""


@dataclass
class KillLog:
    """The kills of one flight, at moments drawn from one seeded generator."""

    seed: int
    """Seed of the delays."""
    path: Path
    """JSON lines file of the kills (also printed)."""
    kills: list[Kill] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.rng = random.Random(self.seed)

    def kill_at(self, case: str, proc: Proc, low_s: float, high_s: float) -> Kill:
        """Wait a random delay in [low_s, high_s], then SIGKILL ``proc`` (which must still run)."""
        delay = self.rng.uniform(low_s, high_s)
        time.sleep(delay)
        assert proc.alive, f"{proc.name} ended before its kill:\n{proc.log_tail()}"
        os.kill(proc.popen.pid, signal.SIGKILL)
        t_s = time.time()
        proc.popen.wait(timeout=10)
        return self._log(Kill(case, proc.name, proc.popen.pid, round(delay, 3), t_s))

    def kill_pid_at(self, case: str, name: str, pid: int, low_s: float, high_s: float) -> Kill:
        """``kill_at`` for a process that is not this lab's child (a PX4 that ``start.sh`` started):
        SIGKILL ``pid``, then wait until it is gone (or a zombie)."""
        delay = self.rng.uniform(low_s, high_s)
        time.sleep(delay)
        assert _running(pid), f"{name} (pid {pid}) ended before its kill"
        os.kill(pid, signal.SIGKILL)
        t_s = time.time()
        assert poll(lambda: not _running(pid), 10, period_s=0.05), f"{name} (pid {pid}) outlived its SIGKILL"
        return self._log(Kill(case, name, pid, round(delay, 3), t_s))

    def _log(self, kill: Kill) -> Kill:
        self.kills.append(kill)
        line = json.dumps(kill.__dict__ | {"seed": self.seed})
        print(f"fault: {line}")
        with open(self.path, "a") as fh:
            fh.write(line + "\n")
        return kill

    def of(self, case: str) -> Kill:
        """The kill of ``case`` (the flight must have reached it)."""
        got = [k for k in self.kills if k.case == case]
        assert got, f"the flight never killed {case!r} (kills: {[k.case for k in self.kills]})"
        return got[0]


@dataclass(frozen=True)
class Duct:
    """What a flight is judged against (``FaultLab.duct``)."""

    ref: Any
    """The built-in reference (``cd_nozzle_inviscid``) the lab's map is fitted from."""
    wall: Any
    """Its real wall (``duct_wall_from_reference``)."""
    scale: float
    """The map's speed scale."""
    outlet_x_m: float
    """The map's outlet plane (map frame): past it an agent's HOLD is its exit's [m]."""


def _running(pid: int) -> bool:
    """``pid`` exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def router_configs(lab: "FaultLab") -> tuple[int, Path, Path]:
    """The field set-up of docs/zenoh.md on loopback: a router config listening on a free port and
    a client config connecting to it, no gossip nor multicast (nothing bypasses the router).
    Returns (the port, router.json5, client.json5) in the lab's directory."""
    port = free_tcp_port()
    router = lab.dir / "router.json5"
    router.write_text(json.dumps({"mode": "router", "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
                                  "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}))
    client = lab.dir / "client.json5"
    client.write_text(json.dumps({"mode": "client", "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
                                  "scouting": {"multicast": {"enabled": False}}}))
    return port, router, client


class FaultLab:
    """One fault-injection flight's directory, map, keys, lab port, children and kills."""

    def __init__(self, root: Path, swarm: str) -> None:
        self.dir, self.swarm = root, swarm
        self.procs = Processes(root / "logs")
        self.port = free_tcp_port()
        seed = int(os.environ.get(SEED_ENV, DEFAULT_SEED))
        self.kills = KillLog(seed, root / "kills.jsonl")
        print(f"fault lab {swarm}: seed {seed} ({SEED_ENV}), lab port {self.port}, logs {root / 'logs'}")
        self.key, self.pub, self.map = root / "ground.key", root / "ground.pub", root / "tunnel.fiscmap"
        self.sha = ""

    def duct(self) -> "Duct":
        """The signed map's duct as the PX4 flights judge it: the built-in reference it was fitted from,
        the wall derived from it, the map's speed scale and its outlet plane."""
        from fisc_agent.map.codec import load_map
        from fisc_ground.maps.duct_wall import duct_wall_from_reference
        from fisc_ground.reference.builtin import load_builtin

        ref, m = load_builtin("cd_nozzle_inviscid"), load_map(self.map, self.pub)
        outlet_x_m = float(m["cv_center_m"][:, 0].max() + 0.5 * m.cell_size_m)
        return Duct(ref, duct_wall_from_reference(ref), m.scale, outlet_x_m)

    def prepare(self) -> None:
        """Key pair and the signed built-in tunnel (15 m, 560 CVs, default speeds: the agents' 5 m/s
        limit clamps none of its commands; ~1 s)."""
        ok(run_cli(ground("keygen", "-o", self.dir / "ground")))
        ok(run_cli(ground("fit", "cd_nozzle_inviscid", "-o", self.map, "--sign", self.key)))
        info = json.loads(ok(run_cli(ground("inspect", self.map, "--json", "--compact", "--trusted-key", self.pub))))
        self.sha = info["sha256"]

    def start(self, name: str, argv: list) -> Proc:
        """A long-running child on this lab's port."""
        with self._on_lab_port():
            return self.procs.start(name, argv)

    def run(self, argv: list, timeout_s: float = 60.0):
        """A short command on this lab's port, to completion (``run_cli``)."""
        with self._on_lab_port():
            return run_cli(argv, timeout_s=timeout_s)

    @contextlib.contextmanager
    def _on_lab_port(self):
        previous = os.environ.get(PORT_ENV)
        os.environ[PORT_ENV] = str(self.port)  # the children inherit os.environ
        try:
            yield
        finally:
            if previous is None:
                del os.environ[PORT_ENV]
            else:
                os.environ[PORT_ENV] = previous

    def monitor(self, name: str, record: Path, *extra) -> Proc:
        """``fisc-ground monitor`` on the map file, recording to ``record``; ``interrupt`` ends it
        cleanly (its MCAP log closed)."""
        return self.start(name, SIGINT_DEFAULT + ground("monitor", "--swarm", self.swarm, "--map", self.map,
                                                        "--record", record, "--sample-period", "0.5",
                                                        "--stale-after", "3", *extra))

    @staticmethod
    def interrupt(proc: Proc, timeout_s: float = 30.0) -> int:
        """Ctrl-C ``proc`` and wait for it to end; its exit code."""
        os.kill(proc.popen.pid, signal.SIGINT)
        return proc.popen.wait(timeout=timeout_s)

    def start_vehicle(self, agent_id: int, east_m: float, *zenoh) -> tuple[Proc, Proc]:
        """A stand-alone PX4 emulator on the ground and the agent that flies it (``--go``)."""
        port = free_udp_port()
        autopilot = self.start(f"autopilot-{agent_id}", cli("fisc-sim") + [
            "autopilot", "--mavlink", f"udpin:127.0.0.1:{port}", "--personality", "px4",
            f"--start=-3,{east_m},0", "--sysid", agent_id])
        agent = self.start(f"agent-{agent_id}", cli("fisc-agent") + [
            "--swarm", self.swarm, "--trusted-key", self.pub, "--mavlink", f"udpout:127.0.0.1:{port}",
            "--id", agent_id, "--go", "--origin", "0,0,-4", "--exit-policy", "loop", "--join-speed", "3",
            "--telemetry-rate", "5", "--mode", "staggered", "--geofence", "return", *zenoh])
        return autopilot, agent

    def start_px4_agents(self, logs: list[Path], anchor: str, *zenoh) -> list[Proc]:
        """``fisc-agent --go`` for PX4 SITL instances 0..len(logs)-1 (udp 14540+i, ``--geodetic-anchor
        anchor``): one pass, then the exit's hold (``--exit-policy loop --laps 1``), flight log i in
        ``logs[i]``."""
        return [self.start(f"agent-{i}", cli("fisc-agent") + [
            "--go", "--swarm", self.swarm, "--trusted-key", self.pub, "--mavlink", f"udpin:0.0.0.0:{14540 + i}",
            "--id", i, "--autopilot", "px4", "--geodetic-anchor", anchor, "--exit-policy", "loop", "--laps", 1,
            "--flight-log", log, *zenoh]) for i, log in enumerate(logs)]

    def wait_in_air(self, agent: Proc, timeout_s: float) -> None:
        """Until the agent's log shows it joining or flowing (it commands its vehicle in OFFBOARD)."""
        assert poll(lambda: not agent.alive or "mission TAKEOFF -> JOIN" in agent.log_tail(400),
                    timeout_s, period_s=0.5) and agent.alive, f"{agent.name} never took off\n{self.procs.report()}"

    def heard(self, zenoh_config: Path | None = None) -> set[int]:
        """Agent ids a ``status --wait 1`` on the lab port (or through ``zenoh_config``) hears now."""
        extra = ["--zenoh-config", zenoh_config] if zenoh_config is not None else []
        out = self.run(ground("status", "--swarm", self.swarm, "--wait", "1", "--json", *extra))
        return {a["id"] for a in json.loads(out.stdout)["agents"]} if out.returncode == 0 else set()

    def stop_all(self) -> None:
        """SIGTERM then SIGKILL every child still running (agents first)."""
        self.procs.stop_all(order=lambda p: 0 if p.name.startswith("agent") else 1)
