"""Block bootstrap (fisc_ground.fields.bootstrap, time_blocks): coverage on data with a known answer,
boundaries, the block sums adding up to the FieldAccumulator's."""

import math

import numpy as np
import pytest

from fisc_ground.fields.bootstrap import block_bootstrap, resample_counts, time_to_width_s
from fisc_ground.fields.swarm_fields import FieldAccumulator, cv_moments
from fisc_ground.fields.time_blocks import BlockAccumulator, accumulator_from_sums


def _mean(s):
    return {"mean": float(s["x"] / s["n"])}


@pytest.mark.parametrize("method", ["basic", "percentile"])
def test_coverage_of_iid_normal_blocks(method):
    """The mean of i.i.d. normal blocks: the 95 % interval holds the true mean in ~95 % of the seeds."""
    rng = np.random.default_rng(0)
    hits, trials = 0, 400
    for seed in range(trials):
        x = rng.normal(3.0, 2.0, size=(40, 5))  # 40 blocks of 5 samples
        sums = {"x": x.sum(axis=1), "n": np.full(40, 5.0)}
        iv = block_bootstrap(sums, _mean, n_boot=300, seed=seed, method=method)["mean"]
        hits += iv.lo <= 3.0 <= iv.hi
        # width ~ 2 * 1.96 sigma / sqrt(200)
        assert 0.25 < iv.width < 0.9
    # the bootstrap's known small-sample shortfall: with 40 blocks it uses the plug-in (n - 1)/n variance
    # and normal quantiles where t's belong, ~0.93 expected (1500 seeds: 0.92 both methods)
    assert 0.89 <= hits / trials <= 0.98


def test_basic_interval_corrects_noise_bias():
    """A figure inflated by sampling noise, like an nRMSE: ||mean||^2 of 20 noisy per-CV means whose
    true value is 0.2 (the noise adds ~0.2 more).  The basic interval holds the noise-free value about
    95 % of the time; the percentile interval (replicates carry twice the noise) almost never."""
    rng = np.random.default_rng(3)
    mu = np.full(20, 0.1)
    hits_basic = hits_pct = 0
    trials = 200
    for seed in range(trials):
        x = rng.normal(mu, 1.0, size=(25, 4, 20))  # 25 blocks of 4 samples of 20 CVs: sd of a mean 0.1
        sums = {"x": x.sum(axis=1), "n": np.full(25, 4.0)}
        f = lambda s: {"sq": float(np.sum((s["x"] / s["n"]) ** 2))}  # noqa: E731
        b = block_bootstrap(sums, f, n_boot=300, seed=seed, method="basic")["sq"]
        p = block_bootstrap(sums, f, n_boot=300, seed=seed, method="percentile")["sq"]
        hits_basic += b.lo <= 0.2 <= b.hi
        hits_pct += p.lo <= 0.2 <= p.hi
        assert b.bias == pytest.approx(p.bias) and b.bias > 0.1
    assert 0.85 <= hits_basic / trials <= 0.99
    assert hits_pct / trials < 0.2


def test_one_block_and_nan_figures_give_no_interval():
    iv = block_bootstrap({"x": np.array([3.0]), "n": np.array([1.0])}, _mean)["mean"]
    assert iv.value == 3.0 and math.isnan(iv.lo) and math.isnan(iv.width)
    assert iv.as_dict()["lo"] is None and iv.text() == "3.00 [n/a, n/a]"
    nan = block_bootstrap({"x": np.ones(5)}, lambda s: {"f": math.nan})["f"]
    assert math.isnan(nan.lo)


def test_bounds_clip_and_bad_arguments():
    sums = {"x": np.array([0.0, 10.0, 0.0, 10.0]), "n": np.ones(4)}
    iv = block_bootstrap(sums, _mean, bounds={"mean": (4.0, 6.0)})["mean"]
    assert 4.0 <= iv.lo <= iv.hi <= 6.0
    with pytest.raises(ValueError, match="level"):
        block_bootstrap(sums, _mean, level=1.0)
    with pytest.raises(ValueError, match="method"):
        block_bootstrap(sums, _mean, method="bca")
    with pytest.raises(ValueError, match="number of blocks"):
        block_bootstrap({"x": np.ones(3), "n": np.ones(4)}, _mean)


def test_resample_counts_seeded():
    a, b = resample_counts(7, 50, 1), resample_counts(7, 50, 1)
    assert np.array_equal(a, b) and (a.sum(axis=1) == 7).all()
    assert not np.array_equal(a, resample_counts(7, 50, 2))


def test_time_to_width_scaling():
    assert time_to_width_s(0.2, 0.1, 60.0) == pytest.approx(180.0)  # 4x the samples: 240 s in all
    assert time_to_width_s(0.1, 0.1, 60.0) == pytest.approx(0.0)  # equal: not narrower yet, no more time by the scaling
    assert time_to_width_s(0.0999, 0.1, 60.0) == 0.0
    assert math.isnan(time_to_width_s(math.nan, 0.1, 60.0))
    assert math.isnan(time_to_width_s(0.2, 0.1, 0.0))


def test_blocks_add_up_to_the_accumulator():
    rng = np.random.default_rng(5)
    n_cv = 6
    ref = rng.normal(size=(n_cv, 3))
    acc = FieldAccumulator(n_cv, 0.125)
    blocks = BlockAccumulator(n_cv, block_s=1.0)
    for k in range(23):
        cv = rng.integers(-1, n_cv, size=9)
        vel = rng.normal(size=(9, 3))
        mom = cv_moments(cv, vel, 1.5, n_cv, ref)
        acc.add_moments(mom)
        blocks.add_moments(0.25 * k, mom)
    assert blocks.n_blocks == 6  # t = 0 .. 5.5 in 1 s blocks
    s = blocks.sums()
    assert s["count"].shape == (6, n_cv) and s["n_time_samples"].tolist() == [4, 4, 4, 4, 4, 3]
    again = accumulator_from_sums({k: v.sum(axis=0) for k, v in s.items()}, acc).result()
    want = acc.result()
    assert np.allclose(again.rho_s_kg_m3, want.rho_s_kg_m3)
    assert np.allclose(again.p_dispersion_pa, want.p_dispersion_pa, equal_nan=True)
    with pytest.raises(ValueError, match="time order"):
        blocks.add_moments(1.0, mom)
    with pytest.raises(ValueError, match="block length"):
        BlockAccumulator(3, block_s=0.0)
    assert BlockAccumulator(3).sums()["count"].shape == (0, 3)
