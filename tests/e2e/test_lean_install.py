"""The lean onboard install (issue 10 part 3): ``pip install fisc`` into a fresh venv has no scipy,
matplotlib or numba, its ``fisc-ground`` names the extra to install, and its ``fisc-agent`` flies the
project's emulator (``fisc-sim autopilot`` from the test environment) through a tunnel.

Needs the package registry (or pip's cache) for numpy, pymavlink, eclipse-zenoh and pynacl.
"""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import Processes, cli, free_udp_port, poll
from fisc_agent.flight.flightlog import read_flight_log

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
HEAVY = ("scipy", "matplotlib", "numba", "meshio", "rich", "dask", "foxglove", "mcap")
LEAN = ("numpy", "pymavlink", "zenoh", "nacl", "fisc_agent")


def _sh(argv: list, timeout_s: float = 600.0) -> subprocess.CompletedProcess:
    out = subprocess.run([str(a) for a in argv], capture_output=True, text=True, timeout=timeout_s)
    assert out.returncode == 0, f"{argv}\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"
    return out


@pytest.fixture(scope="module")
def lean_venv(tmp_path_factory) -> Path:
    """A fresh venv with the project installed from this worktree without any extra."""
    root = tmp_path_factory.mktemp("lean")
    src = root / "src"  # a clean copy: an in-tree build would leave build/ (and stale modules) in the worktree
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, src / name)
    for name in ("fisc_agent", "fisc_ground", "sim", "field_maps"):
        shutil.copytree(REPO / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    venv = root / "venv"
    _sh([sys.executable, "-m", "venv", venv])
    _sh([venv / "bin" / "python", "-m", "pip", "install", "-q", "--disable-pip-version-check", src], timeout_s=900)
    return venv


def test_lean_install_has_only_the_agent_dependencies(lean_venv):
    probe = ("import importlib.util as u, json; "
             f"print(json.dumps({{m: u.find_spec(m) is not None for m in {HEAVY + LEAN!r}}}))")
    found = eval(_sh([lean_venv / "bin" / "python", "-c", probe]).stdout.replace("true", "True")
                 .replace("false", "False"))
    assert not [m for m in HEAVY if found[m]], found
    assert all(found[m] for m in LEAN), found
    # the test environment does have them: the probe would see them
    assert importlib.util.find_spec("scipy") is not None


def test_lean_install_names_the_extra_for_ground_and_sim_commands(lean_venv, tmp_path):
    out = subprocess.run([lean_venv / "bin" / "fisc-ground", "fit", "cd_nozzle_inviscid", "-o", tmp_path / "m.fiscmap"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 1, out.stderr
    assert "pip install 'fisc[ground]'" in out.stderr and "Traceback" not in out.stderr, out.stderr
    assert not (tmp_path / "m.fiscmap").exists()
    out = subprocess.run([lean_venv / "bin" / "fisc-sim", "run", "--duration", "1", "-o", tmp_path / "run"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 1 and "pip install 'fisc[sim]'" in out.stderr and "Traceback" not in out.stderr, \
        out.stderr


def _tunnel_map(path: Path) -> Path:
    spec = importlib.util.spec_from_file_location("agent_testkit_lean", REPO / "tests/fisc_agent/agent_testkit.py")
    kit = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(kit)
    path.write_bytes(kit.tunnel_map_bytes())  # 3 m tunnel along +x, 2-2.4 m/s
    return path


def test_lean_agent_flies_the_emulator_through_the_tunnel(lean_venv, tmp_path):
    cmap = _tunnel_map(tmp_path / "tunnel.fiscmap")
    log = tmp_path / "flight.csv"
    port = free_udp_port()
    procs = Processes(tmp_path / "logs")
    try:
        emu = procs.start("autopilot", cli("fisc-sim") + ["autopilot", "--mavlink", f"udpin:127.0.0.1:{port}",
                                                          "--personality", "px4"])
        agent = procs.start("agent", [lean_venv / "bin" / "fisc-agent", "--go", "--map", cmap, "--mavlink",
                                      f"udpout:127.0.0.1:{port}", "--id", "1", "--origin", "0,0,-4",
                                      "--takeoff-alt", "1", "--climb-speed", "2", "--join-speed", "3",
                                      "--max-accel", "6", "--exit-policy", "hold", "--flight-log", log,
                                      "--max-duration", "90"])

        def crossed():
            if not log.exists():
                return False
            rows = read_flight_log(log)
            flow = [i for i, r in enumerate(rows) if r["state"] == "FLOW"]
            return bool(flow) and any(r["x_m"] and float(r["x_m"]) > 3.0 for r in rows[flow[0]:]) and \
                rows[-1]["state"] in ("EXIT", "HOLD")

        assert poll(crossed, 90, 0.5), procs.report(30)
        assert emu.alive and agent.alive, procs.report()
        assert procs.stop(agent) == 0, procs.report()
    finally:
        procs.stop_all()
    rows = read_flight_log(log)
    states = [r["state"] for r in rows]
    assert "FLOW" in states and states.index("FLOW") < max(i for i, s in enumerate(states) if s in ("EXIT", "HOLD"))
    inside = [float(r["y_m"]) ** 2 + float(r["z_m"]) ** 2 for r in rows if r["state"] == "FLOW"]
    assert max(inside) < 1.0  # flew inside the 1 m radius tunnel
