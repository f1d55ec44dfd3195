"""Algorithm 1 stepping core: CV assignment, commands, bookkeeping, return/escape policy."""

import dataclasses

import numpy as np
import pytest

from fisc_agent.map.lookup import CommandField
from sim.scenarios import seed_positions, synthetic_tunnel_map
from sim.cv_lookup import CVLookup
from sim.swarm import MAP_TO_NED, Swarm, SwarmConfig


@pytest.fixture(scope="module")
def field():
    return CommandField.from_map(synthetic_tunnel_map(nx=10, radius_cells=2.0, speed_m_s=1.0))


def brute_force_nearest(points, centers):
    d2 = ((points[:, None, :] - centers[None, :, :]) ** 2).sum(axis=2)
    return np.argmin(d2, axis=1)


def test_cv_assignment_matches_brute_force_nearest_centre_inside_cvs(field):
    rng = np.random.default_rng(3)
    pts = seed_positions(field, rng, n_agents=2000)
    got = CVLookup(field)(pts)
    assert np.all(got >= 0)
    np.testing.assert_array_equal(got, brute_force_nearest(pts, field.centers_m))
    np.testing.assert_array_equal(got, field.cv_of(pts))


def test_lookup_is_minus_one_outside_cvs_and_return_table_points_to_a_nearby_cv(field):
    lk = CVLookup(field, margin=2)
    outside = np.array([[1.0, 0.9, 0.9], [1.0, -0.9, 0.9], [-0.3, 0.1, 0.1], [1.0, 5.0, 5.0]])
    assert np.all(lk(outside) == -1)
    near = lk.nearest(outside)
    assert np.all(near[:3] >= 0) and near[3] == -1
    d = np.linalg.norm(field.centers_m[near[:3]] - outside[:3], axis=1)
    assert np.all(d < 2 * field.cell_size_m)


def test_agents_follow_the_mean_command_and_advance(field):
    sw = Swarm(field, config=SwarmConfig(mode="mean"))
    pos = np.array([[0.6, 0.1, 0.1], [1.1, -0.2, 0.3]])
    sw.add_agents(pos)
    cv = sw.assign()
    np.testing.assert_allclose(sw.velocity_map(), field.mean_cmd_m_s[cv])  # starts at its command
    sw.step()
    # steady flight at the command: x advances by u dt, y/z stay
    np.testing.assert_allclose(sw.pos_m[:, 0], pos[:, 0] + field.mean_cmd_m_s[cv, 0] * 0.05, atol=2e-3)
    np.testing.assert_allclose(sw.pos_m[:, 1:], pos[:, 1:], atol=2e-3)


def test_map_to_ned_flips_z_for_the_plant(field):
    sw = Swarm(field)
    sw.add_agents(np.array([[0.6, 0.1, 0.1]]), vel_map_m_s=np.array([[1.0, 0.0, 0.5]]))
    assert sw.vel_ned_m_s[0, 2] == pytest.approx(-0.5)  # climbing in the map = negative NED z
    np.testing.assert_allclose(sw.velocity_map(), [[1.0, 0.0, 0.5]])
    assert tuple(MAP_TO_NED) == (1.0, 1.0, -1.0)


def test_slot_mode_flies_the_hashed_fitted_vector(field):
    sw = Swarm(field, config=SwarmConfig(mode="slot"))
    pos = seed_positions(field, np.random.default_rng(0), n_agents=50)
    sw.add_agents(pos)
    cmd = field.command(pos, sw.ids, "slot")
    np.testing.assert_allclose(sw.velocity_map(), cmd)
    assert np.ptp(cmd[:, 1]) > 0.3  # the +/- spread is realised across agents


def test_agents_past_the_outlet_are_removed_and_counted(field):
    sw = Swarm(field)
    x_out = sw.x_outlet_m
    sw.add_agents(np.array([[x_out - 0.01, 0.1, 0.1], [1.0, 0.1, 0.1]]))
    for _ in range(3):
        sw.step()
    sw.assign()
    c = sw.counters
    assert (c.exited, c.escaped, sw.n) == (1, 0, 1)
    assert c.injected == sw.n + c.exited + c.escaped


def test_sideways_agent_is_steered_back_within_grace(field):
    sw = Swarm(field, config=SwarmConfig(escape_grace_s=5.0))
    sw.add_agents(np.array([[1.0, 0.8, 0.8]]), vel_map_m_s=np.zeros((1, 3)))  # corner cell without a CV
    assert sw.assign()[0] == -1
    for _ in range(60):
        sw.step()
    assert sw.assign()[0] >= 0 and sw.counters.escaped == 0 and sw.counters.returned > 0


@pytest.mark.parametrize("backend", ["numpy", "auto"])
def test_agent_beside_a_stagnant_cv_is_steered_back(field, backend):
    at = np.array([[1.0, 0.8, 0.8]])  # corner cell without a CV
    near = CVLookup(field).nearest(at)[0]
    mean = field.mean_cmd_m_s.copy()
    mean[near] *= 1e-3  # its nearest CV barely moves (a boundary layer, a separation)
    stagnant = dataclasses.replace(field, mean_cmd_m_s=mean)
    centre = field.origin_m + (field.cell_of(at) + 0.5) * field.cell_size_m  # the table's point
    assert CVLookup(stagnant).nearest(at)[0] == stagnant.return_cv_within(centre)[0] != near
    sw = Swarm(stagnant, config=SwarmConfig(escape_grace_s=5.0, lookup_backend=backend))
    sw.add_agents(at, vel_map_m_s=np.zeros((1, 3)))
    for _ in range(60):
        sw.step()
    # a pull capped at a fraction of the stagnant CV's own speed (1 mm/s) would leave it outside
    assert sw.assign()[0] >= 0 and sw.counters.escaped == 0


def test_agent_outside_too_long_escapes(field):
    sw = Swarm(field, config=SwarmConfig(escape_grace_s=0.2, return_speed_fraction=0.0))
    sw.add_agents(np.array([[1.0, 0.8, 0.8]]), vel_map_m_s=np.zeros((1, 3)))
    for _ in range(40):
        sw.step()
    sw.assign()
    assert sw.counters.escaped == 1 and sw.n == 0


def test_agent_far_outside_escapes_immediately(field):
    sw = Swarm(field)
    sw.add_agents(np.array([[1.0, 4.0, 4.0]]), vel_map_m_s=np.zeros((1, 3)))
    sw.assign()
    assert sw.counters.escaped == 1


def test_mass_conservation_over_a_long_run_with_removals(field):
    sw = Swarm(field, config=SwarmConfig(mode="slot"))
    rng = np.random.default_rng(1)
    for k in range(200):
        if k % 10 == 0:
            sw.add_agents(seed_positions(field, rng, x_axial_m=0.5))
        sw.step()
        c = sw.counters
        assert c.injected == sw.n + c.exited + c.escaped
    assert sw.counters.exited > 0
    assert len(np.unique(sw.ids)) == sw.n  # compaction kept identities intact


def test_interpolated_mode_runs_and_commands_are_finite(field):
    sw = Swarm(field, config=SwarmConfig(mode="interpolated"))
    sw.add_agents(seed_positions(field, np.random.default_rng(2), n_agents=100))
    for _ in range(10):
        sw.step()
    assert np.all(np.isfinite(sw.pos_m))


def test_bad_mode_is_refused():
    with pytest.raises(ValueError, match="mode"):
        SwarmConfig(mode="fastest")


@pytest.mark.parametrize("mode", ["mean", "slot"])
def test_fused_numba_lookup_matches_the_numpy_path(field, mode):
    runs = []
    for backend in ("numpy", "numba"):
        sw = Swarm(field, config=SwarmConfig(mode=mode, lookup_backend=backend))
        r = np.random.default_rng(7)
        for k in range(60):
            if k % 5 == 0:
                sw.add_agents(seed_positions(field, r, x_axial_m=0.5) + [0.0, 0.0, 0.3 * (k % 2)])
            sw.step()
        runs.append((sw.pos_m.copy(), sw.ids.copy(), sw.assign().copy(), sw.counters))
    (pa, ia, ca, na), (pb, ib, cb, nb) = runs
    np.testing.assert_array_equal(ia, ib)
    np.testing.assert_allclose(pa, pb, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(ca, cb)
    assert (na.exited, na.escaped, na.returned) == (nb.exited, nb.escaped, nb.returned)


def test_lookahead_point_is_position_plus_velocity_times_lead():
    from fisc_agent.map.lookup import lookahead_point

    p = np.array([[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(lookahead_point(p, np.array([[2.0, 0.0, -1.0]]), 0.5), [[2.0, 2.0, 2.5]])
    with pytest.raises(ValueError, match="lead_s"):
        lookahead_point(p, p, -1.0)


@pytest.mark.parametrize("mode", ["mean", "slot", "interpolated"])
def test_lookahead_flies_the_command_of_the_cv_ahead(field, mode):
    """An agent 0.05 m before a CV face moving at 1 m/s along x: with t_lead = 0.5 s it flies the
    next CV's command, without look-ahead its own; a look-ahead point outside the CVs keeps its own."""
    l = field.cell_size_m
    x_face = field.origin_m[0] + 3 * l
    pos = np.array([[x_face - 0.05, 0.1, 0.1], [x_face - 0.05, 0.1, 0.1]])
    vel = np.array([[1.0, 0.0, 0.0], [0.0, 40.0, 0.0]])  # the second looks far outside the tunnel
    got = {}
    for lead in (0.0, 0.5):
        sw = Swarm(field, config=SwarmConfig(mode=mode, lookahead_s=lead, lookup_backend="numpy"))
        ids = sw.add_agents(pos, vel)
        sw.step()
        got[lead] = sw._cmd[:2] * MAP_TO_NED
        own = field.command(pos, ids, mode)
        ahead = field.command(pos + lead * vel * [1, 0, 0], ids, mode)
    np.testing.assert_allclose(got[0.0], own)
    np.testing.assert_allclose(got[0.5][0], ahead[0])
    assert not np.allclose(ahead[0], own[0])
    np.testing.assert_allclose(got[0.5][1], own[1])


def test_lookahead_reduces_the_lag_error_on_an_accelerating_field():
    """The plant lags the command by ~0.6 s; on the accelerating synthetic tunnel the look-ahead
    brings the realised axial speed closer to the command of the CV the agent is in."""
    fld = CommandField.from_map(synthetic_tunnel_map(nx=24, radius_cells=1.0, speed_m_s=3.0, spread_m_s=0.0))
    err = {}
    for lead in (0.0, 0.5):
        sw = Swarm(fld, config=SwarmConfig(lookahead_s=lead))
        sw.add_agents(seed_positions(fld, np.random.default_rng(1), x_axial_m=2.0, n_agents=200))
        e = []
        for _ in range(60):
            sw.step()
            cv = sw.assign()
            ok = cv >= 0
            e.append(np.abs(sw.velocity_map()[ok, 0] - fld.mean_cmd_m_s[cv[ok], 0]).mean())
        err[lead] = np.mean(e[20:])
    assert err[0.5] < 0.5 * err[0.0]


def test_negative_lookahead_is_refused():
    with pytest.raises(ValueError, match="lookahead_s"):
        SwarmConfig(lookahead_s=-0.1)
