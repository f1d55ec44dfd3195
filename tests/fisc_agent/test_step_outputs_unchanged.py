"""Oracle of ``Runner.step()``'s outputs (issue 40: the agent's step made faster, its behaviour unchanged).

Deterministic flights on a simulated clock (``bench_agent.ManualClock``; the wall clock is the same
clock) drive a ``Runner`` tick by tick; every tick's mission output, the setpoint sent (NED) and the
telemetry snapshot are recorded exactly (``repr`` of every float) and compared with the digests
recorded from the code before the optimisation (``step_outputs_golden.json``).  The flights:

- ``bench``: ``bench_agent.BenchLink``'s track (back and forth along the duct), mode ``slot`` (the
  ``Runner.step()`` benchmark's own flight);
- ``plant-<mode>``: a vehicle that flies the agent's setpoints (first-order velocity lag, no noise)
  from the inlet with exit policy ``loop``: FLOW, past the outlet, JOIN back to the inlet, FLOW again, in
  the map's recommended mode (``staggered`` under tracking) and in ``slot``, ``mean``, ``interpolated``
  and explicit ``kinetic``.

Regenerate the golden file (only for an intended change of behaviour) with
``python tests/fisc_agent/test_step_outputs_unchanged.py --write``.
"""

from __future__ import annotations

import hashlib
import json
import sys
from dataclasses import replace
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import bench_agent  # noqa: E402

from fisc_agent.config import AgentConfig, ExitPolicy  # noqa: E402
from fisc_agent.flight.mission_types import FleetOrder, MissionCommand  # noqa: E402
from fisc_agent.mavlink.interfaces import PositionSample  # noqa: E402
from fisc_agent.runner import Runner  # noqa: E402

GOLDEN = Path(__file__).with_name("step_outputs_golden.json")
DT_S = 0.05
PLANT_MODES = ("recommended", "slot", "mean", "interpolated", "kinetic")


class PlantLink(bench_agent.BenchLink):
    """A vehicle that flies the setpoints it is sent: velocity lag ``tau_s``, exact Euler steps."""

    def __init__(self, clock, start_ned_m, tau_s: float = 0.3) -> None:
        super().__init__(clock)
        self.pos = tuple(float(v) for v in start_ned_m)
        self.vel = (0.0, 0.0, 0.0)
        self.sp = (0.0, 0.0, 0.0)
        self.tau_s = tau_s
        self.t_last = clock()
        self.sent: list[tuple[float, float, float]] = []

    def latest_gnss_velocity(self):
        return None

    def latest_position(self):
        now = self.clock()
        dt = now - self.t_last
        if dt > 0.0:
            k = min(1.0, dt / self.tau_s)
            self.vel = tuple(v + k * (s - v) for v, s in zip(self.vel, self.sp))
            self.pos = tuple(p + dt * v for p, v in zip(self.pos, self.vel))
            self.t_last = now
        return PositionSample(now, self.pos, self.vel, now - 900.0)

    def send_velocity_ned(self, vn, ve, vd):
        super().send_velocity_ned(vn, ve, vd)
        self.sp = (vn, ve, vd)
        self.sent.append(self.sp)


def _fly(name: str, ticks: int) -> list[str]:
    """Every tick's record (exact reprs) of one flight."""
    clock = bench_agent.ManualClock()
    cmap = bench_agent.load_map("default")
    if name == "bench":
        cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=7, mode="slot", state_file=None)
        link = bench_agent.BenchLink(clock)
    else:
        mode = name.removeprefix("plant-")
        cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=3, state_file=None,
                          mode=None if mode == "recommended" else mode, exit_policy=ExitPolicy.LOOP)
        link = PlantLink(clock, (0.5, 0.1, -10.0))
    sent: list = []
    inner_send = link.send_velocity_ned

    def send(vn, ve, vd):
        sent.append((vn, ve, vd))
        inner_send(vn, ve, vd)

    link.send_velocity_ned = send
    snaps: list = []
    r = Runner(cfg, link, cmap, clock=clock, wall_clock=clock, on_tick=snaps.append)
    records = []
    for i in range(ticks):
        if i == 3:
            r.mission.command(FleetOrder(MissionCommand.TAKEOVER, addressed=True))
        clock.t += DT_S
        del sent[:]
        out = r.step()
        # the default map's version (and so its sha256) is its build time: recorded as "the map in use"
        snap = replace(snaps[-1], map_sha256=snaps[-1].map_sha256 == cmap.sha256,
                       map_version=snaps[-1].map_version == cmap.map_version)
        records.append(repr((tuple(out), tuple(sent), snap)))
    return records


def _summary(records: list[str]) -> dict:
    states: list[str] = []
    for rec in records:
        state = rec.split("<State.", 1)[1].split(":", 1)[0].lower()
        if not states or states[-1] != state:
            states.append(state)
    return {"ticks": len(records), "sha256": hashlib.sha256("\n".join(records).encode()).hexdigest(),
            "states": states, "every_100th": records[::100]}


FLIGHTS = {"bench": 600, **{f"plant-{m}": 1400 for m in PLANT_MODES}}


def _golden() -> dict:
    return json.loads(GOLDEN.read_text())


@pytest.mark.parametrize("name", list(FLIGHTS))
def test_the_steps_outputs_are_those_recorded_before_the_optimisation(name):
    want = _golden()[name]
    got = _summary(_fly(name, FLIGHTS[name]))
    assert got["ticks"] == want["ticks"]
    assert got["states"] == want["states"]
    for k, (g, w) in enumerate(zip(got["every_100th"], want["every_100th"])):
        assert g == w, f"tick {100 * k} differs"
    assert got["sha256"] == want["sha256"]


def test_the_plant_flights_fly_laps_through_join_and_flow():
    """The oracle covers the flying states: the plant flights flow, pass the outlet and join again (``slot``
    does not reach the outlet within its ticks; ``bench`` flies it back and forth)."""
    for name in FLIGHTS:
        if name.startswith("plant-") and name != "plant-slot":
            states = _golden()[name]["states"]
            assert states.count("flow") >= 2 and "join" in states, (name, states)


if __name__ == "__main__":
    if sys.argv[1:] == ["--write"]:
        GOLDEN.write_text(json.dumps({n: _summary(_fly(n, t)) for n, t in FLIGHTS.items()}, indent=1) + "\n")
        print(f"wrote {GOLDEN}")
