"""The Zenoh link wired to the real agent runner and the MAVLink autopilot emulator:
no map -> stays on the ground unarmed; map over Zenoh -> flies; fleet hold -> holds; telemetry."""

from __future__ import annotations

import threading
import time

import pytest

from fisc_agent.config import AgentConfig
from fisc_agent.mavlink.link import MavlinkLink
from fisc_agent.map.codec import encode_map
from fisc_agent.runner import Runner
from fisc_agent.zenoh.keys import Keys
from fisc_agent.zenoh.runner import connect_runner
from fisc_ground.zenoh.fleet import TelemetryListener, make_command, send_command
from fisc_ground.zenoh.publish import MapServer
from sim.autopilot import server as server_mod

from .conftest import wait_for

pytestmark = pytest.mark.slow



def short_tunnel(version: int, key: bytes) -> bytes:
    """A 3 m tunnel along +x (radius 1 m, l = 0.5 m) flowing at ~2 m/s."""
    import numpy as np

    from .conftest import map_parts

    meta, arrays = map_parts(version, nx=6, ny=4, nz=4, n_max=3)
    v = np.zeros_like(arrays["fit_velocity_m_s"])
    v[..., 0] = 2.0
    arrays.update(fit_velocity_m_s=v, fit_mean_velocity_m_s=v.mean(1), target_velocity_m_s=v.mean(1))
    meta.update(agent_mass_kg=1.0, max_speed_m_s=5.0)
    return encode_map(meta, arrays, key)


def test_runner_waits_for_the_zenoh_map_flies_it_and_obeys_hold(net, sessions, ground_key):
    hub, member = net
    emu = server_mod.AutopilotEmulator("udpin:127.0.0.1:0", personality="px4").start()
    stop = threading.Event()
    link = runner = th = None
    try:
        cfg = AgentConfig(mavlink_url=f"udpout:127.0.0.1:{emu.local_address[1]}", agent_id=3, go=True,
                          origin_ned_m=(0.0, 0.0, -4.0), takeoff_alt_m=1.0, join_speed_m_s=3.0, climb_speed_m_s=2.0,
                          max_accel_m_s2=6.0, exit_clearance_m=1.0)
        runner = Runner(cfg, MavlinkLink(cfg.mavlink_url))
        th = threading.Thread(target=runner.run, args=(stop,), daemon=True)
        th.start()
        link = connect_runner(runner, member, "alpha", [ground_key[1]], telemetry_rate_hz=10)
        ground = sessions(hub)
        listener = TelemetryListener(ground, Keys("fisc", "alpha"))
        assert wait_for(lambda: 3 in listener.snapshot(), timeout_s=15)
        time.sleep(1.0)
        assert listener.snapshot()[3][0].state == "WAIT_MAP" and not emu.state.armed
        server = MapServer(ground, "alpha", announce_period_s=0.3)
        cmap = server.serve(short_tunnel(10, ground_key[0]))
        assert wait_for(lambda: runner.snapshot().state in ("JOIN", "FLOW"), timeout_s=30)
        assert emu.state.armed
        tele = listener.snapshot()[3][0]
        assert tele.map_sha256 == cmap.sha256 and tele.map_version == 10
        res = send_command(ground, Keys("fisc", "alpha"), make_command("hold", "alpha"), ground_key[0],
                           ack_timeout_s=5, listener=listener)
        assert res.acked == (3,)
        assert wait_for(lambda: runner.snapshot().state == "HOLD", timeout_s=5)
        assert wait_for(lambda: listener.snapshot()[3][0].state == "HOLD", timeout_s=5)
        server.close()
        listener.close()
    finally:
        stop.set()
        if link is not None:
            link.close()
        if th is not None:
            th.join(timeout=10)
            runner.shutdown()
        emu.stop()


def test_an_agent_hears_its_neighbours_telemetry_for_the_safety_net(net, sessions, ground_key):
    """Two agents' links on real Zenoh sessions: agent 4's runner hears agent 5's position and
    velocity (its own is left out); with ``--safety-net off`` the runner hears no one."""
    from fisc_agent.zenoh.link import AgentZenohLink

    from .conftest import snap

    hub, member = net
    sessions(hub)
    links = []
    try:
        cfg = AgentConfig(mavlink_url="udpout:127.0.0.1:9", agent_id=4)
        runner = Runner(cfg, MavlinkLink(cfg.mavlink_url))
        deaf = Runner(AgentConfig(mavlink_url="udpout:127.0.0.1:9", agent_id=6, safety_net=None),
                      MavlinkLink(cfg.mavlink_url))
        links.append(connect_runner(runner, member, "alpha", [ground_key[1]], telemetry_rate_hz=10))
        links.append(connect_runner(deaf, member, "alpha", [ground_key[1]], telemetry_rate_hz=10))
        other = AgentZenohLink(member, "alpha", 5, [ground_key[1]], False, lambda m: True, lambda c: None).start()
        links.append(other)
        other.start_telemetry(lambda: snap(agent_id=5, position_map_m=(1.0, 0.5, -0.25), velocity_map_m_s=(1.5, 0, 0),
                                           position_age_s=0.05), rate_hz=10)
        assert wait_for(lambda: 5 in runner.neighbours.reports(4).ids, timeout_s=15)
        rep = runner.neighbours.reports(4)
        assert list(rep.ids) == [5]  # not itself (agent 4 publishes too, with no position yet: dropped)
        assert rep.position_m[0] == pytest.approx((1.0, 0.5, -0.25)) and rep.velocity_m_s[0][0] == pytest.approx(1.5)
        assert 0.05 <= rep.age_s[0] < 1.0
        assert deaf.neighbours is None
    finally:
        for link in links:
            link.close()
