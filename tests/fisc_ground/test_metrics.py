"""Specification of the fidelity metrics (DESIGN.md section 4)."""

import numpy as np
import pytest

from fisc_ground.fields.metrics import (
    centreline_profiles,
    centreline_selection,
    fidelity_metrics,
    normalise_min_max,
    pearson,
)

KEYS = {
    "nrmse_velocity", "nrmse_pressure", "nrmse_density",
    "centreline_max_dev_velocity", "centreline_max_dev_pressure", "centreline_max_dev_density",
    "pearson_velocity", "pearson_pressure", "pearson_density", "n_cv_compared",
}


def _grid(nx=10, n=4, l=0.5):
    """CV centres of a grid with the tunnel axis (y = z = 0) on cell faces."""
    i, j, k = np.meshgrid(np.arange(nx), np.arange(n), np.arange(n), indexing="ij")
    idx = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1)
    return (idx + 0.5) * l + np.array([0.0, -n * l / 2, -n * l / 2])


def _cfd_like(c):
    x, r = c[:, 0], np.hypot(c[:, 1], c[:, 2])
    u = 3.0 + 2.0 * np.exp(-((x - 2.0) ** 2)) + 0.1 * r
    p = -0.5 * 1.2 * u ** 2
    rho = 1.2 * (1.0 - 7e-4 * (u - u.min()) / np.ptp(u))  # ~7e-4 relative variation
    return u, p, rho


def _metrics(c, t, s, samples=None, min_samples=1):
    samples = np.full(c.shape[0], 100) if samples is None else samples
    return fidelity_metrics(c, *t, *s, samples, min_samples=min_samples)


def test_identical_fields_score_perfectly():
    c = _grid()
    t = _cfd_like(c)
    m = _metrics(c, t, t)
    d = m.as_dict()
    assert KEYS <= set(d)
    for q in ("velocity", "pressure", "density"):
        assert d[f"nrmse_{q}"] == pytest.approx(0.0, abs=1e-12)
        assert d[f"centreline_max_dev_{q}"] == pytest.approx(0.0, abs=1e-12)
        assert d[f"pearson_{q}"] == pytest.approx(1.0)
    assert d["n_cv_compared"] == c.shape[0]
    assert m.degenerate == ()


def test_metrics_invariant_to_speed_scale_kappa_and_mass_scale():
    c = _grid()
    t = _cfd_like(c)
    rng = np.random.default_rng(0)
    u, p, rho = (f + rng.normal(scale=0.05 * np.ptp(f), size=f.shape) for f in t)
    plain = _metrics(c, t, (u, p, rho)).as_dict()
    # S = 0.1 on velocity, kappa * (P - min P) on pressure, 7.3x mass on density
    scaled = _metrics(c, t, (0.1 * u, 2.5 * (p - p.min()), 7.3 * rho)).as_dict()
    assert plain["nrmse_velocity"] > 0.01  # a real, non-trivial difference is being measured
    for k in KEYS:
        assert scaled[k] == pytest.approx(plain[k], rel=1e-9, abs=1e-12), k


def test_hand_computed_nrmse_and_centreline_deviation():
    # four CVs, one per axial slice, all adjacent to the axis
    c = np.array([[0.25, 0.25, 0.25], [0.75, 0.25, 0.25], [1.25, 0.25, 0.25], [1.75, 0.25, 0.25]])
    t_u, s_u = np.array([1.0, 2, 3, 4]), np.array([2.0, 2, 3, 4])  # hats: .25/.5 differ -> 0.25
    t_p, s_p = np.array([0.0, 1, 2, 4]), np.array([0.0, 2, 2, 4])  # minmax: .25/.5 differ -> 0.25
    t_r, s_r = np.array([1.0, 2, 3, 5]), np.array([10.0, 20, 30, 50])  # identical after min-max
    m = _metrics(c, (t_u, t_p, t_r), (s_u, s_p, s_r))
    assert m.nrmse_velocity == pytest.approx(np.sqrt(0.25 ** 2 / 4))  # 0.125
    assert m.nrmse_pressure == pytest.approx(0.125)
    assert m.nrmse_density == pytest.approx(0.0, abs=1e-15)
    assert m.centreline_max_dev_velocity == pytest.approx(0.25)
    assert m.centreline_max_dev_pressure == pytest.approx(0.25)
    assert m.n_centreline_slices == 4


def test_cvs_without_enough_samples_are_excluded():
    c = _grid()
    t = _cfd_like(c)
    s = tuple(f.copy() for f in t)
    samples = np.full(c.shape[0], 50)
    samples[7] = 3
    s[0][7] = -100.0  # garbage velocity in a poorly sampled CV
    s[1][7] = np.nan  # and an undefined pressure
    m = _metrics(c, t, s, samples, min_samples=10)
    assert m.n_cv_compared == c.shape[0] - 1
    assert m.nrmse_velocity == pytest.approx(0.0, abs=1e-12)
    assert m.centreline_max_dev_velocity == pytest.approx(0.0, abs=1e-12)
    loose = _metrics(c, t, s, samples, min_samples=1)
    assert loose.nrmse_velocity > 0.1  # would count if included
    assert loose.n_cv_compared == c.shape[0]  # a NaN pressure does not drop the CV from velocity
    assert loose.nrmse_pressure == pytest.approx(0.0, abs=1e-12)


def test_degenerate_fields_give_nan_with_a_reason():
    c = _grid()
    u, p, rho = _cfd_like(c)
    m = _metrics(c, (u, p, None), (u, np.full_like(p, 3.0), rho))
    assert np.isnan(m.nrmse_pressure) and np.isnan(m.centreline_max_dev_pressure)
    assert np.isnan(m.pearson_pressure)
    assert np.isnan(m.nrmse_density) and np.isnan(m.pearson_density)
    assert m.nrmse_velocity == pytest.approx(0.0, abs=1e-12)
    text = " ".join(m.degenerate)
    assert "pressure" in text and "constant" in text and "no density" in text
    zero_u = _metrics(c, (u, p, rho), (np.zeros_like(u), p, rho))
    assert np.isnan(zero_u.nrmse_velocity) and any("velocity" in r for r in zero_u.degenerate)


def test_nearly_constant_cfd_density_is_not_degenerate():
    c = _grid()
    u, p, rho = _cfd_like(c)
    assert np.ptp(rho) / rho.max() < 1e-3
    hat = normalise_min_max(rho)
    assert hat is not None and hat.min() == 0.0 and hat.max() == 1.0
    m = _metrics(c, (u, p, rho), (u, p, 40.0 + 3.0 * (rho - rho.min()) / np.ptp(rho)))
    assert m.nrmse_density == pytest.approx(0.0, abs=1e-9)
    assert m.degenerate == ()
    assert normalise_min_max(np.full(5, 1.2)) is None


def test_centreline_uses_the_four_cvs_around_the_axis():
    c = _grid(nx=3, n=4)
    slice_x, slice_of, on_axis = centreline_selection(c)
    np.testing.assert_allclose(slice_x, [0.25, 0.75, 1.25])
    assert np.bincount(slice_of[on_axis]).tolist() == [4, 4, 4]
    np.testing.assert_allclose(np.hypot(c[on_axis, 1], c[on_axis, 2]), 0.5 ** 0.5 * 0.5)

    u, p, rho = _cfd_like(c)
    s_u = u.copy()
    s_u[~on_axis] *= 3.0  # off-axis disagreement must not affect the centreline
    ax = np.flatnonzero(on_axis & (slice_of == 1))
    s_u[ax] += np.array([0.2, -0.2, 0.1, -0.1])  # zero-mean perturbation: slice mean unchanged
    prof = centreline_profiles(c, u, p, rho, s_u, p, rho, np.full(c.shape[0], 20), min_samples=1)
    np.testing.assert_allclose(prof.swarm["velocity"], prof.target["velocity"], atol=1e-12)
    assert np.nanmax(prof.target["velocity"]) == pytest.approx(1.0)
    assert np.nanmin(prof.target["pressure"]) == pytest.approx(0.0)


def test_pearson_basics():
    assert pearson(np.array([1.0, 2, 3]), np.array([2.0, 4, 6])) == pytest.approx(1.0)
    assert pearson(np.array([1.0, 2, 3]), np.array([3.0, 2, 1])) == pytest.approx(-1.0)
    assert np.isnan(pearson(np.array([1.0, 1, 1]), np.array([1.0, 2, 3])))


def test_shape_errors_name_the_field():
    c = _grid(nx=2)
    u, p, rho = _cfd_like(c)
    with pytest.raises(ValueError, match="pressure"):
        fidelity_metrics(c, u, p[:-1], rho, u, p, rho, np.ones(c.shape[0]))


# ------------------------------------------------------------------ boundaries (issue 38)
import warnings  # noqa: E402

from fisc_ground.fields.metrics import normalise, normalise_by_max, nrmse  # noqa: E402

# found by search: the raw correlation of a perfectly (anti)correlated pair rounds beyond +-1
ROUNDS_ABOVE_ONE = [-0.20917557487171307, -0.15922500991447772, 0.5408455846858077, 0.2146591225063409,
                    0.3553727090399214, -0.6538286094183394, -0.12961363369276946]
ROUNDS_BELOW_MINUS_ONE = [-0.6615280218152191, 0.9350499881140221, 0.049054613825311656, 2.002392583645255]


def _quiet(fn, *args, **kw):
    """Call with every warning an error: a degenerate input is answered, not computed through NaN."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return fn(*args, **kw)


def test_max_normalisation_at_its_limits():
    assert _quiet(normalise_by_max, []) is None
    np.testing.assert_array_equal(_quiet(normalise_by_max, [2.0]), [1.0])  # a single value
    np.testing.assert_array_equal(_quiet(normalise_by_max, [1, 4]), [0.25, 1.0])  # integers
    assert _quiet(normalise_by_max, [0.0, 0.0]) is None and _quiet(normalise_by_max, [-1.0, -2.0]) is None
    assert _quiet(normalise_by_max, [np.nan, np.nan]) is None
    np.testing.assert_array_equal(_quiet(normalise_by_max, [np.nan, 2.0]), [np.nan, 1.0])


def test_min_max_normalisation_at_its_limits():
    assert _quiet(normalise_min_max, []) is None and _quiet(normalise_min_max, [3.0]) is None
    assert _quiet(normalise_min_max, [0.0, 0.0]) is None  # zero range, zero magnitude
    assert _quiet(normalise_min_max, [np.nan, np.nan]) is None
    assert _quiet(normalise_min_max, [1e6, 1e6 + 1e-7]) is None  # range 1e-13 of the magnitude: constant
    np.testing.assert_allclose(_quiet(normalise_min_max, [1e6, 1e6 + 1e-5]), [0.0, 1.0])  # 1e-11: a trend
    np.testing.assert_array_equal(_quiet(normalise_min_max, [-1, 1]), [0.0, 1.0])  # a sign change, integers
    with pytest.raises(ValueError, match=r"^unknown normalisation 'mean' \(use 'max' or 'minmax'\)$"):
        normalise([1.0], "mean")


def test_nrmse_and_pearson_at_their_limits():
    assert np.isnan(_quiet(nrmse, [], []))
    assert _quiet(nrmse, [1], [0]) == 1.0 and _quiet(nrmse, [0.0, 0.0], [3.0, -4.0]) == pytest.approx(12.5 ** 0.5)
    assert np.isnan(_quiet(pearson, [1.0], [2.0]))  # one value
    assert _quiet(pearson, [1, 2], [5, 3]) == -1.0  # two values: defined
    assert np.isnan(_quiet(pearson, [1.0, 1.0, 1.0], [1.0, 2.0, 3.0]))  # a constant input
    a = np.array(ROUNDS_ABOVE_ONE)
    assert _quiet(pearson, a, 3.7 * a + 1.1) == 1.0
    b = np.array(ROUNDS_BELOW_MINUS_ONE)
    assert _quiet(pearson, b, -3.7 * b + 1.1) == -1.0


def test_a_cv_with_exactly_min_samples_is_compared_and_the_dict_carries_every_field():
    c = _grid(nx=4)
    t = _cfd_like(c)
    samples = np.full(c.shape[0], 5)
    m = _metrics(c, t, t, samples=samples, min_samples=5)
    assert m.n_cv_compared == c.shape[0] and m.n_centreline_slices == 4
    assert _metrics(c, t, t, samples=samples, min_samples=6).n_cv_compared == 0
    d = m.as_dict()
    assert (d["n_centreline_slices"], d["min_samples"], d["degenerate"]) == (4, 5, [])
    assert type(d["n_centreline_slices"]) is int and type(d["min_samples"]) is int


def test_no_cv_compared_names_the_reason_per_quantity():
    c = _grid(nx=3)
    u, p, _ = _cfd_like(c)
    m = _metrics(c, (u, p, None), (u, p, u), samples=np.full(c.shape[0], 2), min_samples=3)
    assert m.degenerate[:3] == ("velocity: no CV has enough samples", "pressure: no CV has enough samples",
                                "density: reference has no density")
    assert m.as_dict()["degenerate"] == list(m.degenerate)
    assert all(np.isnan(getattr(m, f"{k}_{q}")) for k in ("nrmse", "pearson") for q in ("velocity", "pressure"))
    rho = np.ones_like(u)
    m = _metrics(c, (u, p, rho), (u, p, rho), samples=np.full(c.shape[0], 2), min_samples=3)
    assert m.degenerate[2] == "density: no CV has enough samples"  # a reference with density, no samples
    m = _metrics(c, (u, p, None), (u, p, u), samples=np.full(c.shape[0], 3), min_samples=3)
    assert "density: reference has no density" in m.degenerate and m.n_cv_compared == c.shape[0]


def test_a_degenerate_target_or_swarm_is_named():
    c = _grid(nx=4)
    u, p, rho = _cfd_like(c)
    swarm_flat = _metrics(c, (u, p, rho), (u, np.full_like(p, 2.0), rho))
    assert "pressure: swarm field cannot be min-max normalised (constant field)" in swarm_flat.degenerate
    assert "centreline pressure: swarm profile cannot be min-max normalised (constant field)" in swarm_flat.degenerate
    target_flat = _metrics(c, (-u, p, rho), (u, p, rho))
    assert "velocity: target field cannot be normalised by its max (max <= 0)" in target_flat.degenerate
    assert "centreline velocity: target profile cannot be normalised by its max (max <= 0)" in target_flat.degenerate
    assert np.isnan(target_flat.nrmse_velocity) and np.isnan(target_flat.centreline_max_dev_velocity)
    assert not np.isnan(target_flat.pearson_velocity)


def test_centreline_selection_at_its_limits():
    for bad in (np.zeros((5, 2)), np.zeros(3)):
        with pytest.raises(ValueError, match=r"^centers_m must be \(n_cv, 3\), got shape"):
            centreline_selection(bad)
    sx, sof, on = centreline_selection(np.zeros((0, 3)))
    assert (sx.shape, sof.shape, on.shape) == ((0,), (0,), (0,))
    assert (sx.dtype, sof.dtype, on.dtype) == (np.float64, np.int64, np.bool_)
    # x extent 0.5 < 1 m: the merge tolerance is rel_tol x 1 m = 1e-6 m; a gap of exactly that merges
    c = np.array([[0.0, 0, 0], [1e-6, 0, 0], [2.5e-6, 0, 0], [0.5, 0, 0]])
    sx, sof, _ = centreline_selection(c)
    assert sof.tolist() == [0, 0, 1, 2] and sx.tolist() == [0.0, 2.5e-6, 0.5]
    # x extent 100 m: the tolerance scales to 1e-4 m
    c = np.array([[0.0, 0, 0], [0.5e-4, 0, 0], [2e-4, 0, 0], [100.0, 0, 0]])
    assert centreline_selection(c)[1].tolist() == [0, 0, 1, 2]
    # radii: within rel_tol x max(r_max, 1 m) of the slice's smallest radius is on the axis
    c = np.array([[0.0, 1.0, 0], [0.0, 1.0 + 5e-5, 0], [0.0, 100.0, 0]])  # r_max 100: tolerance 1e-4
    assert centreline_selection(c)[2].tolist() == [True, True, False]
    c = np.array([[0.0, 0.1, 0], [0.0, 0.1 + 1.5e-6, 0], [0.0, 0.5, 0]])  # r_max 0.5 < 1: tolerance 1e-6
    assert centreline_selection(c)[2].tolist() == [True, False, False]
    c = np.array([[0.0, 0.1, 0], [0.0, 0.2, 0]])
    assert centreline_selection(c, rel_tol=0.0)[2].tolist() == [True, False]  # the nearest itself, always


def test_centreline_means_use_only_the_compared_near_axis_cvs():
    # three slices of two near-axis CVs (r = 0.5, y = +-0.5) and one far CV; the last slice has no sample
    c = np.array([[x, y, 0.0] for x in (0.0, 1.0, 2.0) for y in (-0.5, 0.5, 3.0)])
    t_u = np.array([1.0, 3.0, 50.0, 2.0, 6.0, 50.0, 9.0, 9.0, 50.0])
    s_u = t_u * 2.0
    t_u[1] = np.nan  # not compared: the first slice's target mean is its other CV
    s_u[4] = np.nan  # nor is a CV without a swarm value: the second slice's means are its other CV
    samples = np.array([5, 5, 5, 5, 5, 5, 0, 0, 5])
    p = np.linspace(1.0, 2.0, 9)
    prof = _quiet(centreline_profiles, c, t_u, p, None, s_u, p, p, samples, min_samples=5)
    assert prof.x_m.tolist() == [0.0, 1.0, 2.0] and prof.target["velocity"].shape == (3,)
    np.testing.assert_allclose(prof.target["velocity"], [1.0 / 2.0, 1.0, np.nan])  # means 1 and 2, by max 2
    np.testing.assert_allclose(prof.swarm["velocity"], [2.0 / 4.0, 1.0, np.nan])  # the same CVs: 2 and 4
    t_u[4] = 6.0
    s_u[4] = 12.0
    prof = _quiet(centreline_profiles, c, t_u, p, None, s_u, p, p, samples, min_samples=5)
    np.testing.assert_allclose(prof.target["velocity"], [1.0 / 4.0, 1.0, np.nan])  # a mean of two: 4
    m = _quiet(fidelity_metrics, c, t_u, p, None, s_u, p, p, samples, min_samples=5)
    assert m.n_cv_compared == 6  # 7 CVs with enough samples, less the one without a target velocity
    assert np.isnan(m.centreline_max_dev_density)
    with pytest.raises(ValueError, match=r"^samples must be \(9,\), got \(8,\)$"):
        fidelity_metrics(c, t_u, p, None, s_u, p, p, samples[:8])
    assert "centreline density: no slice has a compared near-axis CV" in prof.degenerate
