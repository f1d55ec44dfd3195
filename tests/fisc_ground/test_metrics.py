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
