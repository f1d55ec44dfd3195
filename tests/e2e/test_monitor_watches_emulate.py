"""The ground-station monitor shows density and pressure while ``fisc-sim emulate`` flies.

Real processes: ``fisc-ground monitor`` (the Zenoh hub of this test, listening on a free
loopback port) records the telemetry that the emulated swarm's agents publish
(``fisc-sim emulate --swarm``); ``fisc-ground replay`` turns the recording into per-CV fields.
"""

from __future__ import annotations

import csv
import json
import math

import pytest

from .conftest import Processes, cli, free_tcp_port, poll, run_cli, write_zenoh_config

pytestmark = pytest.mark.slow

SWARM = "emu"
AGENTS = 3


def test_monitor_records_the_emulated_swarm_and_replay_gives_density_and_pressure(tmp_path):
    port = free_tcp_port()
    hub = write_zenoh_config(tmp_path / "hub.json5", [f"tcp/127.0.0.1:{port}"], [])
    member = write_zenoh_config(tmp_path / "member.json5", ["tcp/127.0.0.1:0"], [f"tcp/127.0.0.1:{port}"])
    map_path = tmp_path / "tunnel.fiscmap"
    assert run_cli(cli("fisc-ground") + ["keygen", "-o", tmp_path / "ground"]).returncode == 0
    fit = run_cli(cli("fisc-ground") + ["fit", "cd_nozzle_inviscid", "-o", map_path, "--max-speed", "8",
                                        "--sign", tmp_path / "ground.key"])
    assert fit.returncode == 0, fit.stderr

    procs = Processes(tmp_path / "logs")
    try:
        rec = tmp_path / "emu.mcap"
        monitor = procs.start("monitor", cli("fisc-ground") + [
            "monitor", "--swarm", SWARM, "--zenoh-config", hub, "--map", map_path, "--record", rec,
            "--duration", "40", "--sample-period", "0.2"])
        emulate = run_cli(cli("fisc-sim") + [
            "emulate", "--map", map_path, "--agents", AGENTS, "--duration", "30", "--swarm", SWARM,
            "--zenoh-config", member, "--trusted-key", tmp_path / "ground.pub", "--no-compare", "--no-figures", "-q", "-o", tmp_path / "emu"], timeout_s=150)
        assert emulate.returncode == 0, emulate.stderr[-3000:]
        assert poll(lambda: not monitor.alive, 60), procs.report()
        assert monitor.popen.returncode == 0, procs.report()
    finally:
        procs.stop_all()

    rep = tmp_path / "replay"
    replay = run_cli(cli("fisc-ground") + ["replay", rec, "-o", rep, "--min-samples", "1", "--no-figures"])
    assert replay.returncode == 0, replay.stderr
    metrics = json.loads((rep / "metrics.json").read_text())
    assert metrics["agents"] == AGENTS and metrics["bad_messages"] == 0, metrics
    with open(rep / "fields.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    visited = [r for r in rows if int(r["samples"]) > 0]
    assert len(visited) >= 5, "the emulated agents' telemetry placed them in too few CVs"
    assert all(float(r["swarm_density"]) > 0 and math.isfinite(float(r["swarm_pressure"])) for r in visited)
    # the values, not only their sign: density = mean agent count x 1 kg / l^3 (l = 0.5 m); the
    # internal pressure lies between the random pressure and the kinetic P_s; the reported
    # swarm_pressure is the dispersion pressure, a column of its own
    for r in visited:
        assert float(r["swarm_density"]) == pytest.approx(float(r["swarm_count"]) * 1.0 / 0.5 ** 3, rel=1e-12)
        kin, internal, rand = (float(r[k]) for k in ("swarm_pressure_kinetic", "swarm_pressure_internal",
                                                     "swarm_pressure_random"))
        assert rand <= internal * (1 + 1e-9) + 1e-12 and internal <= kin * (1 + 1e-9)
    assert any(float(r["swarm_pressure"]) != pytest.approx(float(r["swarm_pressure_kinetic"])) for r in visited)
