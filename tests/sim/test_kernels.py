"""The fused numba kernels of the swarm step compute what the numpy reference path computes."""

import numpy as np
import pytest

from fisc_agent.map.lookup import CommandField
from sim.kernels import move_kernel, return_commands_kernel
from sim.plant.model import PlantParams
from sim.scenarios import seed_positions, synthetic_tunnel_map
from sim.swarm import MAP_TO_NED, Swarm, SwarmConfig

import numba  # noqa: E402,F401  (a dependency of sim: missing means broken, not skipped)


@pytest.fixture(scope="module")
def field():
    return CommandField.from_map(synthetic_tunnel_map(nx=10, radius_cells=2.0, speed_m_s=1.0))


def outside_points(field, rng, n):
    """Points just outside the tunnel's CVs (within the return radius) and some far away."""
    pts = seed_positions(field, rng, n_agents=n)
    pts[:, 1:] *= rng.uniform(1.0, 2.5, (n, 1))
    return pts


@pytest.mark.parametrize("mode", ["mean", "slot"])
def test_return_commands_kernel_equals_the_numpy_return_policy(field, mode):
    rng = np.random.default_rng(5)
    sw = Swarm(field, config=SwarmConfig(mode=mode, lookup_backend="numpy"))
    sw.add_agents(outside_points(field, rng, 400))
    cv = sw.lookup(sw.pos_m)
    assert 0 < np.count_nonzero(cv < 0) < sw.n  # both branches exercised
    out_s = rng.uniform(0.0, 1.0, sw.n)
    sw.outside_s[...] = out_s
    ref = rng.normal(size=(sw.n, 3))
    got = ref.copy()
    sw._return_commands(np.flatnonzero(cv < 0), ref)
    lk = sw.lookup
    n_out = return_commands_kernel()(
        sw.pos_m, sw.ids, cv, got, sw.outside_s, 0.05, lk._origin, lk._inv_l, lk._hi, lk._strides, lk._near,
        sw._centers_m, sw._mean_speed, sw._mean_ned, sw._slot_ned, sw._n_star, mode == "slot",
        sw.config.return_gain_1_s, sw.config.return_speed_fraction, MAP_TO_NED,
    )
    assert n_out == np.count_nonzero(cv < 0)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-14)  # inside agents' commands untouched
    np.testing.assert_array_equal(sw.outside_s, np.where(cv < 0, out_s + 0.05, 0.0))


def test_move_kernel_is_x_plus_u_dt_in_the_map_frame():
    rng = np.random.default_rng(1)
    pos, vel = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    fdt = MAP_TO_NED * 0.05
    want = pos + vel * fdt
    move_kernel()(pos, vel, fdt)
    np.testing.assert_array_equal(pos, want)


@pytest.fixture(scope="module")
def default_field():
    from fisc_ground.maps.build import load_shipped_default_map

    return CommandField.from_map(load_shipped_default_map())


@pytest.mark.parametrize("mode", ["mean", "slot", "staggered", "kinetic"])
def test_fused_step_gives_the_numpy_trajectories(field, default_field, mode):
    """Whole runs (injection, return policy, escapes, exits) agree agent by agent.  Modes staggered
    and kinetic (on the default map: they need its face velocities) take their commands from
    ``flight_command`` on both paths; the kernels do the lookup, removals, returns and moves."""
    if mode in ("staggered", "kinetic"):
        field = default_field
    runs = []
    for backend in ("numpy", "numba"):
        sw = Swarm(field, PlantParams(), SwarmConfig(mode=mode, lookup_backend=backend, plant_backend=backend,
                                                     escape_grace_s=0.5, lookahead_s=0.5 if mode == "kinetic" else 0.0))
        rng = np.random.default_rng(9)
        for k in range(80):
            if k % 10 == 0:
                sw.add_agents(outside_points(field, rng, 60))
                if field is default_field:  # a 15 m duct: agents in the last slice's CVs exit too
                    last = field.centers_m[field.centers_m[:, 0] > field.centers_m[:, 0].max() - 0.1]
                    sw.add_agents(last + rng.uniform(-0.25, 0.25, last.shape))
            sw.step()
        runs.append(sw)
    a, b = runs
    assert a.counters.returned > 0 and a.counters.escaped > 0 and a.counters.exited > 0
    assert a.counters == b.counters
    np.testing.assert_array_equal(a.ids, b.ids)
    for name in ("pos_m", "vel_ned_m_s", "thrust_ned_m_s2", "outside_s"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-11, err_msg=name)
