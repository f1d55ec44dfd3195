"""``benchmarks/bench_agent.py`` measures an agent that flies: handed its vehicle, streaming setpoints
in FLOW (it once measured an idle agent, held by the authority and position-gate rules)."""

from __future__ import annotations

import sys
from pathlib import Path

from fisc_agent.flight.mission_types import Authority, State

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import bench_agent  # noqa: E402


def test_the_runner_step_bench_flows_and_sends_a_setpoint_every_tick():
    cmap = bench_agent.load_map("default")
    us, nbytes, state = bench_agent.bench_runner_step(cmap, n=400)
    assert state == State.FLOW and nbytes > 0 and us > 0


def test_the_bench_track_is_continuous_so_the_position_gate_keeps_it():
    clock = bench_agent.ManualClock(0.0)
    link = bench_agent.BenchLink(clock)
    xs, vs = [], []
    for _ in range(600):  # 30 s at 2 m/s: both ends of the 14 m track
        clock.t += 0.05
        p = link.latest_position()
        xs.append(p.pos_ned_m[0])
        vs.append(p.vel_ned_m_s[0])
    steps = [abs(b - a) for a, b in zip(xs, xs[1:])]
    assert max(steps) <= 2.0 * 0.05 + 1e-9  # never a jump
    assert min(xs) >= 0.3 - 1e-9 and max(xs) <= 14.3 + 1e-9 and {-2.0, 2.0} == set(vs)


def test_a_given_vehicle_is_under_the_agents_command():
    cmap = bench_agent.load_map("default")
    from fisc_agent.config import AgentConfig
    from fisc_agent.runner import Runner

    clock = bench_agent.ManualClock()
    r = Runner(AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=7, state_file=None),
               bench_agent.BenchLink(clock), cmap, clock=clock)

    def tick():
        clock.t += 0.05
        r.step()

    bench_agent.given_the_vehicle(r, tick)
    assert r.mission.authority == Authority.COMMAND and r.mission.state == State.FLOW
