"""MAVProxy (headless) routes between the emulator and a pymavlink client that flies it."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from pymavlink import mavutil

from autopilot_testkit import Client

from ...ports import free_udp_port
from sim.autopilot.server import AutopilotEmulator
from ...optional import needs

ML = mavutil.mavlink
MAVPROXY = shutil.which("mavproxy.py") or str(Path(sys.executable).with_name("mavproxy.py"))


@pytest.mark.slow
@needs(Path(MAVPROXY).exists(), "MAVProxy (mavproxy.py)", extra="test")
def test_mavproxy_router_client_arms_and_flies(tmp_path):
    a, b = free_udp_port(), free_udp_port()
    proc = subprocess.Popen(
        [sys.executable, MAVPROXY, f"--master=udpin:127.0.0.1:{a}", f"--out=udpout:127.0.0.1:{b}",
         "--daemon", "--non-interactive", "--default-modules=", f"--state-basedir={tmp_path}"],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
    )  # fmt: skip
    em = AutopilotEmulator(f"udpout:127.0.0.1:{a}", personality="px4").start()
    c = Client(f"udpin:127.0.0.1:{b}")
    try:
        assert c.wait("HEARTBEAT", timeout=15.0).autopilot == ML.MAV_AUTOPILOT_PX4
        c.heartbeat()
        assert c.arm().result == ML.MAV_RESULT_ACCEPTED
        climb = c.streamer(1.0, 0.0, -1.5)
        c.run_for(0.5, climb)
        assert c.set_mode_px4(6, tick=climb).result == ML.MAV_RESULT_ACCEPTED
        c.run_for(2.0, climb)
        lp = c.wait("LOCAL_POSITION_NED", tick=climb)
        assert lp.x > 0.8 and lp.z < -1.0
        assert em.state.armed and em.state.position_ned_m[0] > 0.8
    finally:
        c.close()
        em.stop()
        proc.terminate()
        try:
            out = proc.communicate(timeout=10)[0]
        except subprocess.TimeoutExpired:
            proc.kill()
            out = proc.communicate()[0]
    assert b"Detected vehicle 1:1" in out
