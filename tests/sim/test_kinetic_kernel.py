"""The numba kinetic step (``sim.kinetic_step``) against its numpy reference, ``flight_command``.

Tolerance: none.  The kernel spells the reference's operations per agent in the same order (division
by the cell size, floor, clip, the hash, ``cos``/``sin``), so commands, deviation state and whole
swarm trajectories are compared bit for bit, on the default map and on a synthetic staircase, with
agents at walls, beyond the grid and outside the CVs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ..optional import require_module

require_module("numba", extra="jit")

from fisc_agent.map.codec import load_map  # noqa: E402
from fisc_agent.map.kinetic import DeviationState, deviation_phase  # noqa: E402
from fisc_agent.map.lookup import CommandField, FlightSettings, flight_command  # noqa: E402
from sim.kinetic_step import KineticStep  # noqa: E402
from sim.scenarios import seed_positions  # noqa: E402
from sim.swarm import MAP_TO_NED, Swarm, SwarmConfig  # noqa: E402

DEFAULT_MAP = Path(__file__).resolve().parents[2] / "field_maps" / "default.fiscmap"
CELL = 0.5


@pytest.fixture(scope="module")
def default_field() -> CommandField:
    """The repository's default map (schema 2, flown kinetic by default)."""
    return CommandField.from_map(load_map(DEFAULT_MAP))


@pytest.fixture(scope="module")
def staircase() -> CommandField:
    """Six slices, 4 x 3 cells across: a 2 x 1 core in slices 0-1 and 5, the full 4 x 3 in slices 2-4
    (walls on every side, steps outward at slice 2 and inward at 5), random face velocities and
    spreads (a fast, mostly axial flow)."""
    mask = np.zeros((6, 4, 3), dtype=bool)
    mask[:, 1:3, 1] = True
    mask[2:5] = True
    grid = np.full(mask.shape, -1, dtype=np.int64)
    idx = np.argwhere(mask)
    grid[tuple(idx.T)] = np.arange(len(idx))
    n = len(idx)
    rng = np.random.default_rng(3)
    nx, ny, nz = mask.shape
    faces = (2.0 + rng.normal(0, 0.3, (nx + 1, ny, nz)), rng.normal(0, 0.5, (nx, ny + 1, nz)),
             rng.normal(0, 0.5, (nx, ny, nz + 1)))
    mean = np.tile([2.0, 0.0, 0.0], (n, 1))
    return CommandField(origin_m=np.array([0.0, -1.0, 0.3]), cell_size_m=CELL, grid_cv=grid,
                        centers_m=np.array([0.0, -1.0, 0.3]) + (idx + 0.5) * CELL, mean_cmd_m_s=mean,
                        slot_cmd_m_s=mean[:, None, :], n_star=np.ones(n, int), spread_m_s=rng.uniform(0.2, 0.8, n),
                        face_u_m_s=faces)


def _points(field: CommandField, rng: np.random.Generator, m: int) -> np.ndarray:
    """Points over the grid and a cell beyond it, a third of them on a cell face or a hair inside one
    (the wall zones' and the cell rule's boundaries)."""
    shape = np.asarray(field.grid_cv.shape)
    cells = rng.uniform(-1.0, shape + 1.0, (m, 3))
    k = m // 3
    cells[:k] = np.floor(cells[:k]) + rng.choice([0.0, 1e-12, 0.25, 0.75, 1.0 - 1e-12], (k, 3))
    return field.origin_m + cells * field.cell_size_m


@pytest.mark.parametrize("which", ["default_field", "staircase"])
def test_kernel_equals_flight_command_bit_for_bit_over_steps(which, request):
    """Commands (NaN -> 0, NED) and the deviation state equal ``flight_command``'s at every step, with
    the look-ahead, across interval changes, for agents inside, at walls, outside the CVs and beyond
    the grid; the state carried from step to step by each path separately."""
    field = request.getfixturevalue(which)
    rng = np.random.default_rng(11)
    m = 600
    ids = np.arange(m, dtype=np.int64) * 7 + 3
    settings = FlightSettings("kinetic", 0.5, 2.0)
    step = KineticStep.make(field, settings.persistence_s, settings.lookahead_s)
    ref = DeviationState.new(m)
    ref = DeviationState(ref.epoch, ref.sign, ref.direction, deviation_phase(ids))
    mine = DeviationState(ref.epoch.copy(), ref.sign.copy(), ref.direction.copy(), ref.phase.copy())
    pos = _points(field, rng, m)
    vel_map = rng.normal(0, 2.0, (m, 3))
    for k in range(12):
        t_s = 0.7 * k
        cv = field.cv_of(pos)
        want, _, ref = flight_command(field, pos, vel_map, ids, t_s, settings, ref, cv_ids=cv)
        want = np.nan_to_num(want, nan=0.0) * MAP_TO_NED
        got = np.full((m, 3), np.nan)
        step.commands(pos, vel_map * MAP_TO_NED, ids, cv, t_s, mine.epoch, mine.sign, mine.direction, mine.phase,
                      got)
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(mine.epoch, ref.epoch)
        np.testing.assert_array_equal(mine.sign, ref.sign)
        np.testing.assert_array_equal(mine.direction, ref.direction)
        pos = pos + 0.05 * vel_map + rng.normal(0, 0.02, pos.shape)
    assert np.any(mine.sign < 0)  # the walls reflected someone: the test reached the reflection rules
    assert np.any(cv < 0) and np.any(cv >= 0)


def test_start_velocity_equals_flight_command_at_rest(staircase):
    """New agents start at ``flight_command`` without look-ahead, at rest, from a fresh state."""
    rng = np.random.default_rng(5)
    pos = _points(staircase, rng, 300)
    ids = np.arange(100, 400, dtype=np.int64)
    step = KineticStep.make(staircase, 2.0, 0.5)
    want, _, _ = flight_command(staircase, pos, np.zeros_like(pos), ids, 3.3, FlightSettings("kinetic", 0.0, 2.0))
    np.testing.assert_array_equal(step.start_velocity(pos, ids, 3.3), np.nan_to_num(want, nan=0.0))


@pytest.mark.parametrize("which", ["default_field", "staircase"])
def test_swarm_numba_kinetic_run_equals_the_numpy_run(which, request):
    """Whole swarms flown kinetic with the look-ahead, numba against numpy: same positions,
    velocities, deviation state and bookkeeping after 80 steps with agents added every 10."""
    field = request.getfixturevalue(which)
    runs = []
    for backend in ("numpy", "numba"):
        sw = Swarm(field, config=SwarmConfig(mode="kinetic", lookahead_s=0.5, lookup_backend=backend))
        assert (sw._kinetic is not None) == (backend == "numba")
        r = np.random.default_rng(9)
        for k in range(80):
            if k % 10 == 0:
                p = seed_positions(field, r, n_agents=200)
                sw.add_agents(p + r.normal(0, 0.4 * field.cell_size_m, p.shape))
            sw.step()
        runs.append(sw)
    a, b = runs
    assert a.counters == b.counters and a.counters.returned > 0
    for name in ("ids", "pos_m", "vel_ned_m_s", "outside_s"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    for buf in ("_epoch", "_sign", "_dir"):
        np.testing.assert_array_equal(getattr(a, buf)[:a.n], getattr(b, buf)[:b.n])


@pytest.mark.parametrize("t_s", [0.0, 1.999, 2.0, 123.45])
def test_deviation_x_equals_deviation_direction(t_s):
    """The reservoir's admission draws (``sim.kinetic_step.deviation_x``, numba) equal the x component of
    ``deviation_direction`` bit for bit, at and around interval boundaries, ids up to 2**40."""
    from fisc_agent.map.kinetic import deviation_direction
    from sim.kinetic_step import deviation_x

    ids = np.concatenate([np.arange(5000), np.array([2**31 - 1, 2**32, 2**40 + 17])]).astype(np.int64)
    np.testing.assert_array_equal(deviation_x(ids, t_s, 2.0), deviation_direction(ids, t_s, 2.0)[0][:, 0])
    assert deviation_x(np.zeros(0, dtype=np.int64), t_s, 2.0).shape == (0,)
