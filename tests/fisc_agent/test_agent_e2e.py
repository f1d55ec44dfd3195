"""End-to-end: the agent over real UDP sockets on 127.0.0.1 against an autopilot.

Peer: the project's MAVLink autopilot emulator (``sim.autopilot.server``), for whole flights and,
through ``agent_testkit.EmulatorProbe``, for injected faults (position loss, link loss).
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from agent_testkit import EmulatorProbe
from fisc_agent.config import AgentConfig
from fisc_agent.flight.control import MapGeometry
from fisc_agent.flight.frames import GeodeticAnchor
from fisc_agent.mavlink.link import TYPEMASK_VELOCITY_ONLY, MavlinkLink
from fisc_agent.map.lookup import CommandField
from fisc_agent.flight.mission import State
from fisc_agent.runner import Runner
from fisc_ground.fields.flight_score import realised_spread_ratio
from fisc_ground.maps.build import build_default_map
from sim.autopilot import server
from ..optional import require_module
from ..sitl_groups import SITL_GROUP

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
    base = dict(mavlink_url=url, agent_id=3, go=True, entry_stagger_s=0.0, origin_ned_m=(0.0, 0.0, -4.0), takeoff_alt_m=1.0, max_speed_m_s=5.0,
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
    if personality == "px4":
        cmap = build_default_map()          # the embedded default: 15 m nozzle
    else:
        cmap = tunnel_map                            # 3 m synthetic tunnel (keeps the test short)
    emu = server.AutopilotEmulator("udpin:127.0.0.1:0", personality=personality).start()
    try:
        # the mission's path through the tunnel, flown on the map's continuity-consistent field with
        # its look-ahead; the map's recommended `kinetic` mode adds random deviations that, at the
        # builder's 5 m/s, can carry a lagging vehicle across a staircase wall into the `hold`
        # geofence (docs/designed_density.md, "Onboard"), which is not what this test is about
        mode = "staggered" if cmap.schema_version >= 2 else None
        cfg = agent_cfg(f"udpout:127.0.0.1:{emu.local_address[1]}", mode=mode)
        runner = Runner(cfg, MavlinkLink(cfg.mavlink_url), cmap)
        with Flight(runner) as f:
            f.wait(lambda s: s.state == "HOLD" and s.mode == "hold", 40, "exit hold")
            assert emu.state.mode.value == {"px4": "loiter", "ardupilot": "brake"}[personality] and emu.state.armed
        assert _visited(runner) == [State.WAIT_POSITION, State.ARM, State.TAKEOFF, State.JOIN, State.FLOW,
                                    State.EXIT, State.HOLD], runner.mission.transitions
        assert runner.snapshot().autopilot == personality
        _check_flight(f, cmap)
    finally:
        emu.stop()


# one pass over a real-time link: under -n 2, run beside the SITL flights, it read 0.48; in their group it runs
# alone on its worker (the other one has finished the fast tests by then)
@pytest.mark.xdist_group(SITL_GROUP)
def test_explicit_kinetic_mode_under_streamline_tracking_flies_the_fitted_spread():
    """``--mode kinetic`` with tracking: the vehicle flies the map's deviations (the swarm's pressure),
    about the fitted spread, where the field alone leaves only its tracking error (~0.1-0.5)."""
    cmap = build_default_map()
    emu = server.AutopilotEmulator("udpin:127.0.0.1:0", personality="px4").start()
    try:
        cfg = agent_cfg(f"udpout:127.0.0.1:{emu.local_address[1]}", mode="kinetic", geofence="return")
        runner = Runner(cfg, MavlinkLink(cfg.mavlink_url), cmap)
        with Flight(runner) as f:
            f.wait(lambda s: s.state in ("EXIT", "HOLD"), 60, "the outlet")
        flow = [s for s in f.track if s.state == "FLOW" and s.velocity_map_m_s is not None]
        pos = np.array([s.position_map_m for s in flow])
        vel = np.array([s.velocity_map_m_s for s in flow])
        ratio = realised_spread_ratio(pos, vel, np.array(["FLOW"] * len(flow)), CommandField.from_map(cmap))
        # one pass over a real-time UDP link: 0.58-0.76 in six runs (2026-12-07, before and after that day's
        # final-leg change; a CI run failed at 0.58 against a bound of 0.6); the field alone leaves 0.1-0.5
        assert 0.55 <= ratio <= 1.4, ratio
        assert pos[:, 0].max() > MapGeometry.from_field(CommandField.from_map(cmap)).x_outlet_m - cmap.cell_size_m
    finally:
        emu.stop()


PX4_HOLD = (4.0, 3.0)  # DO_SET_MODE param2/param3 of AUTO.LOITER ("Hold")
PX4_OFFBOARD = (6.0, 0.0)


def _emulated_flight(personality, port, start_ned=(-3.0, 0.0, 0.0), home_lla=None, **kw):
    """The project's emulator sending to the agent's udpin port, with a probe on what it receives."""
    extra = {} if home_lla is None else {"home_lla": home_lla}
    emu = server.AutopilotEmulator(f"udpout:127.0.0.1:{port}", personality=personality, start_ned=start_ned,
                                   **extra).start()
    cfg = agent_cfg(f"udpin:127.0.0.1:{port}", **kw)
    return emu, EmulatorProbe(emu), Runner(cfg, MavlinkLink(cfg.mavlink_url))


def _mode_requests(probe, since_s, mode):
    return [c for c in probe.commands_since(since_s) if c[1] == 176 and (c[2][1], c[2][2]) == mode]


def test_setpoints_are_velocity_only_local_ned_at_the_rate(udp_port, tunnel_map):
    emu, probe, runner = _emulated_flight("px4", udp_port)
    runner.offer_map(tunnel_map)
    try:
        with Flight(runner) as f:
            f.wait(lambda s: s.state == "FLOW", 20, "FLOW")
            assert emu.state.mode.value == "offboard"      # the emulator accepted the agent's OFFBOARD
            t0 = emu.time_s
            time.sleep(1.0)
            sps = probe.setpoints_since(t0)
        assert sps and all(sp[4] == TYPEMASK_VELOCITY_ONLY == 0b0000110111000111 and sp[5] == 1 for sp in sps)
        ts = [sp[0] for sp in sps]
        rate = (len(ts) - 1) / (ts[-1] - ts[0])
        assert 15.0 < rate < 25.0, rate
        assert max(b - a for a, b in zip(ts, ts[1:])) < 0.25
    finally:
        emu.stop()


def test_position_dropout_holds_with_zero_velocity_then_requests_the_autopilot_hold(udp_port, tunnel_map):
    emu, probe, runner = _emulated_flight("px4", udp_port, hold_grace_s=1.0)
    runner.offer_map(tunnel_map)
    try:
        with Flight(runner) as f:
            f.wait(lambda s: s.state == "JOIN" and s.mode == "offboard", 15, "JOIN in offboard")
            t0 = emu.time_s
            probe.drop_position()
            f.wait(lambda s: s.state == "HOLD", 3, "stale hold")
            t_stale = emu.time_s
            assert runner.mission.reason == "position stale"
            f.wait(lambda s: s.mode == "hold", 5, "autopilot hold mode")
            t_hold = emu.time_s
        requests = _mode_requests(probe, t0, PX4_HOLD)
        assert requests, "the agent never asked the autopilot for its hold mode"
        sps = [sp for sp in probe.setpoints_since(t0) if sp[0] <= requests[0][0]]
        # the agent streamed (zero) setpoints right up to its hold request: the hold is the agent's
        # escalation, not the autopilot's offboard-loss failsafe (COM_OF_LOSS_T = 1.0 s)
        gaps = [b[0] - a[0] for a, b in zip(sps, sps[1:])] + [requests[0][0] - sps[-1][0]]
        assert max(gaps) < 0.5, max(gaps)
        # after the agent's stale hold: the commanded speed ramps down (acceleration clamp) to zero
        speeds = [sum(c * c for c in sp[1:4]) ** 0.5 for sp in sps if sp[0] >= t_stale]
        assert all(b <= a + 1e-6 for a, b in zip(speeds, speeds[1:])), speeds
        settled = [sp for sp in sps if sp[0] > t_stale + 0.5]
        assert settled and all(sp[1:4] == (0.0, 0.0, 0.0) for sp in settled), settled[:3]
        assert emu.state.mode.value == "loiter" and emu.state.armed and t_hold >= requests[0][0]
    finally:
        emu.stop()


def test_link_loss_holds_latched_and_requests_hold_when_the_link_is_back(udp_port, tunnel_map):
    emu, probe, runner = _emulated_flight("px4", udp_port)
    runner.offer_map(tunnel_map)
    try:
        with Flight(runner) as f:
            f.wait(lambda s: s.state == "JOIN" and s.mode == "offboard", 15, "JOIN in offboard")
            probe.mute()
            snap = f.wait(lambda s: not s.link_ok, 5, "link lost")
            assert snap.heartbeat_age_s > runner.cfg.link_timeout_s
            f.wait(lambda s: s.state == "HOLD" and s.reason == "link lost", 2, "link-lost hold")
            t_back = emu.time_s
            probe.mute(False)
            f.wait(lambda s: s.link_ok, 5, "link back")
            f.wait(lambda s: s.mode == "hold", 5, "hold mode after the link came back")
            time.sleep(1.5)
            # latched: a link that comes back does not resume the flight by itself
            assert runner.mission.state == State.HOLD and runner.mission.reason == "link lost"
            assert runner.snapshot().state == "HOLD"
        assert not _mode_requests(probe, t_back, PX4_OFFBOARD), "resumed OFFBOARD without a fleet resume"
        moving = [sp for sp in probe.setpoints_since(t_back) if sp[1:4] != (0.0, 0.0, 0.0)]
        assert not moving, f"non-zero setpoints after the link came back: {moving[:3]}"
        assert emu.state.mode.value == "loiter" and emu.state.armed
    finally:
        emu.stop()


def test_geodetic_anchor_positions_from_global_position_int(udp_port, tunnel_map):
    anchor_geo = GeodeticAnchor(47.3977, 8.5456, 488.0, 0.0)
    # map origin 5 m North, 2 m East, 4 m up of the emulator's home, tunnel pointing East
    lat, lon, alt = anchor_geo.ned_to_geodetic(5.0, 2.0, -4.0)
    anchor = GeodeticAnchor(lat, lon, alt, 90.0)
    emu = server.AutopilotEmulator(f"udpout:127.0.0.1:{udp_port}", personality="px4", start_ned=(3.0, -1.0, -2.0),
                                   home_lla=(47.3977, 8.5456, 488.0)).start()
    cfg = agent_cfg(f"udpin:127.0.0.1:{udp_port}", geodetic_anchor=anchor, origin_ned_m=(0.0, 0.0, -10.0))
    runner = Runner(cfg, MavlinkLink(cfg.mavlink_url, anchor=anchor), tunnel_map)
    try:
        with Flight(runner) as f:
            snap = f.wait(lambda s: s.position_map_m is not None, 5, "a position")
            # vehicle at NED (3,-1,-2): relative to the anchor (-2,-3,+2); tunnel axis along East
            assert snap.position_map_m == pytest.approx((-3.0, 2.0, -2.0), abs=0.05)
    finally:
        emu.stop()


def test_mavsdk_backend_flies_the_emulated_px4_through_the_tunnel(tunnel_map):
    require_module("mavsdk", extra="mavsdk")  # an optional backend
    from fisc_agent.mavlink.mavsdk_backend import MavsdkLink

    emu = server.AutopilotEmulator("udpin:127.0.0.1:0", personality="px4").start()
    try:
        cfg = agent_cfg(f"udpout:127.0.0.1:{emu.local_address[1]}", backend="mavsdk")
        link = MavsdkLink(cfg.mavlink_url)
        runner = Runner(cfg, link, tunnel_map)
        gnss = []  # (the receiver's velocity as MAVSDK gave it, the emulated vehicle's, north-east) while it flows

        def flowed_to_the_exit_hold(s):
            g, v = link.latest_gnss_velocity(), emu.state.velocity_ned_m_s
            if s.state == "FLOW" and g is not None and math.hypot(v[0], v[1]) > 0.5:
                gnss.append((g.vel_ne_m_s, v[:2]))
            return s.state == "HOLD" and s.mode == "hold"

        with Flight(runner) as f:
            f.wait(flowed_to_the_exit_hold, 40, "exit hold")
        assert emu.state.mode.value == "loiter"
        _check_flight(f, tunnel_map)
        # MAVSDK's raw_gps reached the agent (10 Hz asked, read within 0.02 s of a 20 Hz physics step)
        assert len(gnss) > 20, gnss
        err = [math.dist(g, v) for g, v in gnss]
        assert np.median(err) < 0.1 and max(err) < 0.6, sorted(err)[-5:]
    finally:
        emu.stop()


def _wait_for(pred, timeout_s, what, poll=None):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if poll is not None:
            poll()
        if pred():
            return
        time.sleep(0.05)
    raise AssertionError(f"timeout waiting for {what}")


def _emulated_px4_and_link(backend: str):
    """An emulated PX4 on a free UDP port, and a link to it on ``backend`` (pymavlink, or the optional MAVSDK)."""
    if backend == "mavsdk":
        require_module("mavsdk", extra="mavsdk")
        from fisc_agent.mavlink.mavsdk_backend import MavsdkLink as link_type
    else:
        link_type = MavlinkLink
    emu = server.AutopilotEmulator("udpin:127.0.0.1:0", personality="px4").start()
    return emu, link_type(f"udpout:127.0.0.1:{emu.local_address[1]}")


@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
def test_the_mode_is_dated_by_the_heartbeat_alone_on_both_backends(backend):
    """``mode_t_s``, by which the Commander judges a request fresh, advances with the emulated PX4's 1 Hz
    HEARTBEAT only: not with the 50 Hz positions (MAVSDK's liveness, ``last_heartbeat_t``, does)."""
    from fisc_agent.mavlink.adapters import FRESH_HEARTBEAT_S, Px4Adapter

    emu, link = _emulated_px4_and_link(backend)

    def poll():
        link.poll()
        link.send_heartbeat()

    try:
        _wait_for(lambda: link.mode_t_s is not None and link.latest_position() is not None, 10, "the autopilot",
                  poll)
        link.use_adapter(Px4Adapter())
        stamps, ages, fix_ages = set(), [], []
        end = time.monotonic() + 3.5
        while time.monotonic() < end:
            poll()
            now = time.monotonic()
            stamps.add(link.mode_t_s)
            ages.append(now - link.mode_t_s)
            fix_ages.append(now - link.latest_position().t_s)
            time.sleep(0.02)
        assert 3 <= len(stamps) <= 5, sorted(stamps)            # 1 Hz over 3.5 s
        assert max(ages) > 0.8 > FRESH_HEARTBEAT_S, max(ages)   # stale between HEARTBEATs ...
        assert max(fix_ages) < FRESH_HEARTBEAT_S, max(fix_ages)  # ... while the fixes stream
    finally:
        link.close()
        emu.stop()


@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
def test_link_intents_move_the_emulated_px4(backend):
    """The VehicleLink's intents on both backends against the emulator over UDP: arm, hold, land
    change the vehicle's state and come back as accepted CommandResults (MAVSDK: its own actions)."""
    from fisc_agent.mavlink.adapters import CommandKind, ModeClass, Px4Adapter

    emu, link = _emulated_px4_and_link(backend)
    results = []

    def poll():
        link.poll()
        results.extend(link.pop_results())
        link.send_heartbeat()

    try:
        _wait_for(lambda: link.last_heartbeat_t is not None and link.autopilot == "px4", 10, "the autopilot", poll)
        link.use_adapter(Px4Adapter())
        _wait_for(lambda: link.mode != ModeClass.UNKNOWN, 5, "a mode", poll)
        assert not link.armed
        link.arm()
        _wait_for(lambda: link.armed, 5, "armed", poll)
        link.land()
        _wait_for(lambda: link.mode == ModeClass.LAND, 5, "LAND mode", poll)
        link.hold()
        _wait_for(lambda: link.mode == ModeClass.HOLD, 5, "hold mode", poll)
        assert emu.state.mode.value == "loiter"
        _wait_for(lambda: sum(r.kind == CommandKind.SET_MODE for r in results) >= 2, 5, "mode results", poll)
        ours = [r for r in results if r.kind in (CommandKind.ARM, CommandKind.SET_MODE)]
        assert [r.kind for r in ours] == [CommandKind.ARM, CommandKind.SET_MODE, CommandKind.SET_MODE]
        assert all(r.accepted for r in ours), ours
    finally:
        link.close()
        emu.stop()
