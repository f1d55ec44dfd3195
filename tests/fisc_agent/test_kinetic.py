"""The kinetic mode's wall rules on a small staircase that narrows, widens and narrows again."""

from __future__ import annotations

import numpy as np
import pytest

from fisc_agent.map.kinetic import DeviationState, deviation_epoch, kinetic_deviation
from fisc_agent.map.lookup import CommandField

CELL = 0.5
T_S, PERSISTENCE_S = 10.0, 2.0


@pytest.fixture(scope="module")
def staircase() -> CommandField:
    """Five slices along x, one cell high: y cells 1-2 in slices 0-1 and 4, y cells 0-3 in slices 2-3
    (the staircase steps outward on both sides at slice 2 and back inward at slice 4)."""
    mask = np.zeros((5, 4, 1), dtype=bool)
    mask[:, 1:3] = True
    mask[2:4, :] = True
    grid = np.full(mask.shape, -1, dtype=np.int32)
    idx = np.argwhere(mask)
    grid[tuple(idx.T)] = np.arange(len(idx))
    n = len(idx)
    return CommandField(origin_m=np.zeros(3), cell_size_m=CELL, grid_cv=grid, centers_m=(idx + 0.5) * CELL,
                        mean_cmd_m_s=np.zeros((n, 3)), slot_cmd_m_s=np.zeros((n, 1, 3)), n_star=np.ones(n, int))


def test_the_faces_where_the_staircase_steps_outward(staircase):
    """Flagged: the lateral faces of slice 2 that open onto the new cubes; not the straight parts, not
    the new cubes themselves (nothing upstream of them), not where it narrows, never x or z."""
    got = {tuple(int(v) for v in f) for f in np.argwhere(staircase.stepped_out_faces)}
    assert got == {(2, 1, 0, 1, 0), (2, 2, 0, 1, 1)}  # (x, y, z, axis, lower/upper)


def _agent_at(x_cell: int, y_cell: int, y_frac: float = 0.5):
    """One agent in cell (x_cell, y_cell) whose drawn deviation points to -y and was reflected on y."""
    ids = np.array([7])
    epoch = deviation_epoch(ids, T_S, PERSISTENCE_S)
    state = DeviationState(epoch, np.array([[1.0, -1.0, 1.0]]), np.array([[0.0, -1.0, 0.0]]))
    p = np.array([[(x_cell + 0.5) * CELL, (y_cell + y_frac) * CELL, 0.5 * CELL]])
    return p, ids, state


@pytest.mark.parametrize("x_cell, forgotten", [(1, False), (2, True), (3, False)])
def test_a_reflection_is_forgotten_where_its_wall_steps_outward(staircase, x_cell, forgotten):
    """Reflected at the lower wall of slices 0-1, the agent keeps heading away from it while that wall
    runs on beside it (slice 1); where the wall steps outward (slice 2) its drawn direction returns and
    it heads into the newly opened cube; past the step (slice 3, the same width) a reflection is kept."""
    p, ids, state = _agent_at(x_cell, 1)
    d, new = kinetic_deviation(staircase, p, ids, T_S, PERSISTENCE_S, state)
    assert new.sign[0, 1] == (1.0 if forgotten else -1.0)
    assert d[0, 1] == (-1.0 if forgotten else 1.0)
    np.testing.assert_array_equal(new.direction, state.direction)


def test_a_forgotten_reflection_still_turns_at_the_next_wall(staircase):
    """Restored at the step, the drawn direction carries the agent into the newly opened cube, whose
    own wall reflects it again as usual."""
    p, ids, state = _agent_at(2, 1)
    _, state = kinetic_deviation(staircase, p, ids, T_S, PERSISTENCE_S, state)
    p[0, 1] = 0.1 * CELL  # moved into the new cube, near its lower wall
    assert deviation_epoch(ids, T_S + 0.2, PERSISTENCE_S) == state.epoch  # the same interval
    d, new = kinetic_deviation(staircase, p, ids, T_S + 0.2, PERSISTENCE_S, state)
    assert d[0, 1] == 1.0 and new.sign[0, 1] == -1.0
