"""The emulator and agent worker processes: each hosts its share of vehicles in one thread on a
monotonic-deadline schedule and reports its samples, outcomes and loop timing to the parent."""

from __future__ import annotations

import gc
import logging
import math
import os
import resource
import time
import traceback
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from fisc_agent.map.codec import load_map
from pymavlink.dialects.v20.common import MAV_CMD_SET_MESSAGE_INTERVAL

if TYPE_CHECKING:
    from sim.autopilot.estimate_error import EstimateErrorParams

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------ workers
#: Streams an agent needs (HEARTBEAT is fixed-rate): with ``telemetry="lean"`` the agents switch
#: every other stream of their autopilot off (MAV_CMD_SET_MESSAGE_INTERVAL, interval -1).
#: EXTENDED_SYS_STATE stays on: its landed state tells the mission that the take-off has left the
#: ground (``mission.Mission``), and without it no lean agent ever got past TAKEOFF.
LEAN_OFF_MSG_IDS = (33, 1, 2, 24, 242, 74, 30)
"""GLOBAL_POSITION_INT, SYS_STATUS, SYSTEM_TIME, GPS_RAW_INT, HOME_POSITION, VFR_HUD, ATTITUDE."""


@dataclass(frozen=True)
class _EmulatorJob:
    agent_ids: tuple[int, ...]
    start_ned_m: tuple[tuple[float, float, float], ...]
    start_time_s: tuple[float, ...]
    personality: str
    physics_rate_hz: float
    physics_dt_s: float
    plant: str
    position_rate_hz: float
    sample_interval_s: float
    log_level: str
    estimate_error: EstimateErrorParams | None = None
    """The estimate error of every vehicle (seeded per id), or None: the truth."""


@dataclass(frozen=True)
class _AgentJob:
    agent_ids: tuple[int, ...]
    ports: tuple[int, ...]
    start_time_s: tuple[float, ...]
    map_path: str
    personality: str
    mode: str | None
    lookahead_s: float | None
    exit_policy: str
    geofence: str
    rate_hz: float
    position_rate_hz: float
    telemetry: str
    log_level: str
    tracking: bool
    entry_radius_fraction: float
    safety_net: bool = False
    staggered_admission: bool = False
    fleet_mode: bool = False
    swarm: str | None = None
    zenoh_config: str | None = None
    zenoh_prefix: str = "fisc"
    telemetry_rate_hz: float = 5.0
    trusted_key: str | None = None
    flight_log_dir: str | None = None


class _LoopLog:
    """Per-tick timing of a worker loop and its CPU time once a second (times since launch)."""

    def __init__(self, t0: float, period: float) -> None:
        self.t0, self.period = t0, period
        self.tick_t: list[float] = []
        self.lag: list[float] = []
        self.busy: list[float] = []
        self.cpu_t: list[float] = [0.0]
        self.cpu: list[float] = [_cpu_s()]

    def tick(self, start: float, deadline: float, end: float) -> None:
        self.tick_t.append(start - self.t0)
        self.lag.append(start - deadline)
        self.busy.append(end - start)
        if end - self.t0 >= self.cpu_t[-1] + 1.0:
            self.cpu_t.append(end - self.t0)
            self.cpu.append(_cpu_s())

    def export(self) -> dict:
        self.cpu_t.append(time.monotonic() - self.t0)
        self.cpu.append(_cpu_s())
        return {"period_s": self.period, "tick_t_s": np.asarray(self.tick_t), "lag_s": np.asarray(self.lag),
                "busy_s": np.asarray(self.busy), "cpu_t_s": np.asarray(self.cpu_t), "cpu_s": np.asarray(self.cpu)}


def _cpu_s() -> float:
    t = os.times()
    return t.user + t.system


def _raise_fd_limit() -> None:
    """Allow one socket per hosted vehicle beyond the usual soft limit of 1024 descriptors."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = 65536 if hard == resource.RLIM_INFINITY else hard
    if soft != resource.RLIM_INFINITY and soft < want:
        resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))


def _freeze_heap() -> None:
    """Move the set-up objects (emulators, runners, maps) out of the cyclic GC's reach: a full
    collection over hundreds of vehicles' objects stalls a real-time loop for tens of ms."""
    gc.collect()
    gc.freeze()


class ParentWatch:
    """Tells a worker that the ``fisc-sim emulate`` process that started it is gone (killed -9: a
    daemon worker outlives it, and would fly its vehicles to the end of the run).  A process whose
    parent dies is re-parented, so its parent pid changes."""

    def __init__(self, parent_pid: int | None = None) -> None:
        self.parent_pid = os.getppid() if parent_pid is None else parent_pid
        """The parent's pid when the worker started."""

    def gone(self) -> bool:
        """True once the parent has exited."""
        return os.getppid() != self.parent_pid


def _id_span(ids) -> str:
    """``0-19`` for the agent ids a worker hosts."""
    return f"{int(min(ids))}-{int(max(ids))}" if len(ids) else "(none)"


def _sleep_until(deadline: float) -> None:
    dt = deadline - time.monotonic()
    if dt > 0:
        time.sleep(dt)


def _next_tick(t0: float, tick: int, period: float) -> tuple[int, float]:
    """Next tick index and deadline; after an overrun of more than a period, re-synchronise."""
    tick += 1
    next_t = t0 + tick * period
    now = time.monotonic()
    if next_t < now - period:
        tick = int((now - t0) / period) + 1
        next_t = t0 + tick * period
    return tick, next_t


def _emulator_worker(conn, job: _EmulatorJob) -> None:
    """Host ``len(job.agent_ids)`` autopilot emulators in one thread (spawned process); stops
    when the run ends or its parent is gone."""
    parent = ParentWatch()
    try:
        logging.basicConfig(level=job.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        from sim.autopilot.personalities import FlightMode
        from sim.autopilot.server import AutopilotEmulator
        from sim.autopilot.vehicle import VehicleConfig
        from sim.plant.model import VelocityPlant

        _raise_fd_limit()
        from sim.plant.fit import plant_preset
        from sim.plant.px4_loop import PX4_LOOP_PLANT, Px4LoopParams

        loop = job.plant == PX4_LOOP_PLANT  # stock PX4's loop flies the vehicle, not the velocity plant
        vcfg = VehicleConfig(physics_dt_s=job.physics_dt_s, plant_params=plant_preset("paper" if loop else job.plant),
                             px4_loop=Px4LoopParams() if loop else None)
        err = job.estimate_error
        emus = [AutopilotEmulator("udpin:127.0.0.1:0", job.personality, start, sysid=1 + aid % 250,
                                  rate_position_hz=job.position_rate_hz,
                                  vehicle_config=vcfg if err is None else replace(
                                      vcfg, estimate_error=replace(err, seed=err.seed + aid)))
                for aid, start in zip(job.agent_ids, job.start_ned_m)]
        order = np.argsort(np.asarray(job.start_time_s), kind="stable")
        emus = [emus[j] for j in order]  # by launch time (the parent puts the columns back in id order)
        ids = np.asarray(job.agent_ids)[order]
        serve_from = np.asarray(job.start_time_s)[order] - 0.5
        # warm-up: the plant's numba kernel compiles (or loads its cache) on the first call; do
        # it now, not on the first vehicle's lift-off (a stall there reads as a stale position)
        VelocityPlant(vcfg.plant_params, 1).step(np.zeros((1, 3)), job.physics_dt_s)
        n = len(emus)
        sp_count = np.zeros(n, dtype=np.int64)

        def counting(j: int, fn: Callable) -> Callable:
            def set_setpoint(*a, **kw):
                sp_count[j] += 1
                return fn(*a, **kw)
            return set_setpoint

        for j, e in enumerate(emus):  # count the setpoints that reach each vehicle
            e.vehicle.set_setpoint = counting(j, e.vehicle.set_setpoint)
        _freeze_heap()
        ports = [0] * n
        for j, e in zip(order, emus):
            ports[j] = e.local_address[1]
        conn.send(("ports", ports))  # in job order
        msg = conn.recv()
        if msg[0] != "go":
            return
        t0, t_end = msg[1], msg[2]
        offboard = {FlightMode.OFFBOARD, FlightMode.GUIDED}
        period = 1.0 / job.physics_rate_hz
        n_samples = int(math.floor((t_end - t0) / job.sample_interval_s + 1e-9)) + 1
        pos = np.full((n_samples, n, 3), np.nan)
        vel = np.full((n_samples, n, 3), np.nan)
        sample_t = np.full(n_samples, np.nan)
        sp_t: list[float] = []
        sp_rate: list[float] = []
        probe_count = np.zeros(n, dtype=np.int64)
        probe_flying = np.zeros(n, dtype=bool)
        probe_t = 0.0
        n_live = 0
        _sleep_until(t0)
        loop = _LoopLog(t0, period)
        k_next = 0
        tick = 0
        next_probe = t0 + 1.0
        while True:
            deadline = t0 + tick * period
            start = time.monotonic()
            if start >= t_end or parent.gone():
                break
            # a vehicle is served from just before its agent is switched on: until then it sits
            # landed and disarmed with nobody listening, and its first poll catches the physics up
            if n_live < n:
                n_live = int(np.searchsorted(serve_from, start - t0, side="right"))
            for e in emus[:n_live]:
                e.poll()
            now = time.monotonic()
            while k_next < n_samples and now >= t0 + k_next * job.sample_interval_s:
                for j, e in enumerate(emus):
                    st = e.state
                    pos[k_next, j] = st.reported_position_ned_m
                    vel[k_next, j] = st.reported_velocity_ned_m_s
                sample_t[k_next] = now - t0
                k_next += 1
            if now >= next_probe:  # setpoint rate over the last second, vehicles flying offboard throughout
                next_probe += 1.0
                flying = np.array([e.state.armed and e.state.in_air and e.state.mode in offboard for e in emus])
                both = flying & probe_flying
                if both.any() and now > probe_t:
                    rates = (sp_count[both] - probe_count[both]) / (now - t0 - probe_t)
                    sp_rate.extend(rates.tolist())
                    sp_t.extend([now - t0] * rates.size)
                probe_count[:], probe_flying[:], probe_t = sp_count, flying, now - t0
            loop.tick(start, deadline, time.monotonic())
            tick, next_t = _next_tick(t0, tick, period)
            _sleep_until(next_t)
        timing = loop.export()
        if k_next < n_samples:  # the final sample (end of the run), as fisc-sim run takes one at its last step
            for e in emus:
                e.poll()
            for j, e in enumerate(emus):
                pos[k_next:, j] = e.state.reported_position_ned_m
                vel[k_next:, j] = e.state.reported_velocity_ned_m_s
            sample_t[k_next:] = time.monotonic() - t0
        stats = {"rx": int(sum(e.stats["rx"] for e in emus)), "tx": int(sum(e.stats["tx"] for e in emus))}
        for e in emus:
            e.close()
        if parent.gone():
            log.warning("emulators %s: the emulate process is gone, stopped", _id_span(job.agent_ids))
            return
        conn.send(("result", {
            "agent_ids": ids, "pos_ned_m": pos, "vel_ned_m_s": vel, "sample_t_s": sample_t,
            "setpoint_rate_hz": np.asarray(sp_rate), "setpoint_rate_t_s": np.asarray(sp_t), "timing": timing,
            "messages": stats,
        }))
    except Exception:  # noqa: BLE001 - reported to the parent, which raises
        conn.send(("error", traceback.format_exc()))
    finally:
        conn.close()


def _open_fleet_links(job: _AgentJob, runners: list) -> tuple[Any, list]:
    """With ``job.swarm``: one Zenoh session for the worker and one ``AgentZenohLink`` per runner
    (telemetry out; maps and fleet commands in, which need the ground's signature as on a real
    fleet).  Returns (session, links); (None, []) without a swarm."""
    if not job.swarm:
        return None, []
    from fisc_agent.map.codec import read_public_key
    from fisc_agent.zenoh.link import AgentZenohLink
    from fisc_agent.zenoh.neighbours import NeighbourTable
    from fisc_agent.zenoh.runner import CommandDispatcher
    from fisc_agent.zenoh.session import open_session

    keys = [read_public_key(job.trusted_key)]
    session = open_session(job.zenoh_config)
    table = NeighbourTable()  # one subscription per worker, shared by its agents' safety nets
    for r in runners:
        r.neighbours = table if r.cfg.safety_net is not None else None
    links = [AgentZenohLink(None, job.swarm, int(aid), keys, False, r.offer_map, CommandDispatcher(r, r.unix_time),
                            prefix=job.zenoh_prefix, session=session, command_clock=r.unix_time,
                            neighbours=r.neighbours).start()
             for aid, r in zip(job.agent_ids, runners)]
    return session, links


def agent_config(job: _AgentJob, agent_id: int, port: int):
    """The ``fisc_agent.config.AgentConfig`` of one emulated vehicle's agent: the job's settings, and
    streamline tracking only when ``job.tracking`` (else gain 0: the agent flies
    ``fisc_agent.map.lookup.flight_command`` at its position, the function ``fisc-sim run`` flies).  The
    emulated duct has no physical wall: kinetic deviations reflect at the CV staircase, as in ``fisc-sim
    run`` (``wall_margin_m`` None), so the two compare, unless ``job.fleet_mode`` (fisc-agent's own margin
    of the map's real wall, as on a real fleet, and its ``kinetic_axes``: across the stream; without it the deviations
    are isotropic, as ``fisc-sim run``'s); the launches are staggered at the paper's
    source rate (``sim.emulate.plan``), and the agents admit themselves from the map's admission budget
    only with ``job.staggered_admission`` (else ``entry_stagger_s`` 0); the safety net only with
    ``job.safety_net``."""
    from fisc_agent.config import AgentConfig
    from fisc_agent.flight.safety_net import SafetyNetConfig
    from fisc_agent.flight.tracking import KineticAxes, TrackingConfig

    return AgentConfig(mavlink_url=f"udpout:127.0.0.1:{port}", agent_id=agent_id, map_path=job.map_path, go=True, state_file=None,
                       autopilot=job.personality, mode=job.mode, lookahead_s=job.lookahead_s, rate_hz=job.rate_hz,
                       exit_policy=job.exit_policy, geofence=job.geofence,
                       entry_radius_fraction=job.entry_radius_fraction,
                       wall_margin_m=AgentConfig.wall_margin_m if job.fleet_mode else None,
                       entry_stagger_s=None if job.staggered_admission else 0.0,
                       tracking=TrackingConfig(kinetic_axes=TrackingConfig.kinetic_axes if job.fleet_mode
                                               else KineticAxes.ISOTROPIC) if job.tracking
                       else TrackingConfig(gain_1_s=0.0),
                       safety_net=SafetyNetConfig() if job.safety_net else None)


def _agent_worker(conn, job: _AgentJob) -> None:
    """Host ``len(job.agent_ids)`` fisc-agent runners in one thread (spawned process); stops when
    the run ends or its parent is gone."""
    parent = ParentWatch()
    try:
        logging.basicConfig(level=job.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        from fisc_agent.mavlink.adapters import CommandLong
        from fisc_agent.mavlink.endpoints import parse_endpoint
        from fisc_agent.flight.flightlog import FlightLog
        from fisc_agent.mavlink.link import MavlinkLink
        from fisc_agent.runner import Runner

        _raise_fd_limit()
        cmap = load_map(job.map_path)
        runners, logs = [], []
        for aid, port in zip(job.agent_ids, job.ports):
            cfg = agent_config(job, int(aid), port)
            link = MavlinkLink(parse_endpoint(cfg.mavlink_url), position_rate_hz=job.position_rate_hz)
            if job.flight_log_dir is not None:
                logs.append(FlightLog(Path(job.flight_log_dir) / f"agent_{int(aid)}.csv"))
            runners.append(Runner(cfg, link, cmap, on_tick=logs[-1].write if logs else None))
        # lean telemetry: once the autopilot is found, switch its streams other than HEARTBEAT and
        # LOCAL_POSITION_NED off, one command per tick (what a bandwidth-conscious companion does)
        trims = [CommandLong(MAV_CMD_SET_MESSAGE_INTERVAL, (float(mid), -1.0, 0, 0, 0, 0, 0), f"stream {mid} off")
                 for mid in (LEAN_OFF_MSG_IDS if job.telemetry == "lean" else ())]
        trimmed = np.zeros(len(runners), dtype=np.int64)
        session, zlinks = _open_fleet_links(job, runners)
        telemetry_every = max(1, round(job.rate_hz / job.telemetry_rate_hz))
        _freeze_heap()
        conn.send(("ready", None))
        msg = conn.recv()
        if msg[0] != "go":
            return
        t0, t_end = msg[1], msg[2]
        starts = np.asarray(job.start_time_s) + t0
        period = 1.0 / job.rate_hz
        active = np.zeros(len(runners), dtype=bool)
        first_tick = np.full(len(runners), np.nan)
        _sleep_until(t0)
        loop = _LoopLog(t0, period)
        tick = 0
        while True:
            deadline = t0 + tick * period
            start = time.monotonic()
            if start >= t_end or parent.gone():
                break
            newly = (~active) & (starts <= start)
            if newly.any():
                first_tick[newly] = start - t0
                active |= newly
            for i in np.flatnonzero(active):
                r = runners[i]
                r.step()
                if trimmed[i] < len(trims) and r.link.target_system is not None:
                    r.link.send_command(trims[trimmed[i]])
                    trimmed[i] += 1
            if zlinks and tick % telemetry_every == 0:  # every agent: launched, or waiting on the ground
                for zlink, r in zip(zlinks, runners):
                    zlink.publish_telemetry(r.snapshot())
            loop.tick(start, deadline, time.monotonic())
            tick, next_t = _next_tick(t0, tick, period)
            _sleep_until(next_t)
        timing = loop.export()
        agents = []
        for i, r in enumerate(runners):
            m = r.mission
            agents.append({
                "agent_id": int(job.agent_ids[i]), "launch_s": float(first_tick[i]), "state": m.state.value,
                "reason": m.reason, "laps": int(m.laps), "ticks": int(r.ticks),
                "setpoints_sent": int(getattr(r.link, "setpoints_sent", 0)),
                # the drag the agent identified in flight and whether it feeds it forward (fisc_agent.flight.drag)
                "drag_1_s": r.drag.estimator.drag_1_s, "drag_fed_forward": r.drag.on,
                "transitions": [(float(tr.t_s - t0), tr.src.value, tr.dst.value, tr.reason) for tr in m.transitions],
            })
            r.link.close()
        for log in logs:
            log.close()
        for zl in zlinks:
            zl.close()
        if session is not None:
            session.close()
        if parent.gone():
            log.warning("agents %s: the emulate process is gone, stopped", _id_span(job.agent_ids))
            return
        conn.send(("result", {"agents": agents, "timing": timing}))
    except Exception:  # noqa: BLE001 - reported to the parent, which raises
        conn.send(("error", traceback.format_exc()))
    finally:
        conn.close()
