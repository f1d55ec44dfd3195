"""End-to-end: the agent over real UDP sockets on 127.0.0.1 against an autopilot.

Peers: the project's MAVLink autopilot emulator (``sim.autopilot.server``) for whole flights,
and the tiny fake in ``fake_autopilot.py`` for injected faults.
"""

from __future__ import annotations

import threading
import time

import pytest

from fake_autopilot import FakeAutopilot
from fisc_agent.config import AgentConfig
from fisc_agent.control import MapGeometry
from fisc_agent.frames import GeodeticAnchor
from fisc_agent.link import TYPEMASK_VELOCITY_ONLY, MavlinkLink
from fisc_agent.lookup import CommandField
from fisc_agent.mission import State
from fisc_agent.runner import Runner

pytestmark = pytest.mark.slow


class Flight:
    """Runs a Runner in a thread; records every snapshot."""

    def __init__(self, runner: Runner):
        self.runner = runner
        self.stop = threading.Event()
        self.track = []
        self.result = None
        self._t = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        orig = self.runner.step

        def step():
            out = orig()
            self.track.append(self.runner.snapshot())
            return out

        self.runner.step = step
        self.result = self.runner.run(self.stop)

    def __enter__(self):
        self._t.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self._t.join(timeout=10)
        self.runner.shutdown()

    def wait(self, pred, timeout_s, what):
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            snap = self.runner.snapshot()
            if snap is not None and pred(snap):
                return snap
            if not self._t.is_alive() and self.runner.mission.state == State.DONE:
                break
            time.sleep(0.02)
        m = self.runner.mission
        raise AssertionError(f"timeout waiting for {what}: {m.state} ({m.reason}); {m.transitions}")


def agent_cfg(url, **kw):
    base = dict(mavlink_url=url, agent_id=3, origin_ned_m=(0.0, 0.0, -4.0), takeoff_alt_m=1.0, max_speed_m_s=5.0,
                max_accel_m_s2=6.0, join_speed_m_s=3.0, climb_speed_m_s=2.0, exit_clearance_m=1.0)
    base.update(kw)
    return AgentConfig(**base)


def _visited(runner):
    """States visited, leaving out short stale-position holds that resumed by themselves (the
    emulator's plant JIT-compiles on the first airborne step and may stall its thread ~0.5 s)."""
    m = runner.mission
    out, trs = [m.transitions[0].src], m.transitions
    i = 0
    while i < len(trs):
        if (trs[i].reason == "position stale" and i + 1 < len(trs) and trs[i + 1].reason == "position fix back"
                and trs[i + 1].dst == trs[i].src):
            i += 2
            continue
        out.append(trs[i].dst)
        i += 1
    return out


def _check_flight(flight, cmap):
    geom = MapGeometry.from_field(CommandField.from_map(cmap))
    snaps = [s for s in flight.track if s is not None and s.position_map_m is not None]
    before = [s for s in snaps if s.state in ("TAKEOFF", "JOIN")]
    flow = [s for s in snaps if s.state == "FLOW"]
    # never inside the tunnel before entering it through the inlet
    assert not [s for s in before if geom.in_box(s.position_map_m) and s.position_map_m[0] > geom.x_inlet_m + 0.3]
    assert flow and all(s.cv_id >= 0 for s in flow)
    assert flow[0].position_map_m[0] < geom.x_inlet_m + geom.cell_size_m          # entered at the inlet
    assert flow[-1].position_map_m[0] > geom.x_outlet_m - geom.cell_size_m        # left at the outlet
    assert max(s.position_map_m[0] for s in snaps) > geom.x_outlet_m
    sps = [s.setpoint_map_m_s for s in snaps if s.setpoint_map_m_s is not None]
    assert max(sum(c * c for c in v) ** 0.5 for v in sps) <= flight.runner.cfg.max_speed_m_s + 1e-9


@pytest.mark.parametrize("personality", ["px4", "ardupilot"])
def test_emulated_autopilot_ground_to_inlet_through_the_tunnel_and_out(personality, tunnel_map):
    server = pytest.importorskip("sim.autopilot.server")
    if personality == "px4":
        mapbuild = pytest.importorskip("fisc_ground.mapbuild")
        cmap = mapbuild.build_default_map()          # the embedded default: 15 m nozzle
    else:
        cmap = tunnel_map                            # 3 m synthetic tunnel (keeps the test short)
    emu = server.AutopilotEmulator("udpin:127.0.0.1:0", personality=personality).start()
    try:
        # the mission's path through the tunnel, flown on the map's continuity-consistent field with
        # its look-ahead; the map's recommended `kinetic` mode adds random deviations that, at the
        # builder's 5 m/s, can carry a lagging vehicle across a staircase wall into the `hold`
        # geofence (docs/simulation.md, "Onboard"), which is not what this test is about
        mode = "staggered" if cmap.schema_version >= 2 else None
        cfg = agent_cfg(f"udpout:127.0.0.1:{emu.local_address[1]}", mode=mode)
        runner = Runner(cfg, MavlinkLink(cfg.mavlink_url), cmap)
        with Flight(runner) as f:
            f.wait(lambda s: s.state == "HOLD" and s.mode == "hold", 40, "exit hold")
            assert emu.state.mode.value == "loiter" and emu.state.armed
        assert _visited(runner) == [State.WAIT_POSITION, State.ARM, State.TAKEOFF, State.JOIN, State.FLOW,
                                    State.EXIT, State.HOLD], runner.mission.transitions
        assert runner.snapshot().autopilot == personality
        _check_flight(f, cmap)
    finally:
        emu.stop()


def _fake_flight(personality, port, **kw):
    fake = FakeAutopilot(f"udpout:127.0.0.1:{port}", personality, start_ned=(-3.0, 0.0, -2.0)).start()
    cfg = agent_cfg(f"udpin:127.0.0.1:{port}", **kw)
    return fake, Runner(cfg, MavlinkLink(cfg.mavlink_url))


def test_fake_records_velocity_only_local_ned_setpoints_at_the_rate(udp_port, tunnel_map):
    fake, runner = _fake_flight("px4", udp_port)
    runner.offer_map(tunnel_map)
    try:
        with Flight(runner) as f:
            f.wait(lambda s: s.state == "FLOW", 20, "FLOW")
        sps = fake.setpoints
        assert sps and all(sp[4] == TYPEMASK_VELOCITY_ONLY == 0b0000110111000111 and sp[5] == 1 for sp in sps)
        ts = [sp[0] for sp in sps]
        rate = (len(ts) - 1) / (ts[-1] - ts[0])
        assert 15.0 < rate < 25.0
        assert "offboard" in fake.modes_seen
    finally:
        fake.stop()


def test_position_dropout_holds_with_zero_velocity_then_autopilot_hold(udp_port, tunnel_map):
    fake, runner = _fake_flight("px4", udp_port, hold_grace_s=1.0)
    runner.offer_map(tunnel_map)
    try:
        with Flight(runner) as f:
            f.wait(lambda s: s.state == "JOIN" and s.mode == "offboard", 15, "JOIN in offboard")
            fake.drop_position = True
            f.wait(lambda s: s.state == "HOLD", 3, "stale hold")
            time.sleep(0.5)
            assert fake.setpoints[-1][1:4] == (0.0, 0.0, 0.0)
            f.wait(lambda s: s.mode == "hold", 4, "autopilot hold mode")
            assert fake.mode == "hold"
            assert runner.mission.reason == "position stale"
    finally:
        fake.stop()


def test_link_loss_is_detected_and_the_autopilot_failsafe_takes_over(udp_port, tunnel_map):
    fake, runner = _fake_flight("px4", udp_port)
    runner.offer_map(tunnel_map)
    try:
        with Flight(runner) as f:
            f.wait(lambda s: s.state == "JOIN" and s.mode == "offboard", 15, "JOIN in offboard")
            fake.mute = True
            snap = f.wait(lambda s: not s.link_ok, 5, "link lost")
            assert snap.heartbeat_age_s > runner.cfg.link_timeout_s
            f.wait(lambda s: s.state == "HOLD" and s.reason == "link lost", 2, "link-lost hold")
            assert fake.mode == "hold"          # the autopilot's own offboard-loss failsafe
    finally:
        fake.stop()


def test_geodetic_anchor_positions_from_global_position_int(udp_port, tunnel_map):
    anchor_geo = GeodeticAnchor(47.3977, 8.5456, 488.0, 0.0)
    # map origin 5 m North, 2 m East, 4 m up of the fake's EKF origin, tunnel pointing East
    lat, lon, alt = anchor_geo.ned_to_geodetic(5.0, 2.0, -4.0)
    anchor = GeodeticAnchor(lat, lon, alt, 90.0)
    fake = FakeAutopilot(f"udpout:127.0.0.1:{udp_port}", "px4", start_ned=(3.0, -1.0, -2.0),
                         geo_origin=(47.3977, 8.5456, 488.0)).start()
    cfg = agent_cfg(f"udpin:127.0.0.1:{udp_port}", geodetic_anchor=anchor, origin_ned_m=(0.0, 0.0, -10.0))
    runner = Runner(cfg, MavlinkLink(cfg.mavlink_url, anchor=anchor), tunnel_map)
    try:
        with Flight(runner) as f:
            snap = f.wait(lambda s: s.position_map_m is not None, 5, "a position")
            # vehicle at NED (3,-1,-2): relative to the anchor (-2,-3,+2); tunnel axis along East
            assert snap.position_map_m == pytest.approx((-3.0, 2.0, -2.0), abs=0.05)
    finally:
        fake.stop()


def test_mavsdk_backend_flies_the_emulated_px4_through_the_tunnel(tunnel_map):
    server = pytest.importorskip("sim.autopilot.server")
    pytest.importorskip("mavsdk")
    from fisc_agent.mavsdk_backend import MavsdkLink

    emu = server.AutopilotEmulator("udpin:127.0.0.1:0", personality="px4").start()
    try:
        cfg = agent_cfg(f"udpout:127.0.0.1:{emu.local_address[1]}", backend="mavsdk")
        runner = Runner(cfg, MavsdkLink(cfg.mavlink_url), tunnel_map)
        with Flight(runner) as f:
            f.wait(lambda s: s.state == "HOLD" and s.mode == "hold", 40, "exit hold")
        assert emu.state.mode.value == "loiter"
        _check_flight(f, tunnel_map)
    finally:
        emu.stop()
