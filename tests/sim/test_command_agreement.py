"""One command function: the simulator (vectorised) and the onboard agent (one vehicle) fly the same
commands in every mode (issue 9, item 4), and the kinetic mode's deviation behaves as documented."""

from __future__ import annotations

import numpy as np
import pytest

from fisc_agent.flight.control import ScalarField
from fisc_agent.map.kinetic import WALL_ZONE, DeviationState, kinetic_deviation, kinetic_spread
from fisc_agent.map.lookup import COMMAND_MODES, CommandField, FlightSettings, flight_command
from fisc_ground.maps.build import FitConfig, build_map_from_reference
from sim.swarm import Swarm, SwarmConfig

N_POINTS = 10_000


@pytest.fixture(scope="module")
def field() -> CommandField:
    cmap = build_map_from_reference("analytic", FitConfig(max_speed_m_s=2.0))
    assert cmap.schema_version == 2
    return CommandField.from_map(cmap)


def _random_agents(field: CommandField, rng: np.random.Generator, n: int):
    lo = field.centers_m.min(axis=0) - 0.5 * field.cell_size_m
    hi = field.centers_m.max(axis=0) + 0.5 * field.cell_size_m
    pts = lo + rng.random((n, 3)) * (hi - lo)
    vel = rng.normal(0.0, 1.0, (n, 3)) + np.array([1.0, 0.0, 0.0])
    return pts, vel


@pytest.mark.parametrize("lookahead_s", [0.0, 0.5])
@pytest.mark.parametrize("mode", COMMAND_MODES)
def test_agent_and_simulator_fly_the_same_commands(field, mode, lookahead_s):
    rng = np.random.default_rng(hash((mode, lookahead_s)) % 2**32)
    pts, vel = _random_agents(field, rng, N_POINTS)
    swarm = Swarm(field, config=SwarmConfig(mode=mode, lookahead_s=lookahead_s))
    swarm.add_agents(pts, vel)
    swarm.t_s = 7.3
    sim = swarm.current_commands_map()   # also drops the points the simulator removes at once
    inside = np.all(np.isfinite(sim), axis=1)
    assert inside.sum() > 0.4 * N_POINTS  # the box around the duct is mostly inside the staircase
    sf = ScalarField(field)
    pos, v, ids = swarm.pos_m.copy(), swarm.velocity_map(), swarm.ids.copy()
    agent = np.full_like(sim, np.nan)
    for i in np.flatnonzero(inside):
        sf._dev_state = None  # a fresh vehicle, like the simulator's freshly added agents
        out = sf.flight(tuple(pos[i]), tuple(v[i]), int(ids[i]), 7.3, mode, lookahead_s)
        agent[i] = out if out is not None else np.nan
    np.testing.assert_allclose(agent[inside], sim[inside], rtol=0, atol=1e-9)


def test_kinetic_state_evolves_the_same_one_by_one_and_vectorised(field):
    rng = np.random.default_rng(3)
    pts, vel = _random_agents(field, rng, 40)
    ids = np.arange(40) * 7 + 3
    settings = FlightSettings("kinetic", 0.5, 0.7)
    state = DeviationState.new(40)
    singles = [None] * 40
    flips = 0
    for k in range(60):
        t = 0.1 * k
        moved = pts + 0.05 * k * vel
        cmd, _, state = flight_command(field, moved, vel, ids, t, settings, state)
        for i in range(40):
            c1, _, singles[i] = flight_command(field, moved[i:i + 1], vel[i:i + 1], ids[i:i + 1], t, settings, singles[i])
            np.testing.assert_array_equal(c1[0], cmd[i])
        flips += int(np.sum(state.sign < 0))
    assert flips > 0  # some deviations met a wall and were reflected


def test_kinetic_deviation_has_the_fitted_spread_persists_and_reflects(field):
    ids = np.arange(500)
    # agents at the centre of one interior CV: |cmd - staggered| is that CV's fitted spread
    inner = np.where(field.centers_m[:, 0] > field.origin_m[0] + 2 * field.cell_size_m, field.spread_m_s, -1.0)
    j = int(np.argmax(inner))  # past the inlet cell, where the upstream component fades out
    pts = np.repeat(field.centers_m[j:j + 1], 500, axis=0)
    base = field.command(pts, ids, "staggered")
    settings = FlightSettings("kinetic", 0.0, 2.0)
    cmd, _, st = flight_command(field, pts, np.zeros_like(pts), ids, 10.0, settings)
    np.testing.assert_allclose(np.linalg.norm(cmd - base, axis=1), field.spread_m_s[j], rtol=1e-12)
    dirs = (cmd - base) / field.spread_m_s[j]
    assert np.abs(dirs.mean(axis=0)).max() < 0.15  # isotropic over the swarm
    # the same direction a little later (same persistence interval for most agents), a new one much later
    later, _, _ = flight_command(field, pts, np.zeros_like(pts), ids, 10.2, settings, st)
    same = np.all(np.isclose(later, cmd), axis=1).mean()
    assert same > 0.8
    much_later, _, _ = flight_command(field, pts, np.zeros_like(pts), ids, 30.0, settings, st)
    assert np.all(np.isclose(much_later, cmd), axis=1).mean() < 0.05
    # reflection: a point just inside a wall face of a wall CV, deviation toward the wall -> flipped
    g = field.grid_cv
    occupied = np.argwhere(g >= 0)
    for i, jj, k in occupied:
        if jj + 1 < g.shape[1] and g[i, jj + 1, k] < 0 or jj + 1 == g.shape[1]:
            break
    cell_hi_y = field.origin_m[1] + (jj + 1) * field.cell_size_m
    p = field.origin_m + (np.array([i, jj, k]) + 0.5) * field.cell_size_m
    p[1] = cell_hi_y - 0.5 * WALL_ZONE * field.cell_size_m
    d, new = kinetic_deviation(field, np.repeat(p[None], 500, axis=0), ids, 10.0, 2.0, DeviationState.new(500))
    assert np.all(d[:, 1] <= 0)  # nothing heads into the wall
    assert np.any(new.sign[:, 1] < 0)
    # the inlet is no wall (an open boundary to the reservoir): upstream components stay, unreflected
    q = field.centers_m[field.centers_m[:, 0] < field.origin_m[0] + field.cell_size_m][:1].copy()
    q[0, 0] = field.origin_m[0] + 0.5 * WALL_ZONE * field.cell_size_m
    d, new = kinetic_deviation(field, np.repeat(q, 500, axis=0), ids, 10.0, 2.0, DeviationState.new(500))
    assert d[:, 0].min() < -0.9 and d[:, 0].max() > 0.9 and np.all(new.sign[:, 0] > 0)


def test_kinetic_spread_is_the_fitted_spread_at_the_designed_density():
    """sigma^2 ~ P / rho (an ideal gas): uniform design leaves the fitted spread, a CV designed at half
    the mean density gets sqrt(2) of it, and the pressure 2/3 rho sigma^2 the fit gave is kept."""
    fitted = np.array([0.4, 0.4, 0.2, 0.0])
    np.testing.assert_allclose(kinetic_spread(fitted, np.ones(4)), fitted)
    rho = np.array([0.5, 1.5, 1.0, 1.0])  # mean 1
    got = kinetic_spread(fitted, rho)
    np.testing.assert_allclose(got, fitted * np.sqrt(1.0 / rho))
    np.testing.assert_allclose(rho * got ** 2, fitted ** 2)  # same pressure per CV as fitted at rho = 1
    with pytest.raises(ValueError, match="design density"):
        kinetic_spread(fitted, np.array([1.0, 0.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="one value per CV"):
        kinetic_spread(fitted, np.ones(3))


def test_max_command_speed_bounds_the_face_modes(field):
    from fisc_agent.flight.control import max_command_speed

    rng = np.random.default_rng(11)
    pts, vel = _random_agents(field, rng, 20_000)
    for mode in ("staggered", "kinetic"):
        cmd, _, _ = flight_command(field, pts, vel, np.arange(len(pts)), 3.0, FlightSettings(mode, 0.5))
        speed = np.linalg.norm(cmd[np.all(np.isfinite(cmd), axis=1)], axis=1)
        bound = max_command_speed(field, mode)
        assert speed.max() <= bound + 1e-9
        assert speed.max() > 0.7 * bound  # and is not a loose bound
