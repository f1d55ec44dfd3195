"""Oracle of ``Runner.step()``'s outputs (issue 40: the agent's step made faster, its behaviour unchanged).

Deterministic flights on a simulated clock (``bench_agent.ManualClock``; the wall clock is the same
clock) drive a ``Runner`` tick by tick; every tick's mission output, the setpoint sent (NED) and the
telemetry snapshot are recorded (``repr`` of every float) and compared with those recorded from the code
before the optimisation (``step_outputs_golden.json``): everything but the floats exactly (a digest of the
records with each float replaced by ``F``), the floats by one weighted sum per tick within ``TOL``.  The
floats are not compared bit for bit: numpy takes different SIMD paths on different CPUs, and the staggered
and kinetic flights then differ in the last bits (3.6e-15 relative on an AVX-512 host, 2026-12-06;
the golden was rewritten then from the code that had matched the pre-optimisation digests bit for bit on the
earlier host).  The flights:

- ``bench``: ``bench_agent.BenchLink``'s track (back and forth along the duct), mode ``slot`` (the
  ``Runner.step()`` benchmark's own flight);
- ``plant-<mode>``: a vehicle that flies the agent's setpoints (first-order velocity lag, no noise)
  from the inlet with exit policy ``loop``: FLOW, past the outlet, JOIN back to the inlet, FLOW again, in
  the map's recommended mode (``kinetic`` under tracking: the staggered field with the deviations turned
  across the stream, since 2026-12-07, when its record was rewritten; ``staggered`` before) and in ``slot``, ``mean``, ``interpolated``
  and explicit ``kinetic``: ``plant-kinetic`` with the deviations isotropic (``KineticAxes.ISOTROPIC``, the
  only way before 2026-12-07, recorded then), ``plant-kinetic-cross-stream`` turned across the stream (the
  default since, its record added then).

Rewritten on 2026-12-07 for an intended change: the join's final leg timed to its crossing
(``spacing.final_leg_speed_m_s``), which crosses the inlet later in the ``plant-*`` flights' second pass.

Regenerate the golden file (only for an intended change of behaviour) with
``python tests/fisc_agent/test_step_outputs_unchanged.py --write``.
"""

from __future__ import annotations

import hashlib
import json
import re
import sys
from dataclasses import replace
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import bench_agent  # noqa: E402

from fisc_agent.config import AgentConfig, ExitPolicy  # noqa: E402
from fisc_agent.flight.mission_types import FleetOrder, MissionCommand  # noqa: E402
from fisc_agent.flight.tracking import KineticAxes, TrackingConfig  # noqa: E402
from fisc_agent.mavlink.interfaces import PositionSample  # noqa: E402
from fisc_agent.runner import Runner  # noqa: E402

GOLDEN = Path(__file__).with_name("step_outputs_golden.json")
FLOAT = re.compile(r"(?<![\w.])[-+]?(?:\d+\.\d*(?:e[-+]?\d+)?|\d+e[-+]?\d+)")
"""A float's repr in a record (integers, ``inf`` and ``nan`` stay in the exactly compared text)."""
TOL = 1e-11
"""Tolerance of a tick's float sum (``_float_sum``): a last-bit difference of 20 floats moves it by < 1e-13; a
change of 1e-9 in a float near 1 by 2.5e-10 (in one near 10, 8e-12: the sum squashes large floats)."""
DT_S = 0.05
PLANT_MODES = ("recommended", "slot", "mean", "interpolated", "kinetic", "kinetic-cross-stream")


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

    def latest_thrust_accel(self):
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
        axes = KineticAxes.CROSS_STREAM if mode.endswith("-cross-stream") else KineticAxes.ISOTROPIC
        mode = mode.removesuffix("-cross-stream")
        cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=3, state_file=None,
                          mode=None if mode == "recommended" else mode, exit_policy=ExitPolicy.LOOP,
                          tracking=TrackingConfig(kinetic_axes=axes))
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
        # a field added after the records (the GNSS receiver's velocity): none in these flights, left out of them
        assert snap.gnss_velocity_map_m_s is None
        rec = repr((tuple(out), tuple(sent), snap))
        records.append(rec.replace(", gnss_velocity_map_m_s=None)", ")"))
    return records


def _float_sum(record: str) -> float:
    """Sum of w_k x_k / (1 + |x_k|) over the record's floats x_k, w_k = 1 + k / 7: each float counts by its
    relative size (a last bit of 1005.05 no more than one of 1.06), and a changed sign or order shows."""
    total = 0.0
    for k, m in enumerate(FLOAT.finditer(record)):
        x = float(m.group())
        total += (1.0 + k / 7.0) * x / (1.0 + abs(x))
    return total


def _summary(records: list[str]) -> dict:
    states: list[str] = []
    for rec in records:
        state = rec.split("<State.", 1)[1].split(":", 1)[0].lower()
        if not states or states[-1] != state:
            states.append(state)
    skeleton = "\n".join(FLOAT.sub("F", rec) for rec in records)
    return {"ticks": len(records), "skeleton_sha256": hashlib.sha256(skeleton.encode()).hexdigest(),
            "states": states, "float_sums": [_float_sum(rec) for rec in records],
            "every_100th": records[::100]}


FLIGHTS = {"bench": 600, **{f"plant-{m}": 1400 for m in PLANT_MODES}}


def _golden() -> dict:
    return json.loads(GOLDEN.read_text())


@pytest.mark.parametrize("name", list(FLIGHTS))
def test_the_steps_outputs_are_those_recorded_before_the_optimisation(name):
    want = _golden()[name]
    records = _fly(name, FLIGHTS[name])
    got = _summary(records)
    assert got["ticks"] == want["ticks"]
    assert got["states"] == want["states"]
    for k, (g, w) in enumerate(zip(got["every_100th"], want["every_100th"])):
        assert FLOAT.sub("F", g) == FLOAT.sub("F", w), f"tick {100 * k} differs beyond its floats"
    assert got["skeleton_sha256"] == want["skeleton_sha256"], "a tick differs beyond its floats"
    for k, (rec, w) in enumerate(zip(records, want["float_sums"])):
        assert abs(_float_sum(rec) - w) <= TOL, (k, _float_sum(rec), w, rec)


def test_the_float_comparison_tells_a_last_bit_from_a_change():
    """The tolerance of the float sums: a last-bit difference passes, a change of 1e-9 in one float fails."""
    rec = "(1.064271955259414, -0.10873884693235758, 1005.0499999999954, 156, inf)"
    assert FLOAT.findall(rec) == ["1.064271955259414", "-0.10873884693235758", "1005.0499999999954"]
    for old, new, same in [("1.064271955259414", "1.064271955259415", True), ("1005.0499999999954", "1005.05", True),
                           ("1.064271955259414", "1.064271956259414", False),
                           ("1.064271955259414", "-1.064271955259414", False),
                           ("-0.10873884693235758", "-0.10873884593235758", False)]:
        assert (abs(_float_sum(rec.replace(old, new)) - _float_sum(rec)) <= TOL) == same, new


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
