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
