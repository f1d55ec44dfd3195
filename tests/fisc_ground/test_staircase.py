"""The designed staircase (fisc_ground.fit.staircase): hand-computed cases, its refusals, and its purpose on the
shipped tunnel (the swarm's continuity pattern follows the CFD's density pattern)."""

import numpy as np
import pytest

from fisc_ground.fit.partition import partition, partition_field
from fisc_ground.reference.builtin import load_builtin
from fisc_ground.fit.staggered import cfd_pattern, slice_flux_area
from fisc_ground.fit.staircase import DEFAULT_STAIRCASE_CONTRAST, axial_pockets, designed_staircase, slice_pattern

# four slices of four cells: two full cubes, one 48 % and one 24 % open; open area 2.72 cubes -> m >= 3
COUNTS = np.array([[125, 125, 60, 30]] * 4)
U = np.ones((4, 4))
DIP = np.array([1.0, 0.0, 0.0, 1.0])


def test_the_flux_area_follows_the_pattern():
    """Pattern (1, 0, 0, 1) at contrast 0.25 asks for flux areas in the ratio 1 : 4/3 : 4/3 : 1, i.e. 3, 4,
    4, 3 cubes."""
    keep = designed_staircase(COUNTS, U, DIP, 0.25, min_step_open=0.0)
    np.testing.assert_array_equal(keep.sum(axis=1), [3, 4, 4, 3])
    # the most covered cubes are kept first
    assert keep[:, :3].all() and not keep[0, 3] and keep[1, 3] and keep[2, 3]


def test_no_step_outwards_into_a_barely_open_cube():
    """The 24 %-open cube of the second slice would step out (its upstream neighbour is not kept): below
    min_step_open it is not eligible (nor, then, the third slice's), at or above it is."""
    np.testing.assert_array_equal(designed_staircase(COUNTS, U, DIP, 0.25, 0.25).sum(axis=1), [3, 3, 3, 3])
    np.testing.assert_array_equal(designed_staircase(COUNTS, U, DIP, 0.25, 0.24).sum(axis=1), [3, 4, 4, 3])
    # the inlet slice has no upstream: every covered cube is eligible there
    first = designed_staircase(COUNTS, U, np.array([0.0, 0.0, 1.0, 1.0]), 0.25, 0.9)
    assert first[0].sum() == 4


def test_a_cube_with_neither_axial_neighbour_kept_is_dropped():
    """Pattern (1, 0, 1) alone would keep the 24 %-open cube in the middle slice only: a pocket the flow
    cannot pass through (no axial neighbour), so it is dropped; the inlet and outlet slices' cubes are not
    pockets (their missing neighbour is the inlet or the outlet)."""
    keep = designed_staircase(COUNTS[:3], U[:3], np.array([1.0, 0.0, 1.0]), 0.25, min_step_open=0.0)
    np.testing.assert_array_equal(keep.sum(axis=1), [3, 3, 3])
    mask = np.array([[1, 0, 1], [0, 1, 0], [1, 0, 0], [0, 0, 1]], dtype=bool)
    np.testing.assert_array_equal(axial_pockets(mask), [[0, 0, 0], [0, 1, 0], [1, 0, 0], [0, 0, 0]])
    assert not axial_pockets(np.ones((3, 2), dtype=bool)).any()


def test_a_uniform_pattern_keeps_every_slice_alike_and_at_least_the_open_area():
    keep = designed_staircase(COUNTS, U, np.ones(4), 0.4)
    assert np.all(keep.sum(axis=1) == keep.sum(axis=1)[0]) and keep.sum(axis=1)[0] >= 3


def test_slice_pattern_is_the_min_max_of_the_node_weighted_slice_means():
    sums = np.array([[2.0, 2.0], [3.0, 0.0], [5.0, 5.0]])
    counts = np.array([[1, 1], [1, 0], [2, 2]])
    np.testing.assert_allclose(slice_pattern(sums, counts), [0.0, 1.0, 0.5])


@pytest.mark.parametrize("kwargs, match", [
    ({"contrast": 0.0}, "contrast must lie in"),
    ({"contrast": 1.0}, "contrast must lie in"),
    ({"min_step_open": 1.5}, "min_step_open"),
    ({"pattern": np.ones(2)}, "must be equal"),
    ({"u": np.full((4, 4), np.nan)}, "finite"),
    ({"counts": np.array([[125, 0], [0, 0], [125, 0], [125, 0]]), "u": np.ones((4, 2))},
     "x slice 1 has no covered cube"),
    ({"u": -np.ones((4, 4))}, "no net CFD flow"),
])
def test_refusals_name_the_problem(kwargs, match):
    args = {"counts": COUNTS, "u": U, "pattern": DIP, "contrast": 0.3, "min_step_open": 0.0}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        designed_staircase(args["counts"], args["u"], args["pattern"], args["contrast"], args["min_step_open"])


def test_a_straight_pipe_has_no_pattern_and_keeps_every_cube():
    assert slice_pattern(np.ones((3, 2)), np.ones((3, 2))) is None
    rng = np.random.default_rng(0)
    pts = rng.uniform([0, -1, -1], [3, 1, 1], (4000, 3))
    vel = np.tile([1.0, 0, 0], (4000, 1))
    cvs = partition(pts, vel, np.zeros(4000), np.ones(4000), staircase_contrast=0.4)
    assert cvs.staircase_contrast is None and cvs.n_cv == partition(pts, vel, np.zeros(4000), None).n_cv


def test_slice_pattern_refuses_an_empty_slice():
    with pytest.raises(ValueError, match="x slice 1 holds no reference node"):
        slice_pattern(np.ones((3, 2)), np.array([[1, 1], [0, 0], [1, 1]]))


def test_on_the_tunnel_the_swarm_continuity_pattern_follows_the_cfd_density():
    """The point of the design: with every covered cube a CV the swarm's density at the CFD velocity
    (1 / slice flux area) correlates 0.74 with the CFD's density; with the designed staircase above 0.95,
    at the designed contrast, and the staircase still covers every slice."""
    field = load_builtin("cd_nozzle_inviscid")

    def continuity_vs_cfd(cvs):
        inv_s = 1.0 / slice_flux_area(cvs.grid_cv, cvs.target_velocity_m_s)
        pattern = cfd_pattern(cvs.target_density_kg_m3, cvs.target_pressure_gauge_pa)
        return float(np.corrcoef(inv_s, pattern)[0, 1]), 1.0 - inv_s.min() / inv_s.max()

    full = partition_field(field)
    designed = partition_field(field, staircase_contrast=DEFAULT_STAIRCASE_CONTRAST)
    r_full, _ = continuity_vs_cfd(full)
    r_designed, contrast = continuity_vs_cfd(designed)
    assert r_full < 0.8 and r_designed > 0.95
    assert abs(contrast - DEFAULT_STAIRCASE_CONTRAST) < 0.05
    assert designed.n_cv < full.n_cv and set(designed.index[:, 0]) == set(range(full.shape[0]))
    assert designed.staircase_contrast == DEFAULT_STAIRCASE_CONTRAST and full.staircase_contrast is None
    # every designed CV is a CV of the full staircase, with the same targets
    ids = full.grid_cv[tuple(designed.index.T)]
    np.testing.assert_array_equal(full.node_count[ids], designed.node_count)
    np.testing.assert_allclose(full.target_velocity_m_s[ids], designed.target_velocity_m_s)


def _reference_select(c, u, open_fraction, log_target, min_step_open):
    """The per-scale selection as first written (numpy per slice, no cache): the oracle of ``_select``."""
    keep = np.zeros(c.shape, dtype=bool)
    upstream = np.ones(c.shape[1], dtype=bool)
    err = 0.0
    for i in range(c.shape[0]):
        eligible = (c[i] > 0) & (upstream | (open_fraction[i] >= min_step_open))
        order = np.argsort(-np.where(eligible, c[i], -1.0), kind="stable")[:int(eligible.sum())]
        s = np.cumsum(u[i, order])
        m = np.arange(1, s.size + 1)
        m_min = min(max(int(np.rint(open_fraction[i].sum())), 1), s.size)
        e = np.where((m >= m_min) & (s > 0), (np.log(np.where(s > 0, s, 1.0)) - log_target[i]) ** 2, np.inf)
        j = int(np.argmin(e))
        if not np.isfinite(e[j]):
            return keep, np.inf
        err += float(e[j])
        keep[i, order[:j + 1]] = True
        upstream = keep[i]
    return keep, err


@pytest.mark.parametrize("seed", range(40))
def test_select_with_its_cache_equals_the_uncached_selection(seed):
    """``_select`` reuses a slice's candidates across scales: the same masks and the same error bits as the
    plain per-scale selection, over the scales ``designed_staircase`` tries (ties, negative flux, steps)."""
    from fisc_ground.fit import staircase as sc

    rng = np.random.default_rng(seed)
    nx, m = rng.integers(1, 12), rng.integers(1, 9)
    c = rng.integers(0, 4, (nx, m)).astype(float)  # small counts: many ties in the ordering
    c[np.arange(nx), rng.integers(0, m, nx)] += 1.0  # every slice covered
    u = rng.normal(1.0, 0.8 if seed % 3 else 0.1, (nx, m))  # some negative axial velocities
    f = rng.random(nx)
    open_fraction = c / c.max(axis=1, keepdims=True)
    log_want = -np.log(1.0 - 0.4 * (1.0 - f))
    slices: dict = {}
    for scale in np.geomspace(0.2, 5.0, 60) * max(float(np.where(c > 0, u, 0).sum(axis=1).mean()), 0.1):
        target = log_want + np.log(scale)
        for step_open in (0.0, 0.25, 1.0):
            got = sc._select(c, u, open_fraction, target, step_open, slices.setdefault(step_open, {}))
            want = _reference_select(c, u, open_fraction, target, step_open)
            np.testing.assert_array_equal(got[0], want[0])
            assert got[1] == want[1] or (np.isinf(got[1]) and np.isinf(want[1]))
