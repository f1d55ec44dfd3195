"""Acceptance test of issue 5 with real processes: a signed map over Zenoh to a fleet.

Every box is its own OS process, started from the installed console scripts exactly as a
person types them (docs/fleet_walkthrough.md is the same scenario by hand):

    fisc-ground publish MAP      (the hub: listens on tcp/127.0.0.1:<free port>)
    fisc-sim autopilot  x 4      (PX4 x 3, ArduPilot x 1; MAVLink over UDP on free ports)
    fisc-agent          x 4      (3 start before the publisher, 1 after it serves the map)
    fisc-ground status / cmd / fit / inspect / monitor / replay   (short-lived)

Specification checked:
1. every agent receives the SIGNED map over Zenoh (status reports its sha256 and map_version)
   and flies it: each vehicle is seen in FLOW inside the tunnel (CV >= 0, map-frame x within
   the map), with its position coming from its emulator over MAVLink;
2. a map signed by a stranger key with a newer map_version, served by the same publisher, is
   refused by every agent (telemetry: refused-map counter, reason ``signature``) and every
   agent keeps its good map and keeps flying;
3. ``fisc-ground cmd hold`` (signed) is acknowledged by all four, they hold and stop; ``resume``
   makes them fly again;
4. the monitor receives the agents' telemetry headless (``--duration``), records it, and
   ``replay`` of the recording yields non-empty per-CV swarm density and pressure.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from .conftest import Processes, cli, free_tcp_port, free_udp_port, poll, run_cli, write_zenoh_config

pytestmark = pytest.mark.slow

SWARM = "e2e"
AGENT_IDS = (1, 2, 3, 4)
LATE_AGENT = 4
PERSONALITY = {1: "px4", 2: "px4", 3: "px4", 4: "ardupilot"}
FLYING = {"TAKEOFF", "JOIN", "FLOW", "RETURN", "EXIT"}
START_DOWN_M = {"px4": -1.5, "ardupilot": 0.0}
"""Emulator start height (local NED D): the PX4 vehicles start hovering, armed, in AUTO.LOITER
(not their agents' vehicles: the ground hands them over with a signed ``takeover --agents 1,2,3``);
the ArduPilot one starts on the ground and arms on the fleet's signed ``go`` (GUIDED, arm,
takeoff), which it learns late, from the publisher's re-published fleet state.  Why not all on the ground: a stand-alone ``fisc-sim autopilot`` loads its numba
plant kernel on the first airborne step (~0.4 s idle, >1 s on a loaded machine); the stalled
emulator then catches up its physics before reading the queued setpoints and trips PX4's
offboard-loss failsafe (COM_OF_LOSS_T 1 s), which the agent respects (hands-off hold)."""
STATUS_FRESH_S = 2.5
"""An agent whose newest telemetry in a status window is older than this is not counted."""


@dataclass
class Fleet:
    """The running fleet and what the tests need to know about it."""

    dir: Path
    procs: Processes
    hub_cfg: Path
    member_cfg: Path
    map_path: Path
    """The file the publisher serves (and re-serves when it is replaced)."""
    good_copy: Path
    """A copy of the good map (the served file is replaced by a stranger's map in test 1)."""
    ground_key: Path
    ground_pub: Path
    stranger_key: Path
    good: dict
    """``fisc-ground inspect --json`` of the good map."""
    started_s: float
    stranger: dict | None = None
    """``inspect --json`` of the stranger's map once it is served (``serve_stranger_map``)."""



ADMISSION_WAIT_S = 45.0
"""Longest an agent may wait at its staging point for its admission window (the map's budget and the
agents' windows on the autopilots' GNSS time): four emulated agents that had just missed theirs waited
25-38 s before moving on (2026-12-06), over the 30 s and 60 s these checks allowed before, which they
failed at times depending on where in the windows' cycle the test began."""
WINDOW_GIVEN_UP_S = 60.0
"""What one entry window given up costs an agent: the rest of the windows' cycle (a CI run, 2026-12-07: an
agent that had flown its first pass before the checks began gave its next window up on its way, slowed by the
safety net, 2.7 s late, and was not in FLOW again within the 75 s this check allowed)."""


def ground(*args) -> list[str]:
    return cli("fisc-ground") + [str(a) for a in args]


def ok(out) -> str:
    """stdout of a finished command; its stderr in the failure message otherwise."""
    assert out.returncode == 0, f"{out.args}: exit {out.returncode}\nstdout:\n{out.stdout}\nstderr:\n{out.stderr}"
    return out.stdout


def inspect(path: Path, trusted: Path | None = None) -> dict:
    args = ["inspect", path, "--json", "--compact"] + (["--trusted-key", trusted] if trusted else [])
    return json.loads(ok(run_cli(ground(*args))))


def fit_map(out: Path, key: Path) -> None:
    """The small built-in tunnel (15 m, 560 CVs), signed with ``key`` (~0.5 s)."""
    ok(run_cli(ground("fit", "cd_nozzle_inviscid", "--max-speed", "8", "-o", out, "--sign", key)))


def status(fleet: Fleet, wait_s: float = 1.0) -> dict[int, dict]:
    """``fisc-ground status --json``: the agents heard recently, by id."""
    out = ok(run_cli(ground("status", "--swarm", SWARM, "--zenoh-config", fleet.member_cfg, "--json",
                            "--wait", wait_s)))
    return {a["id"]: a for a in json.loads(out)["agents"] if a["last_seen_s"] < STATUS_FRESH_S}


def await_fleet(fleet: Fleet, pred, timeout_s: float, what: str, ids=AGENT_IDS) -> dict[int, dict]:
    """Poll status until ``pred(agent)`` holds for every agent in ``ids``; fail with the evidence."""
    last: dict[int, dict] = {}

    def check():
        nonlocal last
        assert not fleet.procs.dead(), f"a process died while waiting for {what}:\n{fleet.procs.report()}"
        last = status(fleet)
        return last if all(i in last and pred(last[i]) for i in ids) else None

    got = poll(check, timeout_s, period_s=0.0)
    if got is None:
        summary = {i: {k: last[i].get(k) for k in ("state", "map_sha256", "cv_index", "position_m", "velocity_m_s",
                                                   "maps_rejected", "reject_reason", "ack_command", "flags")}
                   for i in sorted(last)}
        raise AssertionError(f"timeout ({timeout_s} s) waiting for {what}; last status:\n"
                             f"{json.dumps(summary, indent=1)}\n{fleet.procs.report()}")
    return got


def speed(agent: dict) -> float:
    return math.sqrt(sum(v * v for v in agent["velocity_m_s"]))


def cmd(fleet: Fleet, name: str, *extra) -> dict:
    """``fisc-ground cmd NAME [EXTRA...]`` signed with the ground key; its JSON line."""
    out = ok(run_cli(ground("cmd", name, "--swarm", SWARM, "--zenoh-config", fleet.member_cfg,
                            "--key", fleet.ground_key, "--ack-wait", "8", *extra)))
    return json.loads(out.strip().splitlines()[-1])


def serve_stranger_map(fleet: Fleet) -> dict:
    """Replace the served file by a newer map signed with the stranger's key (once), wait until
    the publisher serves it and every agent has refused it; returns its ``inspect --json``."""
    if fleet.stranger is not None:
        return fleet.stranger
    good = fleet.good
    stranger = fleet.dir / "stranger.fiscmap"
    fit_map(stranger, fleet.stranger_key)
    bad = inspect(stranger)
    assert bad["signed"] and bad["map_version"] > good["map_version"] and bad["sha256"] != good["sha256"]
    os.replace(stranger, fleet.map_path)
    publisher = next(p for p in fleet.procs.procs if p.name == "publisher")
    assert poll(lambda: f"now serving map_version {bad['map_version']}" in publisher.log_tail(50), 20), \
        publisher.log_tail()
    await_fleet(fleet, lambda a: a["maps_rejected"] >= 1 and a["reject_reason"] == "signature", 30,
                "every agent to refuse the stranger's map")
    fleet.stranger = bad
    return bad


def _start_vehicle(fleet: Fleet, agent_id: int) -> None:
    """One emulated autopilot and the agent on it (the agent talks first: udpout -> udpin)."""
    port = free_udp_port()
    east = -1.5 + (agent_id - 1)  # side by side, 3 m upstream of the inlet
    down = START_DOWN_M[PERSONALITY[agent_id]]
    fleet.procs.start(f"autopilot-{agent_id}", cli("fisc-sim") + [
        "autopilot", "--mavlink", f"udpin:127.0.0.1:{port}", "--personality", PERSONALITY[agent_id],
        f"--start=-3,{east},{down}", "--sysid", agent_id])
    fleet.procs.start(f"agent-{agent_id}", cli("fisc-agent") + [
        "--zenoh-config", fleet.member_cfg, "--swarm", SWARM, "--trusted-key", fleet.ground_pub,
        "--mavlink", f"udpout:127.0.0.1:{port}", "--id", agent_id,
        "--origin", "0,0,-4", "--exit-policy", "loop", "--join-speed", "3", "--telemetry-rate", "5",
        # the map's continuity-consistent field; its recommended `kinetic` mode deviates up to the walls,
        # and at this map's 8 m/s a vehicle can cross one into the `hold` geofence (docs/simulation.md)
        "--mode", "staggered"])


def _stop_rank(p) -> int:
    # agents first (they put their vehicle in hold while the emulator still runs), then the
    # publisher, then the emulators
    return 0 if p.name.startswith("agent") else 1 if p.name == "publisher" else 2


@pytest.fixture(scope="module")
def fleet(tmp_path_factory, request):
    d = tmp_path_factory.mktemp("fleet")
    procs = Processes(d / "logs")
    request.addfinalizer(lambda: procs.stop_all(order=_stop_rank))
    t0 = time.monotonic()

    ok(run_cli(ground("keygen", "-o", d / "ground")))
    ok(run_cli(ground("keygen", "-o", d / "stranger")))
    map_path = d / "tunnel.fiscmap"
    fit_map(map_path, d / "ground.key")
    good_copy = d / "good.fiscmap"
    shutil.copyfile(map_path, good_copy)
    good = inspect(map_path, trusted=d / "ground.pub")
    assert good["signed"]

    port = free_tcp_port()
    hub = write_zenoh_config(d / "hub.json5", [f"tcp/127.0.0.1:{port}"], [])
    member = write_zenoh_config(d / "member.json5", ["tcp/127.0.0.1:0"], [f"tcp/127.0.0.1:{port}"])
    f = Fleet(d, procs, hub, member, map_path, good_copy, d / "ground.key", d / "ground.pub", d / "stranger.key",
              good, t0)

    # three vehicles come up before the ground: their agents wait on the ground for a map
    for i in AGENT_IDS:
        if i != LATE_AGENT:
            _start_vehicle(f, i)
    procs.start("publisher", ground("publish", map_path, "--swarm", SWARM, "--zenoh-config", hub))
    early = [i for i in AGENT_IDS if i != LATE_AGENT]
    await_fleet(f, lambda a: a["map_sha256"] == good["sha256"] and a["state"] == "STANDBY"
                and a["authority"] == "not-ours", 45, "the early agents to receive the map, hovering not theirs", early)
    # the ground hands the hovering vehicles over, and gives the fleet its go
    sent = cmd(f, "takeover", "--agents", ",".join(str(i) for i in early))
    assert sent["target"] == early, sent
    cmd(f, "go")
    # the publisher is serving: now the late joiner starts (it gets the map and the go by query)
    _start_vehicle(f, LATE_AGENT)
    return f


def test_signed_map_to_four_agents_stranger_map_refused_hold_and_resume(fleet):
    good = fleet.good
    x_max = good["grid"]["origin_m"][0] + good["grid"]["shape"][0] * good["grid"]["cell_size_m"]

    # 1. every agent flies the signed map: seen in FLOW, inside the tunnel, on the good map
    inside: set[int] = set()

    def flying_the_map(a: dict) -> bool:
        on_map = (a["map_sha256"] == good["sha256"] and a["map_version"] == good["map_version"]
                  and "map_unsigned" not in a["flags"] and a["maps_rejected"] == 0)
        if on_map and a["state"] == "FLOW" and a["cv_index"] >= 0 and 0.0 <= a["position_m"][0] <= x_max \
                and {"armed", "mavlink_ok", "position_fresh"} <= set(a["flags"]):
            inside.add(a["id"])
        return on_map and a["id"] in inside

    await_fleet(fleet, flying_the_map, ADMISSION_WAIT_S + 30 + WINDOW_GIVEN_UP_S,
                "every agent to fly the signed map inside the tunnel")
    t_flying = time.monotonic() - fleet.started_s

    # 2. a stranger's newer map is served (the file is replaced; the publisher re-serves it):
    #    every agent refuses it (reason "signature") and keeps flying the good map
    serve_stranger_map(fleet)
    after = status(fleet)
    assert sorted(after) == list(AGENT_IDS), after
    for a in after.values():
        assert a["map_sha256"] == good["sha256"] and a["map_version"] == good["map_version"], a
        assert a["state"] in FLYING, a  # still flying the good map

    # 3. fleet hold, then resume (signed commands, acknowledged in telemetry)
    sent = cmd(fleet, "hold")
    assert sent["subscribers_matched"] and sent["acked"] == list(AGENT_IDS), sent
    await_fleet(fleet, lambda a: a["state"] == "HOLD" and a["ack_command"] == "hold" and a["ack_seq"] == sent["seq"]
                and speed(a) < 0.5, 30, "every agent to hold and stop")
    sent = cmd(fleet, "resume")
    assert sent["subscribers_matched"] and sent["acked"] == list(AGENT_IDS), sent
    # every agent is seen moving after the resume; one may then wait at its staging point for its
    # admission window (speed 0 in JOIN), or hold later on this map's geofence (8 m/s at the outlet's wall),
    # so the moves need not be simultaneous: an agent counts once seen flying on
    moved: set[int] = set()

    def flying_on(a: dict) -> bool:
        acked = a["state"] in FLYING and a["ack_command"] == "resume" and a["ack_seq"] == sent["seq"]
        if acked and speed(a) > 0.5:
            moved.add(a["id"])
        return a["id"] in moved

    resumed = await_fleet(fleet, flying_on, ADMISSION_WAIT_S + 15, "every agent to fly on")
    for a in resumed.values():  # the refused map is still refused, the good one still flown
        assert a["map_sha256"] == good["sha256"] and a["reject_reason"] == "signature", a
    assert not fleet.procs.dead(), fleet.procs.report()
    print(f"fleet flying the map {t_flying:.1f} s after start; test done {time.monotonic() - fleet.started_s:.1f} s")


def test_monitor_aggregates_the_fleet_telemetry_into_per_cv_density_and_pressure(fleet):
    good = fleet.good
    resumed = status(fleet)
    if any(a["state"] == "HOLD" for a in resumed.values()):  # left held by a failed test above
        cmd(fleet, "resume")
    # start recording while someone is inside the tunnel
    await_fleet(fleet, lambda a: a["state"] in FLYING, 60, "every agent to fly")
    poll(lambda: any(a["state"] == "FLOW" for a in status(fleet, 0.5).values()), 30, period_s=0.0)

    rec = fleet.dir / "flight.mcap"
    out = ok(run_cli(ground("monitor", "--swarm", SWARM, "--zenoh-config", fleet.member_cfg,
                            "--map", fleet.good_copy, "--record", rec, "--duration", "6", "--sample-period", "0.2"),
                     timeout_s=60))
    assert " 0 dropped" in out and "recorded to" in out, out[-2000:]
    rep = fleet.dir / "replay"
    ok(run_cli(ground("replay", rec, "-o", rep, "--min-samples", "1", "--no-figures")))

    metrics = json.loads((rep / "metrics.json").read_text())
    assert metrics["agents"] == len(AGENT_IDS), metrics
    assert metrics["map"]["sha256"] == good["sha256"] and metrics["spoofed"] == 0 and metrics["bad_messages"] == 0
    assert metrics["messages"] >= len(AGENT_IDS) * 5 * 6 * 0.5, metrics  # ~5 Hz per agent for 6 s
    assert metrics["n_cv_compared"] > 0, metrics

    with open(rep / "fields.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == good["n_cv"]
    visited = [r for r in rows if int(r["samples"]) > 0]
    assert visited, "no CV received a telemetry sample"
    assert all(float(r["swarm_density"]) > 0 and math.isfinite(float(r["swarm_pressure"])) for r in visited)
    assert all(float(r["swarm_density"]) == 0 for r in rows if int(r["samples"]) == 0)


def test_monitor_started_while_a_strangers_map_is_served_refuses_it_and_watches_the_fleet(fleet):
    serve_stranger_map(fleet)
    out = run_cli(ground("monitor", "--swarm", SWARM, "--zenoh-config", fleet.member_cfg,
                         "--trusted-key", fleet.ground_pub, "--duration", "3", "--map-timeout", "3"), timeout_s=60)
    ok(out)
    assert "map was refused" in out.stderr and "signature" in out.stderr, out.stderr
    got = re.search(r"(\d+) messages received, 0 dropped", out.stdout)
    assert got and int(got.group(1)) > 0, out.stdout[-2000:]
    assert "refused a map: agents 1, 2, 3, 4" in out.stdout, out.stdout[-2000:]  # the dashboard's alarm
