"""``fisc-ground router``: config errors name the problem; a real router process carries a
swarm between lab-default processes and client-mode ones."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from fisc_ground.zenoh.router import router_config

from .conftest import free_port, listening, snap, wait_for


def test_router_config_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.json5"):
        router_config(tmp_path / "missing.json5")
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: ")
    with pytest.raises(ValueError, match="bad.json5: invalid Zenoh config"):
        router_config(bad)
    peer = tmp_path / "peer.json5"
    peer.write_text('{ mode: "peer" }')
    with pytest.raises(ValueError, match='peer.json5: mode is "peer"; fisc-ground router needs mode "router"'):
        router_config(peer)
    with pytest.raises(ValueError, match="--listen or --config"):
        router_config(peer, ["tcp/127.0.0.1:0"])
    no_mode = tmp_path / "plain.json5"
    no_mode.write_text('{ listen: { endpoints: ["tcp/127.0.0.1:0"] } }')
    assert router_config(no_mode).get_json("mode") == '"router"'


@pytest.mark.slow
def test_router_process_connects_a_lab_agent_and_a_client_status(tmp_path):
    from fisc_agent.zenoh.link import AgentZenohLink
    from fisc_agent.zenoh.session import PORT_ENV, LabDiscovery, open_lab_session

    port = free_port()
    env = {**os.environ, PORT_ENV: str(port)}
    router = subprocess.Popen([sys.executable, "-m", "fisc_ground.cli", "router", "--duration", "60"], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    session = link = None
    try:
        assert wait_for(lambda: listening(port), timeout_s=20), "the router never listened on the lab port"
        # a lab-default agent finds the port taken by the router and connects to it
        session = open_lab_session(LabDiscovery(port=port))
        assert wait_for(lambda: len(list(session.info.routers_zid())) == 1, timeout_s=10)
        link = AgentZenohLink(None, "rt", 9, None, True, lambda m: None, lambda c: None, session=session).start()
        link.start_telemetry(lambda: snap(agent_id=9, position_map_m=(1.0, 0.0, 0.0)), rate_hz=10)
        client = tmp_path / "client.json5"
        client.write_text(json.dumps({"mode": "client", "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]}}))
        out = subprocess.run([sys.executable, "-m", "fisc_ground.cli", "status", "--swarm", "rt", "--zenoh-config",
                              client, "--json", "--wait", "3"], capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        assert [a["id"] for a in json.loads(out.stdout)["agents"]] == [9], out.stdout
        # a second router on the same port fails with a message naming the endpoint
        again = subprocess.run([sys.executable, "-m", "fisc_ground.cli", "router", "--duration", "1"], env=env,
                               capture_output=True, text=True, timeout=60)
        assert again.returncode != 0 and f"tcp/127.0.0.1:{port}" in again.stderr, again.stderr
    finally:
        if link is not None:
            link.close()
        if session is not None:
            session.close()
        router.terminate()
        router.communicate(timeout=20)
