"""Runner on a simulated clock with an in-memory link: clamps on every setpoint, map swap,
fleet commands, snapshots, shutdown."""

import math

import pytest

from agent_testkit import RecordingVehicle, tunnel_map_bytes
from fisc_agent.mavlink.adapters import ModeClass
from fisc_agent.config import AgentConfig
from fisc_agent.flight.drag import DragConfig
from fisc_agent.mavlink.interfaces import ThrustAccel
from fisc_agent.mavlink.link import PositionSample, PositionSource, SetpointSink
from fisc_agent.map.codec import MapError, decode_map
from fisc_agent.flight.mission import HoldCause, State
from fisc_agent.flight.tick import AgentSnapshot
from fisc_agent.runner import Runner


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t

    def sleep(self, dt):
        self.t += dt


class MemoryLink(RecordingVehicle):
    """A PX4 that obeys commands at once; kinematic vehicle in local NED on the shared clock."""

    def __init__(self, clock, pos_ned=(0.0, 0.0, 0.0)):
        super().__init__()
        self.commands = self.sent    # the intents asked for
        self.clock = clock
        self.autopilot = "px4"
        self.armed = False
        self.vehicle_mode = ModeClass.OTHER   # POSCTL
        self.adapter = None
        self.last_heartbeat_t = None
        self.pos = list(pos_ned)
        self.vel = [0.0, 0.0, 0.0]
        self.setpoints = []          # (t, vn, ve, vd)
        self.accels = []             # (an, ae, ad) of each setpoint, None for a velocity-only one
        self.thrust = None           # the ThrustAccel latest_thrust_accel gives
        self.heartbeats_sent = 0
        self.closed = False
        self.freeze_position = False
        self._t = clock()
        self._fix = None

    def _respond(self, target, dt):
        """The velocity the vehicle flies for the commanded ``target`` (at once here)."""
        return list(target)

    def poll(self):
        now = self.clock()
        dt, self._t = now - self._t, now
        mode = self.vehicle_mode
        if mode == ModeClass.OFFBOARD and self.armed and self.setpoints:
            self.vel = self._respond(self.setpoints[-1][1:], dt)
        elif mode == ModeClass.LAND and self.armed:
            self.vel = [0.0, 0.0, 1.0]
            if self.pos[2] >= 0.0:
                self.armed = False
        else:
            self.vel = self._respond((0.0, 0.0, 0.0), dt)
        for i in range(3):
            self.pos[i] += self.vel[i] * dt
        self.pos[2] = min(self.pos[2], 0.0)
        self.last_heartbeat_t = now
        if not self.freeze_position:
            self._fix = PositionSample(now, tuple(self.pos), tuple(self.vel))
        return 1

    gnss = None
    """The GNSS velocity the link reports (``interfaces.GnssVelocity``), None: no receiver velocity."""

    def latest_gnss_velocity(self):
        return self.gnss

    def latest_thrust_accel(self):
        return self.thrust

    def latest_position(self):
        return self._fix

    def send_velocity_ned(self, vn, ve, vd):
        self.setpoints.append((self.clock(), vn, ve, vd))
        self.accels.append(None)

    def send_velocity_accel_ned(self, vn, ve, vd, an, ae, ad):
        self.setpoints.append((self.clock(), vn, ve, vd))
        self.accels.append((an, ae, ad))

    @property
    def mode(self):
        return self.vehicle_mode if self.adapter is not None and self.last_heartbeat_t is not None else ModeClass.UNKNOWN

    @property
    def mode_t_s(self):
        return self.last_heartbeat_t

    def use_adapter(self, adapter):
        self.adapter = adapter

    def arm(self):
        super().arm()
        self.armed = True

    def set_mode(self, mode):
        super().set_mode(mode)
        self.vehicle_mode = mode

    def send_heartbeat(self):
        self.heartbeats_sent += 1

    def pop_results(self):
        return []

    def close(self):
        self.closed = True


def make(link=MemoryLink, **kw):
    clock = Clock()
    base = dict(mavlink_url="udpin:0.0.0.0:14540", agent_id=1, go=True, origin_ned_m=(0.0, 0.0, -3.0), takeoff_alt_m=1.0,
                max_speed_m_s=3.0, max_accel_m_s2=2.0, join_speed_m_s=2.5, climb_speed_m_s=1.0)
    base.update(kw)
    cfg = AgentConfig(**base)
    link = link(clock)
    r = Runner(cfg, link, decode_map(tunnel_map_bytes()), clock=clock, sleep=clock.sleep, wall_clock=lambda: 1.7e9)
    return cfg, clock, link, r


def tick_until(r, clock, pred, max_s=60.0):
    end = clock.t + max_s
    while clock.t < end:
        r.step()
        clock.sleep(r.cfg.period_s)
        if pred():
            return
    raise AssertionError(f"timeout in {r.mission.state} ({r.mission.reason})")


def test_memory_link_satisfies_the_protocols():
    _, _, link, _ = make()
    assert isinstance(link, PositionSource) and isinstance(link, SetpointSink)


def test_full_pass_every_setpoint_is_clamped_and_velocity_only_transformed():
    cfg, clock, link, r = make()
    tick_until(r, clock, lambda: r.mission.state == State.HOLD)
    assert r.mission.laps == 1
    sps = link.setpoints
    assert len(sps) > 100
    prev = None
    for t, vn, ve, vd in sps:
        assert math.hypot(vn, ve, vd) <= cfg.max_speed_m_s + 1e-9
        if prev is not None and t - prev[0] < 1.5 * cfg.period_s:
            dv = math.dist((vn, ve, vd), prev[1:])
            assert dv <= cfg.max_accel_m_s2 * (t - prev[0]) + 1e-9
        prev = (t, vn, ve, vd)
    # PX4: the stream ran for >= 1 s before OFFBOARD was requested
    first_mode = next(c for c in link.commands if c[0] == "set_mode")
    assert first_mode == ("set_mode", ModeClass.OFFBOARD) and r.adapter.name == "px4"
    assert link.setpoints[0][0] <= 100.0 + 0.1
    assert link.heartbeats_sent >= 10


def test_snapshot_reports_state_position_map_and_link():
    cfg, clock, link, r = make()
    pre = r.snapshot()  # before the first tick: waiting on the ground, map known, no position
    assert pre.state == "WAIT_POSITION" and pre.position_map_m is None and pre.map_sha256 == r.cmap.sha256
    assert not (pre.armed or pre.link_ok or pre.failsafe or pre.outside_map)
    tick_until(r, clock, lambda: r.mission.state == State.FLOW)
    snap = r.snapshot()
    assert isinstance(snap, AgentSnapshot)
    assert snap.state == "FLOW" and snap.cv_id >= 0 and snap.link_ok and snap.armed and snap.mode == "offboard"
    assert snap.map_sha256 == r.cmap.sha256 and snap.map_version == 1 and snap.autopilot == "px4"
    # map frame = local NED through the deployment transform (origin 0,0,-3)
    assert snap.position_map_m == pytest.approx((link.pos[0], link.pos[1], -3.0 - link.pos[2]))
    assert snap.wall_time_s == 1.7e9 and snap.agent_id == 1
    with pytest.raises(AttributeError):
        snap.state = "X"


def test_offer_map_swaps_atomically_at_the_next_tick_and_refuses_older():
    cfg, clock, link, r = make()
    tick_until(r, clock, lambda: r.mission.state == State.JOIN)
    old = r.cmap
    newer = decode_map(tunnel_map_bytes(length_m=4.0, map_version=5))
    assert r.offer_map(newer)
    assert r.cmap is old                       # not before the tick
    r.step()
    assert r.cmap is newer and r.snapshot().map_version == 5
    assert r.offer_map(newer)                  # same map again: no-op
    assert not r.offer_map(decode_map(tunnel_map_bytes(map_version=2)))   # older
    assert not r.offer_map(decode_map(tunnel_map_bytes(length_m=5.0, map_version=5)))  # same version, other map
    assert r.offer_map(decode_map(tunnel_map_bytes(length_m=4.0, map_version=6)))       # one version up
    r.step()
    assert r.cmap.map_version == 6
    tick_until(r, clock, lambda: r.mission.state == State.EXIT)
    assert r.snapshot().position_map_m[0] >= 4.0


def test_offer_map_refuses_a_map_that_fails_agent_checks():
    import numpy as np
    from agent_testkit import tunnel_arrays
    from fisc_agent.map.codec import encode_map

    cfg, clock, link, r = make(mode="slot")
    meta, arrays = tunnel_arrays()
    arrays["n_star"] = np.zeros_like(arrays["n_star"])
    meta["map_version"] = 9
    assert not r.offer_map(decode_map(encode_map(meta, arrays)))
    with pytest.raises(MapError):
        Runner(cfg, MemoryLink(clock), decode_map(encode_map(meta, arrays)), clock=clock)


def test_fleet_commands_reach_the_mission():
    cfg, clock, link, r = make()
    tick_until(r, clock, lambda: r.mission.state == State.JOIN)
    r.fleet_command("hold")
    r.step()
    assert r.mission.state == State.HOLD and r.snapshot().setpoint_map_m_s is not None
    r.fleet_command("resume")
    r.step()
    assert r.mission.state == State.JOIN
    r.fleet_command("land")
    r.step()
    assert r.mission.state == State.LAND
    assert link.commands[-1] == ("set_mode", ModeClass.LAND)
    with pytest.raises(ValueError):
        r.fleet_command("selfdestruct")


def test_stale_position_streams_zero_then_requests_hold_mode():
    cfg, clock, link, r = make(hold_grace_s=1.0)
    tick_until(r, clock, lambda: r.mission.state == State.JOIN)
    link.freeze_position = True
    tick_until(r, clock, lambda: r.mission.state == State.HOLD, max_s=2)
    tick_until(r, clock, lambda: link.setpoints[-1][1:] == (0.0, 0.0, 0.0), max_s=2)  # ramps down (accel clamp)
    tick_until(r, clock, lambda: link.mode == ModeClass.HOLD, max_s=3)
    assert r.snapshot().position_age_s > cfg.stale_timeout_s + cfg.hold_grace_s


def test_run_keeps_the_rate_and_stops_when_done():
    cfg, clock, link, r = make(exit_policy="land")
    final = r.run(max_duration_s=120)
    assert final == State.DONE and r.mission.reason == "landed and disarmed"
    assert r.overruns == 0
    ts = [s[0] for s in link.setpoints]
    gaps = [b - a for a, b in zip(ts, ts[1:]) if b - a < 0.5]
    assert max(gaps) == pytest.approx(cfg.period_s) and min(gaps) == pytest.approx(cfg.period_s)


def test_shutdown_holds_a_flying_vehicle_and_closes():
    cfg, clock, link, r = make()
    tick_until(r, clock, lambda: r.mission.state == State.FLOW)
    r.shutdown()
    assert link.setpoints[-1][1:] == (0.0, 0.0, 0.0)
    assert link.mode == ModeClass.HOLD and link.commands[-1] == ("set_mode", ModeClass.HOLD)
    assert link.closed


class StoppedMidTickLink(MemoryLink):
    """The agent is stopped (SIGSTOP) inside a tick, after it read its clock: the clock jumps by
    ``stop_s`` during the next poll, once."""

    stop_s = 0.0

    def poll(self):
        n = super().poll()
        if self.stop_s:
            self.clock.t += self.stop_s
            self.stop_s = 0.0
        return n


@pytest.mark.parametrize("stop_s, sent", [(3.0, True), (3.0 + 1e-6, False), (6.0, False)])
def test_a_tick_stopped_mid_way_past_the_link_timeout_sends_nothing(stop_s, sent):
    """PX4 SITL under load: the agent frozen between reading its clock and sending sent that tick's setpoint
    after the freeze, over PX4's offboard-loss Land, and PX4 took OFFBOARD back.  Stopped longer than
    ``link_timeout_s`` (3 s) within a tick, it sends neither setpoint nor command; the next tick finds the stall."""
    cfg, clock, link, r = make(link=StoppedMidTickLink)
    tick_until(r, clock, lambda: r.mission.state == State.FLOW)
    assert cfg.link_timeout_s == 3.0
    n_sp, n_cmd = len(link.setpoints), len(link.commands)
    link.stop_s = stop_s
    r.step()
    assert (len(link.setpoints) == n_sp + 1) == sent and len(link.commands) == n_cmd


@pytest.mark.parametrize("mode, age_s, holds", [(ModeClass.OFFBOARD, 3.0, True), (ModeClass.OFFBOARD, 3.0 + 1e-6, False),
                                                (ModeClass.LAND, 0.0, False), (ModeClass.OTHER, 0.0, False),
                                                (ModeClass.HOLD, 0.0, False)])
def test_shutdown_touches_only_a_vehicle_heard_afresh_flying_the_agents_setpoints(mode, age_s, holds):
    """A HEARTBEAT older than the link timeout (the agent stalled, the link cut: an autopilot failsafe may be
    landing the vehicle), or a mode not the agent's: shutdown sends nothing."""
    cfg, clock, link, r = make()
    tick_until(r, clock, lambda: r.mission.state == State.FLOW)
    link.vehicle_mode = mode
    link.poll = lambda: 0                        # nothing more heard
    link.last_heartbeat_t = clock.t - age_s
    n_sp, n_cmd = len(link.setpoints), len(link.commands)
    r.shutdown()
    assert (len(link.setpoints) > n_sp) == holds and (len(link.commands) > n_cmd) == holds
    assert link.closed


def test_shutdown_on_the_ground_sends_nothing():
    cfg, clock, link, r = make()
    r.step()
    n = len(link.commands)
    r.shutdown()
    assert len(link.commands) == n and link.closed


def test_map_offers_and_fleet_commands_from_another_thread_while_running():
    import threading
    import time

    cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=1, go=True, origin_ned_m=(0.0, 0.0, -3.0), rate_hz=50.0)
    link = MemoryLink(time.monotonic)
    r = Runner(cfg, link, decode_map(tunnel_map_bytes()))
    stop = threading.Event()
    th = threading.Thread(target=r.run, args=(stop,), daemon=True)
    th.start()
    try:
        newer = decode_map(tunnel_map_bytes(length_m=4.0, map_version=7))
        results = []
        offers = [threading.Thread(target=lambda: results.append(r.offer_map(newer))) for _ in range(4)]
        for t in offers:
            t.start()
        for t in offers:
            t.join()
        assert all(results)
        r.fleet_command("hold")
        end = time.monotonic() + 3
        while time.monotonic() < end:
            snap = r.snapshot()
            if snap is not None and snap.map_version == 7 and snap.state == "HOLD":
                break
            time.sleep(0.02)
        assert snap.map_version == 7 and snap.state == "HOLD" and snap.reason.startswith("fleet hold")
    finally:
        stop.set()
        th.join(timeout=2)
    assert not th.is_alive()


def test_runner_gates_fixes_of_any_backend_non_finite_and_implausible_never_reach_the_mission():
    """Issue 12 finding 3 (any backend: the runner gates what ``latest_position`` returns): a NaN
    or inf fix used to raise in the mission; a fix 1 km away ended the pass."""
    cfg, clock, link, r = make()
    tick_until(r, clock, lambda: r.mission.state == State.FLOW)
    sent = len(link.setpoints)
    for bad in ((math.nan, 0.0, -3.0), (math.inf, 0.0, -3.0), (link.pos[0] + 1000.0, link.pos[1], link.pos[2])):
        link.freeze_position = True
        link._fix = PositionSample(clock(), bad, (0.0, 0.0, 0.0))
        out = r.step()
        clock.sleep(cfg.period_s)
        link.freeze_position = False
        assert out.state == State.FLOW and math.isfinite(r.snapshot().position_map_m[0])
    assert len(link.setpoints) == sent + 3
    assert r.rlog.count("position:non_finite") == 2 and r.rlog.count("position:implausible_jump") == 1
    tick_until(r, clock, lambda: len(link.setpoints) > sent + 20, max_s=5.0)
    assert r.mission.state not in (State.HOLD, State.DONE), r.mission.transitions[-3:]


class LaggingLink(MemoryLink):
    """A vehicle with a first-order velocity lag whose autopilot takes ``mode_delay_s`` to enter a
    mode it is asked for (PX4 wants a setpoint stream before it takes OFFBOARD) and hovers meanwhile."""

    lag_s = 0.5
    mode_delay_s = 1.5

    def __init__(self, clock):
        super().__init__(clock)
        self._pending = None

    def set_mode(self, mode):
        self.commands.append(("set_mode", mode))
        if mode != self.vehicle_mode and (self._pending is None or self._pending[1] != mode):
            self._pending = (self.clock() + self.mode_delay_s, mode)  # repeated requests do not restart it

    def _respond(self, target, dt):
        k = min(1.0, dt / self.lag_s)
        return [v + k * (s - v) for v, s in zip(self.vel, target)]

    def poll(self):
        if self._pending is not None and self.clock() >= self._pending[0]:
            self.vehicle_mode, self._pending = self._pending[1], None
        return super().poll()


def test_identification_uses_only_ticks_flown_in_the_mode_asked_for():
    """A fleet hold during the join, then resume: the autopilot sits in its hold mode for 1.5 s while
    the join's setpoints stream again.  Those ticks are not the vehicle's response to them."""
    cfg, clock, link, r = make(LaggingLink, origin_ned_m=(-6.0, 0.0, -3.0), hold_grace_s=0.5)
    tick_until(r, clock, lambda: r.mission.state == State.JOIN)
    r.fleet_command("hold")
    tick_until(r, clock, lambda: link.vehicle_mode == ModeClass.HOLD, max_s=5.0)
    r.fleet_command("resume")
    tick_until(r, clock, lambda: r.mission.state == State.FLOW, max_s=60.0)
    resp = r.mission.response
    assert resp is not None
    assert resp.lag_s + resp.dead_time_s == pytest.approx(0.5, abs=0.1)


def test_a_kinetic_agent_takes_the_maps_real_wall_and_says_when_there_is_none(caplog):
    import numpy as np
    from fisc_agent.map.codec import encode_map, load_map
    from fisc_agent.map.wall import WALL_ARRAY
    from fisc_ground.maps.build import default_map_path

    cmap = load_map(default_map_path())
    body = {k: v for k, v in cmap.body.items() if k not in ("arrays", "sha256")}
    bare = decode_map(encode_map(body, {k: np.asarray(v) for k, v in cmap.arrays.items() if k != WALL_ARRAY}))
    for m, margin, warned in ((cmap, 0.8, False), (bare, 0.8, True), (bare, None, False)):
        caplog.clear()
        clock = Clock()
        cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=1, mode="kinetic", wall_margin_m=margin)
        r = Runner(cfg, MemoryLink(clock), m, clock=clock, sleep=clock.sleep, wall_clock=lambda: 1.7e9)
        assert (r.mission.sfield.wall is not None) == (m is cmap)
        assert ("carries no real wall" in caplog.text) == warned, caplog.text


class StallingLink(MemoryLink):
    """While the agent stalls, the vehicle's failsafe lands it; what queued up meanwhile (old OFFBOARD
    heartbeats) would read as current unless the backlog is discarded."""

    def __init__(self, clock):
        super().__init__(clock)
        self.backlog = 0        # polls' worth of old OFFBOARD heartbeats queued during a stall
        self.discards = 0

    def discard_backlog(self):
        self.discards += 1
        n, self.backlog = self.backlog, 0
        return n

    def poll(self):
        if self.backlog:        # an old heartbeat: the mode the vehicle had, stamped now
            self.backlog -= 1
            self.last_heartbeat_t = self.clock()
            return 1
        if self.heartbeat_gap_s and self.clock() < self.stall_end_s + self.heartbeat_gap_s:
            return 0            # the first fresh HEARTBEAT comes a little after the stall
        return super().poll()

    heartbeat_gap_s = 0.0
    stall_end_s = 0.0


def test_a_stalled_agent_drops_its_backlog_and_never_flies_over_a_failsafe_land():
    cfg, clock, link, r = make(link=StallingLink)
    tick_until(r, clock, lambda: r.mission.state == State.FLOW)
    real_mode = link.vehicle_mode
    clock.sleep(cfg.link_timeout_s + 3.0)       # the agent is frozen (SIGSTOP) ...
    link.vehicle_mode = ModeClass.LAND          # ... the autopilot's offboard-loss failsafe lands
    link.backlog, link.stall_end_s, link.heartbeat_gap_s = 50, clock.t, 0.5
    n_sp, n_cmd = len(link.setpoints), len(link.commands)
    r.step()
    assert link.discards == 1 and link.backlog == 0 and real_mode == ModeClass.OFFBOARD
    assert r.mission.hold_cause == HoldCause.LINK_LOST and len(link.setpoints) == n_sp
    tick_until(r, clock, lambda: r.mission.hands_off, max_s=2.0)   # the fresh HEARTBEAT says LAND
    tick_until(r, clock, lambda: False if clock.t < link.stall_end_s + 3.0 else True, max_s=4.0)
    # nothing sent since the stall (no setpoint, no mode request): the vehicle is still landing
    assert len(link.setpoints) == n_sp and len(link.commands) == n_cmd and link.vehicle_mode == ModeClass.LAND


def test_a_gap_of_the_link_timeout_is_the_stall_boundary():
    cfg, clock, link, r = make(link=StallingLink)
    tick_until(r, clock, lambda: r.mission.state == State.FLOW)
    clock.t = r._last_tick_s + cfg.link_timeout_s   # a gap of exactly --link-timeout is not a stall
    r.step()
    assert link.discards == 0
    clock.t = r._last_tick_s + cfg.link_timeout_s + 1e-6   # just longer is
    r.step()
    assert link.discards == 1


def test_a_failing_sleep_does_not_end_the_loop():
    """libfaketime's clock_nanosleep once raised EINVAL inside time.sleep: the loop logs it and ticks on."""
    cfg, clock, link, r = make()

    def bad_sleep(dt):
        clock.sleep(dt)
        raise OSError(22, "Invalid argument")

    r.sleep = bad_sleep
    assert r.run(max_duration_s=1.0) == r.mission.state and r.ticks >= 10
    assert r.rlog.counts()["loop:sleep"] >= 9


def _fly_at_a_still_neighbour(**kw):
    """Fly into FLOW, then put a still neighbour 2.5 m ahead on the agent's neighbour table for 4 s of
    ticks; returns the closest the vehicle came, the ids the net acted on, and the runner."""
    from fisc_agent.zenoh import telemetry_codec as tc
    from fisc_agent.zenoh.neighbours import NeighbourTable

    cfg, clock, link, r = make(**kw)
    tick_until(r, clock, lambda: r.mission.state == State.FLOW and r.snapshot().velocity_map_m_s[0] > 0.5)
    table = NeighbourTable(clock)
    r.neighbours = table if cfg.safety_net is not None else None
    x, y, z = r.snapshot().position_map_m
    other = (x + 2.5, y, z)
    closest, nets = math.inf, set()
    for _ in range(int(4.0 / cfg.period_s)):
        table.take(tc.encode(tc.Telemetry(agent_id=9, seq=1, time_s=0.0, position_m=other, velocity_m_s=(0, 0, 0),
                                          position_age_s=0.0, landed="in-air")))
        r.step()
        clock.sleep(cfg.period_s)
        snap = r.snapshot()
        closest = min(closest, math.dist(snap.position_map_m, other))
        nets.update(snap.net_ids)
    return closest, nets, r


def test_the_safety_net_stops_the_agent_short_of_a_neighbour_inside_d_min():
    closest, nets, r = _fly_at_a_still_neighbour()
    assert nets == {9}
    assert closest > 0.92 * 0.75  # d_min 0.92 m, less the lag of the 2 m/s^2 clamp
    assert math.dist(r.snapshot().position_map_m, (0, 0, 0)) > 0  # still flying, not held
    assert r.mission.state == State.FLOW


def test_without_the_safety_net_the_agent_flies_through_the_neighbour():
    closest, nets, _ = _fly_at_a_still_neighbour(safety_net=None)
    assert nets == set() and closest < 0.1


@pytest.mark.parametrize("age_s, used", [(0.0, True), (0.5, True), (0.55, False)])
def test_a_fresh_gnss_velocity_reaches_the_mission_in_the_map_frame(age_s, used, tmp_path):
    """... and the snapshot and the flight log's ``gnss_vx_m_s``, ``gnss_vy_m_s`` (empty when none is fresh)."""
    from fisc_agent.flight.flightlog import FlightLog, read_flight_log
    from fisc_agent.mavlink.interfaces import GnssVelocity

    cfg, clock, link, r = make(yaw_deg=90.0)      # the map's x axis points East
    seen = []
    step = r.mission.step
    r.mission.step = lambda s: (seen.append(s.gnss_vel_m_s), step(s))[1]
    link.gnss = GnssVelocity(clock.t - age_s, (0.3, 1.2))   # 0.3 m/s north, 1.2 m/s east
    r.step()
    log = FlightLog(tmp_path / "f.csv")
    log.write(r.snapshot())
    log.close()
    row = read_flight_log(tmp_path / "f.csv")[-1]
    if used:
        assert seen[-1] == pytest.approx((1.2, -0.3))         # east is map +x, north map -y
        assert r.snapshot().gnss_velocity_map_m_s == seen[-1]
        assert (float(row["gnss_vx_m_s"]), float(row["gnss_vy_m_s"])) == pytest.approx((1.2, -0.3))
    else:
        assert seen[-1] is None                               # older than GNSS_FRESH_S: the position's rate
        assert r.snapshot().gnss_velocity_map_m_s is None and row["gnss_vx_m_s"] == row["gnss_vy_m_s"] == ""


class DragLink(MemoryLink):
    """A vehicle with a linear drag ``c`` whose attitude (as PX4's ODOMETRY gives it) leans with the thrust
    it takes: its acceleration plus ``c v``, plus an attitude estimate's tilt bias."""

    drag_1_s = 0.8
    tilt_bias_ne = (0.3, -0.1)

    def poll(self):
        v0, t0 = list(self.vel), self._t
        n = super().poll()
        now = self.clock()
        dt = now - t0
        a = [(v - u) / dt if dt > 0 else 0.0 for v, u in zip(self.vel, v0)]
        c, b = self.drag_1_s, self.tilt_bias_ne
        self.thrust = ThrustAccel(now, (a[0] + c * self.vel[0] + b[0], a[1] + c * self.vel[1] + b[1]))
        return n

    def takeoff(self, alt_m):
        """ArduPilot's take-off command: the vehicle is at the height at once."""
        super().takeoff(alt_m)
        self.pos[2] = -alt_m


def _accel_setpoints(link):
    return [(sp, a) for sp, a in zip(link.setpoints, link.accels) if a is not None]


def test_px4_the_drag_identified_is_fed_forward_once_the_vehicle_is_slow():
    cfg, clock, link, r = make(DragLink, exit_policy="loop", origin_ned_m=(-6.0, 0.0, -3.0))
    tick_until(r, clock, lambda: r.drag.estimator.drag_1_s is not None, max_s=120.0)
    assert r.drag.estimator.drag_1_s == pytest.approx(DragLink.drag_1_s, rel=0.1)
    tick_until(r, clock, lambda: bool(_accel_setpoints(link)), max_s=120.0)
    first_sp, _ = _accel_setpoints(link)[0]
    assert math.hypot(first_sp[1], first_sp[2]) <= cfg.drag.switch_on_speed_m_s  # switched on slow, not at speed
    laps = r.mission.laps
    tick_until(r, clock, lambda: r.mission.laps >= laps + 2, max_s=120.0)
    c = r.drag.estimator.drag_1_s
    flown = _accel_setpoints(link)
    assert len(flown) > 100 and all(a is not None for a in link.accels[-len(flown):])  # on for good
    for (_, vn, ve, _), (an, ae, ad) in flown:  # the drag's thrust at each setpoint, horizontal only
        assert an == pytest.approx(c * vn, abs=0.05) and ae == pytest.approx(c * ve, abs=0.05) and ad == 0.0
    assert max(math.hypot(a[0], a[1]) for _, a in flown) > 0.5


def test_the_feedforward_switched_off_or_an_ardupilot_sends_velocity_only():
    for kw in (dict(drag=DragConfig(feedforward=False)), dict(autopilot="ardupilot")):
        cfg, clock, link, r = make(DragLink, exit_policy="loop", origin_ned_m=(-6.0, 0.0, -3.0), **kw)
        if kw.get("autopilot"):
            link.autopilot = "ardupilot"
        tick_until(r, clock, lambda: r.mission.laps >= 6, max_s=300.0)
        assert r.drag.estimator.drag_1_s == pytest.approx(DragLink.drag_1_s, rel=0.1), kw  # identified all the same
        assert len(link.setpoints) > 500 and not _accel_setpoints(link), kw


def test_a_vehicle_without_attitude_flies_velocity_only():
    cfg, clock, link, r = make(exit_policy="loop", origin_ned_m=(-6.0, 0.0, -3.0))
    tick_until(r, clock, lambda: r.mission.laps >= 6, max_s=300.0)
    assert r.drag.estimator.windows == 0 and len(link.setpoints) > 500 and not _accel_setpoints(link)


def test_the_feedforward_is_bounded_by_the_acceleration_clamp():
    class DraggyLink(DragLink):
        drag_1_s = 2.0

    cfg, clock, link, r = make(DraggyLink, exit_policy="loop", origin_ned_m=(-6.0, 0.0, -3.0), max_accel_m_s2=2.0)
    tick_until(r, clock, lambda: bool(_accel_setpoints(link)), max_s=240.0)
    laps = r.mission.laps
    tick_until(r, clock, lambda: r.mission.laps >= laps + 2, max_s=120.0)
    flown = _accel_setpoints(link)
    sizes = [math.hypot(a[0], a[1]) for _, a in flown]
    assert max(sizes) == pytest.approx(cfg.max_accel_m_s2)  # reached (2 /s x 2.5 m/s) and bounded
    for (_, vn, ve, _), (an, ae, _) in flown:  # along the setpoint
        assert an * ve == pytest.approx(ae * vn, abs=1e-9)
