"""`fisc-ground publish | status | cmd | monitor | replay` as real processes on loopback."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from fisc_agent.zenoh.link import AgentZenohLink

from .conftest import snap, wait_for

pytestmark = pytest.mark.slow


def ground(*args, **kw):
    return [sys.executable, "-m", "fisc_ground.cli", *map(str, args)]


def test_cli_publish_status_cmd_monitor_replay(net, make_map, ground_key, tmp_path):
    hub, member = net
    map_path = tmp_path / "m.fiscmap"
    map_path.write_bytes(make_map(100))
    pub = subprocess.Popen(ground("publish", map_path, "--swarm", "alpha", "--zenoh-config", hub,
                                  "--announce-period", "0.3", "--duration", "60"),
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    maps, cmds = [], []
    link = AgentZenohLink(member, "alpha", 4, [ground_key[1]], False, maps.append, cmds.append)
    try:
        link.start()
        assert wait_for(lambda: maps, timeout_s=20), "agent never got the published map"
        link.start_telemetry(lambda: snap(position_map_m=(1.0, 0.1, 0.1), velocity_map_m_s=(3, 0, 0),
                                                 map_sha256=maps[-1].sha256), rate_hz=10)
        out = subprocess.run(ground("status", "--swarm", "alpha", "--zenoh-config", member, "--json", "--wait", "2"),
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        status = json.loads(out.stdout)
        agent = next(a for a in status["agents"] if a["id"] == 4)
        assert agent["state"] == "FLOW" and agent["map_sha256"] == maps[-1].sha256 and agent["last_seen_s"] < 5

        out = subprocess.run(ground("cmd", "hold", "--swarm", "alpha", "--zenoh-config", member,
                                    "--key", ground_key[2], "--ack-wait", "5"),
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        assert wait_for(lambda: [c.name for c in cmds] == ["hold"])
        assert json.loads(out.stdout.strip().splitlines()[-1])["acked"] == [4]

        rec = tmp_path / "r.mcap"
        out = subprocess.run(ground("monitor", "--swarm", "alpha", "--zenoh-config", member, "--record", rec,
                                    "--duration", "3", "--sample-period", "0.2"),
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        assert "0 dropped" in out.stdout
        out = subprocess.run(ground("replay", rec, "-o", tmp_path / "rep", "--min-samples", "1", "--no-figures"),
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        metrics = json.loads((tmp_path / "rep" / "metrics.json").read_text())
        assert metrics["agents"] == 1 and metrics["map"]["sha256"] == maps[-1].sha256

        # a newer map dropped in place of the file is served to the running agent
        map_path.write_bytes(make_map(200, seed=5))
        assert wait_for(lambda: [m.map_version for m in maps] == [100, 200], timeout_s=20)
    finally:
        link.close()
        pub.terminate()
        pub.wait(timeout=20)
