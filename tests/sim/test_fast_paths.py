"""The numba passes that replaced small numpy passes of the swarm loop (issue 40) give the numpy
reference's bits: agent removal, the prepared plant step, the per-CV moments, entering agents' state."""

from pathlib import Path

import numpy as np
import pytest

from fisc_agent.map.codec import load_map
from fisc_agent.map.kinetic import deviation_phase
from fisc_agent.map.lookup import CommandField
from fisc_ground.fields.swarm_fields import cv_moments
from sim.entry import entry_phase, entry_thrust
from sim.kernels import compact_kernel
from sim.moments import swarm_moments
from sim.plant.model import PlantParams, plant_stepper, step_plant, trim_thrust_accel
from sim.scenarios import seed_positions
from sim.swarm import MAP_TO_NED, Swarm, SwarmConfig

import numba  # noqa: F401  (a dependency of sim: missing means broken, not skipped)

DEFAULT_MAP = Path(__file__).resolve().parents[2] / "field_maps" / "default.fiscmap"


def _numpy_keep(keep, bufs):
    """``Swarm._keep``'s numpy moves on copies of ``bufs``."""
    m = int(np.count_nonzero(keep))
    holes, src = np.flatnonzero(~keep[:m]), np.flatnonzero(keep[m:]) + m
    out = [b.copy() for b in bufs]
    for b in out:
        b[holes] = b[src]
    return m, out


@pytest.mark.parametrize("pattern", ["none", "all", "first", "last", "alternate", "random", "empty"])
def test_compact_kernel_moves_rows_as_the_numpy_removal(pattern):
    rng = np.random.default_rng(3)
    n = 0 if pattern == "empty" else 41
    keep = {"none": np.ones(n, bool), "all": np.zeros(n, bool), "first": np.arange(n) != 0,
            "last": np.arange(n) != n - 1, "alternate": np.arange(n) % 2 == 0, "random": rng.random(n) < 0.7,
            "empty": np.ones(0, bool)}[pattern]
    cap = n + 5  # buffers longer than the agents, as Swarm's
    f3 = [rng.normal(size=(cap, 3)) for _ in range(6)]
    f1 = [rng.normal(size=cap) for _ in range(2)]
    i1 = [rng.integers(-5, 10**6, cap) for _ in range(2)] + [rng.integers(-1, 9, n)]
    m_ref, want = _numpy_keep(keep, f3 + f1 + i1)
    m = compact_kernel()(keep, tuple(f3), tuple(f1), tuple(i1))
    assert m == m_ref == int(keep.sum())
    for got, ref in zip(f3 + f1 + i1, want):
        np.testing.assert_array_equal(got, ref)


@pytest.mark.parametrize("backend", ["numpy", "numba"])
@pytest.mark.parametrize("dt_s", [0.05, 0.013, 0.2])
def test_plant_stepper_equals_step_plant(backend, dt_s):
    rng = np.random.default_rng(7)
    co = PlantParams().coefficients()
    vel, thr = rng.normal(0, 3, (200, 3)), rng.normal(0, 6, (200, 3))
    cmd = rng.normal(0, 8, (200, 3))  # some beyond the tilt and thrust limits
    want = step_plant(*step_plant(vel, thr, cmd, dt_s, co, backend=backend), cmd, dt_s, co, backend=backend)
    step = plant_stepper(co, dt_s, backend)
    step(vel, thr, cmd)
    step(vel, thr, cmd)  # twice: the prepared arguments are reused
    np.testing.assert_array_equal(vel, want[0])
    np.testing.assert_array_equal(thr, want[1])
    empty = np.zeros((0, 3))
    step(empty, empty.copy(), empty.copy())  # no agents: nothing to do, no error


def test_plant_stepper_refuses_bad_arguments():
    with pytest.raises(ValueError, match="dt_s"):
        plant_stepper(PlantParams().coefficients(), 0.0)
    with pytest.raises(ValueError, match="fleet-wide"):
        plant_stepper(PlantParams(mass_kg=np.array([1.0, 2.0])).coefficients(2), 0.05)


@pytest.mark.parametrize("n", [0, 1, 7, 1000])
def test_swarm_moments_equal_cv_moments(n):
    rng = np.random.default_rng(n)
    n_cv = 13
    cv = rng.integers(-1, n_cv, n)
    cv[: min(n, 2)] = [n_cv - 1, -1][: min(n, 2)]  # the last CV and an agent outside
    vel_ned = rng.normal(0, 2, (n, 3)) * rng.lognormal(0, 2, (n, 3))
    ref = rng.normal(0, 1, (n_cv, 3))
    want = cv_moments(cv, vel_ned * MAP_TO_NED, 1.3, n_cv, ref)
    got = swarm_moments(cv, vel_ned, MAP_TO_NED, 1.3, n_cv, ref)
    for name in ("count", "mass_kg", "momentum_kg_m_s", "m_v2_kg_m2_s2", "m_dev2_kg_m2_s2"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)


def test_swarm_moments_refuse_what_cv_moments_refuses():
    cv, vel, ref = np.array([0, 1]), np.ones((2, 3)), np.zeros((2, 3))
    with pytest.raises(ValueError, match="cv_ids"):
        swarm_moments(np.array([0, 2]), vel, MAP_TO_NED, 1.0, 2, ref)  # 2 == n_cv: just outside
    with pytest.raises(ValueError, match="cv_ids"):
        swarm_moments(np.array([0, -2]), vel, MAP_TO_NED, 1.0, 2, ref)
    with pytest.raises(ValueError, match="masses"):
        swarm_moments(cv, vel, MAP_TO_NED, 0.0, 2, ref)
    with pytest.raises(ValueError, match="reference"):
        swarm_moments(cv, vel, MAP_TO_NED, 1.0, 2, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="finite"):
        swarm_moments(cv, np.array([[0, 0, 0], [np.nan, 0, 0]]), MAP_TO_NED, 1.0, 2, ref)
    swarm_moments(np.array([-1]), np.array([[np.nan, 0, 0]]), MAP_TO_NED, 1.0, 2, ref)  # outside: ignored


def test_entry_phase_equals_deviation_phase():
    ids = np.concatenate([np.arange(0, 2000), [2**31 - 1, 2**32 - 1, 2**32, 2**40 + 17]]).astype(np.int64)
    np.testing.assert_array_equal(entry_phase(ids), deviation_phase(ids))
    assert entry_phase(np.zeros(0, np.int64)).shape == (0,)


def test_entry_thrust_equals_trim_thrust_accel():
    rng = np.random.default_rng(11)
    co = PlantParams().coefficients()
    vel = np.concatenate([rng.normal(0, 5, (3000, 3)) * rng.lognormal(0, 1, (3000, 3)),
                          np.zeros((1, 3)), [[40.0, 0.0, 0.0], [0.0, 0.0, 80.0], [0.0, 0.0, -80.0]]])
    np.testing.assert_array_equal(entry_thrust(vel, co), trim_thrust_accel(vel, co))
    per_agent = PlantParams(mass_kg=np.array([1.0, 2.0])).coefficients(2)  # per-agent rows: the numpy path
    np.testing.assert_array_equal(entry_thrust(vel[:2], per_agent), trim_thrust_accel(vel[:2], per_agent))


def test_kinetic_swarm_with_exits_and_inflow_equals_the_numpy_path():
    """A kinetic run on the default map whose agents leave (the compaction) and enter (their phase and
    trim thrust) gives the all-numpy run's state, bit for bit."""
    field = CommandField.from_map(load_map(DEFAULT_MAP))
    runs = []
    for backend in ("numpy", "numba"):
        rng = np.random.default_rng(2)
        sw = Swarm(field, PlantParams(), SwarmConfig(mode="kinetic", lookahead_s=0.5, lookup_backend=backend,
                                                     plant_backend=backend))
        for k in range(60):
            if k % 10 == 0:  # every other batch near the outlet thrown downstream at 6 m/s: some leave
                pos = seed_positions(field, rng, n_agents=150) + ([12.5, 0.0, 0.0] if k % 20 else 0.0)
                sw.add_agents(pos, vel_map_m_s=np.tile([6.0, 0.5, -0.5], (150, 1)) if k % 20 else None)
            sw.step()
        runs.append(sw)
    a, b = runs
    assert a.counters == b.counters and a.counters.exited > 0
    for buf in ("_pos", "_vel", "_thr", "_ids", "_out", "_epoch", "_sign", "_dir", "_phase"):
        np.testing.assert_array_equal(getattr(a, buf)[:a.n], getattr(b, buf)[:b.n], err_msg=buf)


def test_kinetic_reservoir_batches_equal_the_numpy_batch_and_admission():
    """``Reservoir.entering`` in one numba pass draws the same numbers and admits the same agents at the
    same positions as ``_batch`` then ``admit`` (many batches: empty ones, and times across intervals)."""
    from sim.scenarios import Reservoir

    field = CommandField.from_map(load_map(DEFAULT_MAP))
    fast, slow = (Reservoir(field, 0.2, 0.01, kinetic_persistence_s=1.7) for _ in range(2))
    rng_fast, rng_slow = np.random.default_rng(8), np.random.default_rng(8)
    first, admitted, empty = 0, 0, 0
    for b in range(300):
        t_s = 0.2 * b
        pos, ids = fast.entering(rng_fast, first, t_s)
        cand, cv = slow._batch(rng_slow)
        want_pos, want_ids = slow.admit(cand, first, t_s, rng_slow, cv)
        np.testing.assert_array_equal(pos, want_pos)
        np.testing.assert_array_equal(ids, want_ids)
        admitted, empty = admitted + ids.size, empty + (ids.size == 0)
        first += cand.shape[0]
    np.testing.assert_array_equal(fast._carry, slow._carry)
    assert rng_fast.random() == rng_slow.random()  # the same draws consumed
    assert admitted > 0 and empty > 0 and admitted < first  # some batches empty, some candidates refused
