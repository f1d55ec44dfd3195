"""The failsafe flag from a real agent to the monitor's alarm (issue 11's bug: it never got there).

1. A real ``Runner`` on a simulated clock (the in-memory PX4 of ``tests/fisc_agent``) is driven
   into each failsafe state; its snapshot, turned into telemetry by the agent's Zenoh link,
   carries ``failsafe`` (and ``outside_map`` for the geofence), and the monitor's aggregator
   raises the alarm.  Fleet and exit holds and normal flight raise none.
2. End to end: a real ``fisc-agent`` process flying the project's MAVLink emulator
   (``fisc-sim autopilot``) on a map whose field leaves the tunnel sideways is held by its
   geofence; a monitor on a real Zenoh session raises the failsafe alarm.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parents[1] / "fisc_agent"))  # the agent tests' in-memory PX4

from test_agent_runner import MemoryLink, make, tick_until  # noqa: E402

from fisc_agent.zenoh import telemetry_codec as tc  # noqa: E402
from fisc_agent.mavlink.adapters import ModeClass  # noqa: E402
from fisc_agent.mavlink.link import PositionSample  # noqa: E402
from fisc_agent.map.codec import decode_map, encode_map  # noqa: E402
from fisc_agent.flight.mission import State  # noqa: E402
from fisc_agent.flight.mission_types import Cause, Reason  # noqa: E402
from fisc_agent.zenoh.keys import Keys  # noqa: E402
from fisc_agent.zenoh.link import AgentZenohLink  # noqa: E402
from fisc_agent.zenoh.session import PORT_ENV, LabDiscovery, open_lab_session  # noqa: E402
from fisc_ground.maps.write import generate_keypair, read_signing_key  # noqa: E402
from fisc_ground.monitor.run import TelemetryAggregator, TelemetryPipe  # noqa: E402
from fisc_ground.zenoh.fleet import make_command, send_command  # noqa: E402

from .conftest import free_port, map_parts, wait_for  # noqa: E402



class FaultyLink(MemoryLink):
    """The in-memory PX4 whose HEARTBEATs can be muted (the link-lost failsafe)."""

    def __init__(self, clock):
        super().__init__(clock)
        self.mute = False

    def poll(self):
        last_hb = self.last_heartbeat_t
        n = super().poll()
        if self.mute:
            self.last_heartbeat_t = last_hb
        return n


def runner_with(**kw):
    """``make`` of the agent tests, with the fault-injecting link swapped in."""
    cfg, clock, _, r = make(**kw)
    link = FaultyLink(clock)
    r.link = link
    return cfg, clock, link, r


def drift(link, clock, dt, east_m_s):
    """Push the vehicle east (a gust the setpoints cannot beat), fix and velocity consistent."""
    link.pos[1] += east_m_s * dt
    vel = (link.vel[0], link.vel[1] + east_m_s, link.vel[2])
    link._fix = PositionSample(clock(), tuple(link.pos), vel)


def alarms_for(snapshot) -> tuple[frozenset, tuple[str, ...]]:
    """Telemetry flags of ``snapshot`` as the agent's link builds them, and the monitor's alarms."""
    link = AgentZenohLink(None, "fs", snapshot.agent_id, None, True, lambda m: None, lambda c: None)
    tele = link.telemetry_from(snapshot)
    agg = TelemetryAggregator(None)
    agg.ingest(np.array([time.time()]), np.array([snapshot.agent_id]), [tc.encode(tele)])
    return tele.flags, agg.view().alarms


def to_flow(r, clock):
    tick_until(r, clock, lambda: r.mission.state == State.FLOW)


def test_link_lost_sets_failsafe_and_the_monitor_alarms():
    cfg, clock, link, r = runner_with()
    to_flow(r, clock)
    assert "failsafe" not in alarms_for(r.snapshot())[0]
    link.mute = True
    tick_until(r, clock, lambda: r.mission.state == State.HOLD)
    snap = r.snapshot()
    assert snap.reason == "link lost" and snap.failsafe
    flags, alarms = alarms_for(snap)
    assert "failsafe" in flags and "mavlink_ok" not in flags
    assert f"failsafe: agents {cfg.agent_id}" in alarms


@pytest.mark.parametrize("lost", [False, True], ids=["stale", "lost"])
def test_stale_or_lost_position_sets_failsafe(lost):
    cfg, clock, link, r = runner_with()
    to_flow(r, clock)
    link.freeze_position = True
    tick_until(r, clock, lambda: r.mission.state == State.HOLD)
    if lost:  # stale beyond the grace: the autopilot's hold mode is requested, still a failsafe hold
        tick_until(r, clock, lambda: r.snapshot().position_age_s > cfg.stale_timeout_s + cfg.hold_grace_s)
    snap = r.snapshot()
    assert snap.reason == "position stale" and snap.failsafe
    flags, alarms = alarms_for(snap)
    assert "failsafe" in flags and ("position_fresh" not in flags or not lost)
    assert f"failsafe: agents {cfg.agent_id}" in alarms


@pytest.mark.parametrize("policy", ["hold", "return"])
def test_geofence_sets_failsafe_and_outside_map(policy):
    cfg, clock, link, r = runner_with(geofence=policy)
    to_flow(r, clock)
    want = State.HOLD if policy == "hold" else State.RETURN
    end = clock.t + 20.0
    while r.mission.state != want and clock.t < end:
        drift(link, clock, cfg.period_s, 6.0)
        r.step()
        clock.sleep(cfg.period_s)
    snap = r.snapshot()
    assert snap.state == want.value and snap.reason.startswith("geofence"), r.mission.transitions
    assert snap.failsafe and snap.outside_map and snap.cv_id == -1
    flags, alarms = alarms_for(snap)
    assert {"failsafe", "outside_map"} <= flags
    assert f"failsafe: agents {cfg.agent_id}" in alarms and f"outside the tunnel: agents {cfg.agent_id}" in alarms


def test_mode_taken_by_the_pilot_sets_failsafe():
    cfg, clock, link, r = runner_with()
    to_flow(r, clock)
    link.vehicle_mode = ModeClass.OTHER  # the pilot switched to POSCTL
    tick_until(r, clock, lambda: r.mission.state == State.HOLD)
    snap = r.snapshot()
    assert snap.reason.startswith("pilot override") and snap.failsafe
    assert f"failsafe: agents {cfg.agent_id}" in alarms_for(snap)[1]


def test_fleet_hold_exit_hold_and_flight_are_no_failsafe():
    cfg, clock, link, r = runner_with()
    to_flow(r, clock)
    assert not r.snapshot().failsafe and not r.snapshot().outside_map
    r.fleet_command("hold")
    tick_until(r, clock, lambda: r.mission.state == State.HOLD)
    flags, alarms = alarms_for(r.snapshot())
    assert r.snapshot().reason == "fleet hold" and "failsafe" not in flags and not alarms
    r.fleet_command("resume")
    tick_until(r, clock, lambda: r.mission.state == State.HOLD and r.mission.reason.startswith("exit"))
    snap = r.snapshot()
    assert not snap.failsafe and not snap.outside_map  # past the outlet by design
    assert "failsafe" not in alarms_for(snap)[0]


# --------------------------------------------------------------------------------------------
# End to end: fisc-agent process + fisc-sim autopilot process + a monitor on a real session

def sideways_map(signing_key: bytes) -> bytes:
    """The tests' 6 m x 2 m x 2 m grid map, its field blowing across the tunnel (+y): a vehicle
    flowing in it leaves through the side wall, inside the outlet plane."""
    meta, arrays = map_parts(100)
    n, n_max = arrays["fit_velocity_m_s"].shape[:2]
    vel = np.broadcast_to(np.array([0.5, 2.0, 0.0]), (n, n_max, 3)).copy()
    arrays.update(fit_velocity_m_s=vel, fit_mean_velocity_m_s=vel.mean(axis=1), target_velocity_m_s=vel.mean(axis=1))
    return encode_map(meta, arrays, signing_key)


@pytest.mark.slow
def test_agent_process_held_by_its_geofence_raises_the_monitor_failsafe_alarm(tmp_path):
    key, pub = generate_keypair(tmp_path / "ground")
    blob = sideways_map(read_signing_key(key))
    map_path = tmp_path / "side.fiscmap"
    map_path.write_bytes(blob)
    cmap = decode_map(blob, None)
    port, udp = free_port(), free_port()
    env = {**os.environ, PORT_ENV: str(port), "PYTHONUNBUFFERED": "1"}
    session = open_lab_session(LabDiscovery(port=port))
    agg = TelemetryAggregator(cmap)
    pipe = TelemetryPipe(Keys("fisc", "fs"), agg).attach(session)
    procs = []
    try:
        with open(tmp_path / "autopilot.log", "w") as log_ap, open(tmp_path / "agent.log", "w") as log_ag:
            # PX4 hovering armed 4 m up, inside the map's first cells (map origin 4 m up: --origin 0,0,-4)
            procs.append(subprocess.Popen([sys.executable, "-m", "sim.cli", "autopilot", "--mavlink",
                                           f"udpin:127.0.0.1:{udp}", "--personality", "px4", "--start=1,0,-4"],
                                          env=env, stdout=log_ap, stderr=subprocess.STDOUT))
            procs.append(subprocess.Popen([sys.executable, "-m", "fisc_agent.cli", "--go", "--map", map_path, "--swarm", "fs",
                                           "--trusted-key", pub, "--mavlink", f"udpout:127.0.0.1:{udp}", "--id", "5",
                                           "--origin", "0,0,-4", "--geofence", "hold", "--max-duration", "60"],
                                          env=env, stdout=log_ag, stderr=subprocess.STDOUT))

        # the hovering vehicle is not the agent's (armed before it started): it waits, then a signed
        # takeover addressed to it hands the vehicle over
        standby = wait_for(lambda: pipe.view().by_state.get("STANDBY") == 1, timeout_s=30, period_s=0.2)
        assert standby, (tmp_path / "agent.log").read_text()[-3000:]
        send_command(session, Keys("fisc", "fs"), make_command("takeover", "fs", (5,)), read_signing_key(key))

        def alarm():
            return any(a.startswith("failsafe: agents 5") for a in pipe.view().alarms)

        ok = wait_for(alarm, timeout_s=45, period_s=0.2)
        agent_log = (tmp_path / "agent.log").read_text()
        assert ok, f"no failsafe alarm; alarms {pipe.view().alarms}\n{agent_log[-3000:]}"
        assert "geofence: outside the map" in agent_log, agent_log[-3000:]
        view = pipe.view()
        assert view.by_state.get("HOLD") == 1, view
        assert any(a.startswith("outside the tunnel: agents 5") for a in view.alarms), view.alarms
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        pipe.close()
        session.close()


@pytest.mark.parametrize("cause", [Cause.GEOFENCE_RETURN, Cause.POSITION_BACK, Cause.FLEET_RESUME])
def test_every_return_into_the_map_is_a_failsafe_whatever_began_it(cause):
    # a geofence RETURN interrupted by a stale-position hold resumes with "position fix back": still returning
    from fisc_agent.flight.tick import failsafe_active

    assert failsafe_active(State.RETURN, Reason(cause))
    assert not failsafe_active(State.FLOW, Reason(cause)) and not failsafe_active(State.JOIN, Reason(cause))
