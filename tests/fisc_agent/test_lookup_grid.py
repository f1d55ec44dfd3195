"""CV lookup and commands: O(1) grid lookup equals the paper's nearest-centre assignment."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from fisc_agent.map.hashing import slot_index
from fisc_agent.map.lookup import RETURN_STAGNANT_FRACTION, CommandField


def field_from_mask(mask: np.ndarray, cell: float = 0.5, origin=(0.0, -1.0, -1.0), n_max: int = 4, seed: int = 0):
    rng = np.random.default_rng(seed)
    grid = np.full(mask.shape, -1, dtype=np.int32)
    idx = np.argwhere(mask)
    grid[tuple(idx.T)] = np.arange(len(idx))
    centers = np.asarray(origin) + (idx + 0.5) * cell
    slots = rng.normal(size=(len(idx), n_max, 3))
    n_star = rng.integers(2, n_max + 1, size=len(idx))
    for j, n in enumerate(n_star):
        slots[j, n:] = np.nan
    mean = np.nanmean(slots, axis=1)
    return CommandField(origin_m=np.asarray(origin, float), cell_size_m=cell, grid_cv=grid, centers_m=centers,
                        mean_cmd_m_s=mean, slot_cmd_m_s=slots, n_star=n_star)


@pytest.fixture()
def ball_field():
    n = 8
    c = (np.indices((n, n, n)).transpose(1, 2, 3, 0) + 0.5 - n / 2)
    return field_from_mask(np.linalg.norm(c, axis=-1) < n / 2 - 0.3, origin=(0.0, -2.0, -2.0))


def test_grid_lookup_equals_brute_force_nearest_centre_inside_cvs(ball_field):
    rng = np.random.default_rng(3)
    pts = rng.uniform([0, -2, -2], [4, 2, 2], size=(5000, 3))
    ids = ball_field.cv_of(pts)
    inside = ids >= 0
    assert inside.sum() > 1000
    d2 = ((pts[inside, None, :] - ball_field.centers_m[None]) ** 2).sum(-1)
    np.testing.assert_array_equal(ids[inside], np.argmin(d2, axis=1))


def test_points_outside_every_cv_get_minus_one(ball_field):
    far = np.array([[-1.0, 0, 0], [100.0, 0, 0], [2.0, 1.99, 1.99]])
    assert list(ball_field.cv_of(far)) == [-1, -1, -1]
    assert np.all(np.isnan(ball_field.command(far, np.arange(3), "mean")))


def test_half_open_cells_put_face_points_in_the_upper_cell():
    f = field_from_mask(np.ones((2, 1, 1), bool), origin=(0.0, 0.0, 0.0))
    assert list(f.cv_of(np.array([[0.5, 0.1, 0.1], [0.4999999, 0.1, 0.1]]))) == [1, 0]


def test_nearest_cv_within_finds_the_closest_existing_cv(ball_field):
    p = np.array([[2.0, 1.95, 1.95], [-5.0, 0.0, 0.0]])
    got = ball_field.nearest_cv_within(p, radius_cells=2)
    d2 = ((p[0] - ball_field.centers_m) ** 2).sum(-1)
    assert got[0] == np.argmin(d2)
    assert got[1] == -1


def test_mean_mode_gives_the_cv_mean_command(ball_field):
    pts = ball_field.centers_m[:10]
    np.testing.assert_allclose(ball_field.command(pts, np.arange(10), "mean"), ball_field.mean_cmd_m_s[:10])


def test_slot_mode_picks_a_fitted_vector_deterministically(ball_field):
    j = 5
    pts = np.repeat(ball_field.centers_m[j:j + 1], 200, axis=0)
    ids = np.arange(200)
    cmd = ball_field.command(pts, ids, "slot")
    k = slot_index(ids, j, ball_field.n_star[j])
    np.testing.assert_allclose(cmd, ball_field.slot_cmd_m_s[j, k])
    # every slot is used and the slot mean over many agents approaches the fitted mean
    assert set(np.unique(k)) == set(range(ball_field.n_star[j]))
    np.testing.assert_array_equal(cmd, ball_field.command(pts, ids, "slot"))


def test_slot_hash_is_uniform_enough():
    counts = np.bincount(slot_index(np.arange(100_000), 17, 7), minlength=7)
    assert counts.min() > 0.9 * 100_000 / 7


def test_interpolation_reproduces_a_linear_field_exactly_between_centres():
    f = field_from_mask(np.ones((4, 4, 4), bool), origin=(0.0, 0.0, 0.0))
    lin = lambda p: np.stack([1 + 2 * p[:, 0], -p[:, 1] + 0.5 * p[:, 2], 3 * p[:, 0] - p[:, 2]], axis=1)
    f = CommandField(f.origin_m, f.cell_size_m, f.grid_cv, f.centers_m, lin(f.centers_m), f.slot_cmd_m_s, f.n_star)
    rng = np.random.default_rng(0)
    pts = rng.uniform(0.25, 1.75, size=(500, 3))  # between the outermost centres
    np.testing.assert_allclose(f.command(pts, np.zeros(500), "interpolated"), lin(pts), atol=1e-12)


def test_interpolation_at_a_centre_is_that_cvs_command(ball_field):
    pts = ball_field.centers_m[::7]
    np.testing.assert_allclose(ball_field.command(pts, np.zeros(len(pts)), "interpolated"),
                               ball_field.mean_cmd_m_s[::7], atol=1e-12)


def test_unknown_mode_is_a_clear_error(ball_field):
    with pytest.raises(ValueError, match="unknown command mode 'fast'"):
        ball_field.command(ball_field.centers_m[:1], [0], "fast")


def test_return_target_passes_over_a_stagnant_cv_while_another_is_in_reach(ball_field):
    at = np.array([[2.0, 0.0, 2.3]])  # just above the ball (no CV in its cell)
    assert ball_field.cv_of(at)[0] == -1
    near = int(ball_field.nearest_cv_within(at)[0])
    assert near >= 0 and ball_field.return_cv_within(at)[0] == near  # nothing stagnant: the nearest
    mean = ball_field.mean_cmd_m_s.copy()
    mean[near] *= 1e-3  # a stagnant CV (a boundary layer's, a separation's)
    f = dataclasses.replace(ball_field, mean_cmd_m_s=mean)
    speed = np.linalg.norm(mean, axis=1)
    np.testing.assert_array_equal(f.stagnant, speed < RETURN_STAGNANT_FRACTION * np.median(speed))
    assert f.stagnant[near] and f.nearest_cv_within(at)[0] == near
    target = int(f.return_cv_within(at)[0])
    others = np.flatnonzero(~f.stagnant)
    d = np.linalg.norm(f.centers_m[others] - at, axis=1)
    assert target == others[np.argmin(d)]  # the nearest CV that flows


def test_return_target_is_a_stagnant_cv_only_when_no_other_is_in_reach():
    mask = np.zeros((8, 1, 1), dtype=bool)
    mask[:6] = True  # a row of six CVs along x
    f = field_from_mask(mask, origin=(0.0, 0.0, 0.0))
    mean = np.tile([1.0, 0.0, 0.0], (6, 1))
    mean[5] = [1e-3, 0.0, 0.0]  # the last one stagnant
    f = dataclasses.replace(f, mean_cmd_m_s=mean)
    beyond = np.array([[3.25, 0.25, 0.25]])  # cell 6: no CV
    assert f.return_cv_within(beyond, radius_cells=1)[0] == 5  # only the stagnant CV in reach
    assert f.return_cv_within(beyond, radius_cells=2)[0] == 4  # a flowing one in reach: that one
    assert f.nearest_cv_within(beyond, radius_cells=2)[0] == 5
    assert f.return_cv_within(beyond, radius_cells=0)[0] == -1


def test_locate_reads_the_cell_a_point_clips_to_and_its_own_fraction(ball_field):
    """``CommandField.locate``: one index serves every per-cell table; a point beyond the grid reads
    the cell it clips to (the wall and stepped-out faces, the face velocities), its CV is -1, and its
    fraction is taken in its own (unclipped) cell."""
    rng = np.random.default_rng(5)
    shape = np.array(ball_field.grid_cv.shape)
    f = dataclasses.replace(ball_field, face_u_m_s=tuple(rng.normal(size=tuple(shape + np.eye(3, dtype=int)[a]))
                                                         for a in range(3)))
    pts = rng.uniform([-1.0, -3.0, -3.0], [5.0, 3.0, 3.0], size=(4000, 3))  # a margin of two cells all round
    rows, frac, cv = f.locate(pts)
    cell = np.floor((pts - f.origin_m) / f.cell_size_m).astype(int)
    beyond = np.any((cell < 0) | (cell >= shape), axis=1)
    assert 1000 < beyond.sum() < 3500
    clipped = tuple(np.clip(cell, 0, shape - 1).T)
    np.testing.assert_array_equal(cv, np.where(beyond, -1, f.grid_cv[clipped]))
    np.testing.assert_array_equal(cv, f.cv_of(pts))
    np.testing.assert_allclose(frac, (pts - f.origin_m) / f.cell_size_m - cell, rtol=0, atol=1e-12)
    faces = np.stack([f.wall_faces, f.stepped_out_faces], axis=3)[clipped]
    bits = (f.kinetic_codes[rows][:, :, None] >> np.arange(4)) & 1  # (m, axis, bit)
    np.testing.assert_array_equal(np.stack([bits[:, :, :2], bits[:, :, 2:]], axis=1) == 1, faces)
    fx, fy, fz = f.face_u_m_s
    i, j, k = clipped
    t = np.clip(frac, 0.0, 1.0)
    lo = np.stack([fx[i, j, k], fy[i, j, k], fz[i, j, k]], axis=1)
    hi = np.stack([fx[i + 1, j, k], fy[i, j + 1, k], fz[i, j, k + 1]], axis=1)
    np.testing.assert_allclose(f.staggered_at(rows, frac), (1 - t) * lo + t * hi, rtol=0, atol=1e-12)


def test_a_point_that_is_not_a_number_is_outside_every_cv(ball_field):
    """A NaN or infinite coordinate (a vehicle whose estimate is lost) reads a border cell: CV -1 and
    a row inside every per-cell table, never an index error; the points beside it are unaffected."""
    pts = np.array([[np.nan, 0.0, 0.0], [1.0, np.inf, 0.0], [1.0, 0.0, -np.inf], [1.0, 0.1, 0.1]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning either: an agent's log stays clean
        rows, frac, cv = ball_field.locate(pts)
    np.testing.assert_array_equal(cv[:3], [-1, -1, -1])
    assert cv[3] == ball_field.cv_of(pts[3:])[0] >= 0
    assert np.all((rows >= 0) & (rows < ball_field.kinetic_codes.shape[0]))
    np.testing.assert_array_equal(ball_field.command(pts, np.arange(4))[:3], np.full((3, 3), np.nan))
