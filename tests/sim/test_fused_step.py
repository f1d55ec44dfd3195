"""The one-call fused swarm step (``sim.fused_step``) leaves the state of the multi-pass step bit for bit.

Two swarms from the same agents, one stepping fused and one through the passes (``SwarmConfig(fused=False)``,
the reference), are compared after every step: positions, velocities, thrust states, ids, time outside,
the kinetic deviation state and the counters, on the paper preset and the default (kinetic) preset, with
agents injected mid-run, assignments cached between steps (as ``sim.run.simulate`` samples), agents
leaving at the outlet and sideways, an empty swarm and one agent.
"""

import numpy as np
import pytest

from fisc_agent.map.lookup import CommandField
from sim.plant.model import PlantParams
from sim.run import RunConfig, load_command_map
from sim.scenarios import seed_positions
from sim.swarm import Swarm, SwarmConfig

import numba  # noqa: F401  (a dependency of sim: missing means broken, not skipped)


@pytest.fixture(scope="module")
def maps():
    """The default (schema-2) and the paper preset's (schema-1) maps of the default reference."""
    return {"default": load_command_map(None), "paper": load_command_map(None, preset="paper")}


def pair(field, fused_first: bool = True, **config):
    """The fused swarm and its multi-pass reference, same settings."""
    a = Swarm(field, PlantParams(), SwarmConfig(fused=True, **config))
    b = Swarm(field, PlantParams(), SwarmConfig(fused=False, **config))
    assert a._fused is not None and b._fused is None
    return a, b


def state(sw: Swarm) -> tuple:
    n = sw.n
    return (sw.pos_m, sw.vel_ned_m_s, sw.thrust_ned_m_s2, sw.ids, sw.outside_s, sw._epoch[:n], sw._sign[:n],
            sw._dir[:n], sw._phase[:n], np.array([sw.t_s]))


def assert_same(a: Swarm, b: Swarm, k: int) -> None:
    assert a.n == b.n, f"step {k}"
    assert a.counters == b.counters, f"step {k}"
    for x, y in zip(state(a), state(b)):
        np.testing.assert_array_equal(x, y, err_msg=f"step {k}")


def fly(a: Swarm, b: Swarm, field, steps: int, inject_every: int = 0, assign_every: int = 0, seed: int = 0):
    rng = np.random.default_rng(seed)
    for k in range(steps):
        if inject_every and k % inject_every == 0:
            pts = seed_positions(field, rng, n_agents=20)
            a.add_agents(pts)
            b.add_agents(pts)
        if assign_every and k % assign_every == 0:
            np.testing.assert_array_equal(a.assign(), b.assign())
        a.step()
        b.step()
        assert_same(a, b, k)


@pytest.mark.parametrize("preset", ["paper", "default"])
def test_fused_step_flies_the_presets_bit_for_bit(maps, preset):
    cmap = maps[preset]
    st = RunConfig(preset=preset).flight_settings(cmap)
    field = CommandField.from_map(cmap)
    a, b = pair(field, mode=st.mode, lookahead_s=st.lookahead_s, persistence_s=st.persistence_s)
    pts = seed_positions(field, np.random.default_rng(1), n_agents=600)
    a.add_agents(pts)
    b.add_agents(pts)
    fly(a, b, field, 300, inject_every=25, assign_every=7)
    c = a.counters
    assert c.exited > 0 and c.returned > 0 and a.n > 0  # outflow and the return policy both exercised


@pytest.mark.parametrize("mode", ["mean", "slot"])
def test_fused_step_escapes_and_returns_bit_for_bit(maps, mode):
    """Agents seeded sideways out of the CVs: some fly back, some escape (no CV in reach, or too long out)."""
    field = CommandField.from_map(maps["default"])
    a, b = pair(field, mode=mode, escape_grace_s=1.0)
    pts = seed_positions(field, np.random.default_rng(2), n_agents=500)
    mid = np.asarray(field.centers_m).mean(axis=0)
    pts[:, 1:] = mid[1:] + (pts[:, 1:] - mid[1:]) * np.random.default_rng(3).uniform(1.0, 1.6, (500, 1))
    a.add_agents(pts)
    b.add_agents(pts)
    fly(a, b, field, 200)
    assert a.counters.escaped > 0 and a.counters.returned > 0


def test_fused_step_at_the_outlet(maps):
    """Just before, at and just past the outlet plane x_outlet: removed when x >= x_outlet, at the step
    that finds them there, as the reference does."""
    field = CommandField.from_map(maps["paper"])
    a, b = pair(field)
    pts = seed_positions(field, np.random.default_rng(4), n_agents=5)
    x = a.x_outlet_m
    pts[:, 0] = [x - 1e-9, x, np.nextafter(x, np.inf), x - 0.5, x + 3.0]
    a.add_agents(pts, vel_map_m_s=np.zeros((5, 3)))
    b.add_agents(pts, vel_map_m_s=np.zeros((5, 3)))
    a.step()
    b.step()
    assert_same(a, b, 0)
    assert a.counters.exited == 3 and a.n == 2  # x, nextafter(x) and x + 3 m: out; x - 1e-9 and x - 0.5: in
    fly(a, b, field, 60)


def test_fused_step_of_an_empty_swarm_and_of_one_agent(maps):
    field = CommandField.from_map(maps["paper"])
    a, b = pair(field)
    for k in range(3):  # empty: the clock and the step count move, nothing else
        a.step()
        b.step()
        assert_same(a, b, k)
    assert a.counters.steps == 3 and a.counters.agent_steps == 0 and a.n == 0
    pts = seed_positions(field, np.random.default_rng(5), n_agents=1)
    a.add_agents(pts)
    b.add_agents(pts)
    fly(a, b, field, 400)  # one agent, until it leaves at the outlet and after
    assert a.counters.exited == 1 and a.n == 0


@pytest.mark.parametrize("speed_m_s", [0.0, 12.0])
def test_fused_step_under_the_thrust_limit(maps, speed_m_s):
    """Agents entering fast in random directions saturate the thrust (tilt and thrust limits): the fused
    step's scaled sub-steps give the reference's bits (speed 0: entering at rest)."""
    field = CommandField.from_map(maps["paper"])
    a, b = pair(field)
    rng = np.random.default_rng(6)
    pts = seed_positions(field, rng, n_agents=700)
    vel = rng.normal(scale=speed_m_s, size=(700, 3))
    a.add_agents(pts, vel_map_m_s=vel)
    b.add_agents(pts, vel_map_m_s=vel)
    fly(a, b, field, 40)


@pytest.mark.parametrize("preset,mode", [("paper", None), ("default", None), ("default", "slot"),
                                         ("default", "interpolated")])
def test_several_steps_in_one_call_are_the_steps_one_by_one(maps, preset, mode):
    """``Swarm.step(m)`` (one kernel call looping over m steps where the kernel does the whole step; one call
    per step otherwise) leaves the state and counters of m calls of ``step()``, whether or not an assignment
    is cached before (``sim.run.simulate`` flies the steps between two events so)."""
    cmap = maps[preset]
    st = RunConfig(preset=preset, mode=mode).flight_settings(cmap)
    field = CommandField.from_map(cmap)
    cfg = SwarmConfig(mode=st.mode, lookahead_s=st.lookahead_s, persistence_s=st.persistence_s)
    a, b = Swarm(field, PlantParams(), cfg), Swarm(field, PlantParams(), cfg)
    rng = np.random.default_rng(2)
    for k, m in enumerate([1, 3, 16, 2, 7, 1, 5, 16, 16, 4] * 8):
        pts = seed_positions(field, rng, n_agents=300 if k == 0 else 20)
        a.add_agents(pts)
        b.add_agents(pts)
        if k % 3 == 0:
            np.testing.assert_array_equal(a.assign(), b.assign())
        a.step(m)
        for _ in range(m):
            b.step()
        assert_same(a, b, k)
    assert a.counters.exited > 0 and a.counters.returned > 0
    with pytest.raises(ValueError):
        a.step(0)
