"""Block bootstrap over time (issue 37, item 7): how far a figure computed from a time average can be
trusted (pure, seeded).

The samples of a run are summed per contiguous time block (``fisc_ground.fields.time_blocks``).  A
replicate draws as many blocks as there are, with replacement, and recomputes the figure from the sums
of the drawn blocks.  Blocks long against the correlation time of the samples make the blocks nearly
independent, which is what the bootstrap assumes (samples a few tenths of a second apart are not).

The interval is the *basic* (reverse-percentile) one by default: ``[2 v - q_hi, 2 v - q_lo]`` with
``q`` the replicates' central ``level`` quantiles.  It corrects the first-order bias, and the fidelity
figures have one: sampling noise inflates a min-max nRMSE and deflates a Pearson r, and a replicate
(duplicated blocks) carries more of that noise than the figure itself, so the replicates sit on the
pessimistic side of the figure.  The basic interval is then an interval for the figure with unlimited
samples, and may exclude the figure itself when the noise bias is larger than its spread (``bias``
says how large it is).  ``method="percentile"`` gives ``[q_lo, q_hi]``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

DEFAULT_REPLICATES = 200
"""Bootstrap replicates of the reports (200 gives the 2.5 / 97.5 % points to about +-0.01 in r)."""
DEFAULT_LEVEL = 0.95
"""Coverage of the reported intervals."""


@dataclass(frozen=True)
class Interval:
    """A figure and its bootstrap interval (lo / hi NaN when it cannot be estimated: fewer than 2 blocks,
    or the figure undefined in most replicates)."""

    value: float
    """The figure on all samples."""
    lo: float
    """Lower end of the interval."""
    hi: float
    """Upper end of the interval."""
    level: float
    """Nominal coverage (0.95)."""
    n_blocks: int
    """Time blocks resampled."""
    bias: float = math.nan
    """Bootstrap estimate of the figure's bias from sampling noise: mean of the replicates - value."""

    @property
    def width(self) -> float:
        """hi - lo (NaN without an interval)."""
        return self.hi - self.lo

    def as_dict(self) -> dict:
        """JSON-ready: value, lo, hi, width, level, n_blocks (NaN as None)."""
        f = lambda v: float(v) if math.isfinite(v) else None  # noqa: E731
        return {"value": f(self.value), "lo": f(self.lo), "hi": f(self.hi), "width": f(self.width),
                "level": self.level, "n_blocks": self.n_blocks, "bias": f(self.bias)}

    def text(self, digits: int = 2) -> str:
        """``0.62 [0.41, 0.78]`` (``n/a`` where undefined)."""
        f = lambda v: f"{v:.{digits}f}" if math.isfinite(v) else "n/a"  # noqa: E731
        return f"{f(self.value)} [{f(self.lo)}, {f(self.hi)}]"


def resample_counts(n_blocks: int, n_boot: int, seed: int) -> np.ndarray:
    """(n_boot, n_blocks) how often each block is drawn in each replicate (rows sum to ``n_blocks``)."""
    rng = np.random.default_rng(seed)
    if n_blocks == 0:
        return np.zeros((n_boot, 0), dtype=np.int64)
    return rng.multinomial(n_blocks, np.full(n_blocks, 1.0 / n_blocks), size=n_boot)


def weighted_sums(block_sums: dict[str, np.ndarray], weights: np.ndarray) -> dict[str, np.ndarray]:
    """Sums over the block axis with one weight per block (``weights`` (n_blocks,))."""
    w = np.asarray(weights, dtype=float)
    return {k: np.tensordot(w, np.asarray(v, dtype=float), axes=(0, 0)) for k, v in block_sums.items()}


METHODS = ("basic", "percentile")
"""Interval methods of ``block_bootstrap``."""


def block_bootstrap(block_sums: dict[str, np.ndarray], statistic: Callable[[dict[str, np.ndarray]], dict[str, float]],
                    n_boot: int = DEFAULT_REPLICATES, seed: int = 0, level: float = DEFAULT_LEVEL,
                    method: str = "basic", bounds: dict[str, tuple[float, float]] | None = None) -> dict[str, Interval]:
    """Bootstrap intervals of every figure ``statistic`` returns from summed block sums.

    ``block_sums``: name -> (n_blocks, ...) additive sums per time block; ``statistic(sums)`` gets the
    same names summed over (resampled) blocks and returns name -> figure.  Replicates where a figure
    is NaN are left out of its interval; when more than half are, its interval is NaN.  ``bounds``:
    figure -> (lowest, highest) value it can take (the interval is clipped to it, e.g. r to [-1, 1])."""
    if not 0 < level < 1:
        raise ValueError(f"level must lie in (0, 1), is {level!r}")
    if method not in METHODS:
        raise ValueError(f"method {method!r}: choose one of {', '.join(METHODS)}")
    if int(n_boot) < 1:
        raise ValueError(f"n_boot must be >= 1, is {n_boot!r}")
    sizes = {np.asarray(v).shape[0] for v in block_sums.values()}
    if len(sizes) != 1:
        raise ValueError(f"block sums differ in their number of blocks: {sorted(sizes)}")
    n_blocks = sizes.pop()
    point = statistic(weighted_sums(block_sums, np.ones(n_blocks)))
    if n_blocks < 2:
        return {k: Interval(float(v), math.nan, math.nan, level, n_blocks) for k, v in point.items()}
    counts = resample_counts(n_blocks, int(n_boot), seed)
    reps = {k: np.empty(counts.shape[0]) for k in point}
    for b, w in enumerate(counts):
        vals = statistic(weighted_sums(block_sums, w))
        for k in point:
            reps[k][b] = vals.get(k, math.nan)
    out = {}
    a = 50.0 * (1.0 - level)
    for k, v in point.items():
        r = reps[k][np.isfinite(reps[k])]
        if r.size * 2 <= counts.shape[0]:
            out[k] = Interval(float(v), math.nan, math.nan, level, n_blocks)
        else:
            q_lo, q_hi = np.percentile(r, [a, 100.0 - a])
            lo, hi = (2.0 * v - q_hi, 2.0 * v - q_lo) if method == "basic" else (q_lo, q_hi)
            b_lo, b_hi = (bounds or {}).get(k, (-math.inf, math.inf))
            out[k] = Interval(float(v), float(np.clip(lo, b_lo, b_hi)), float(np.clip(hi, b_lo, b_hi)), level,
                              n_blocks, float(r.mean() - v))
    return out


def time_to_width_s(width: float, target_width: float, elapsed_s: float) -> float:
    """Further time [s] until an interval now ``width`` wide after ``elapsed_s`` of sampling is narrower
    than ``target_width``, from the 1/sqrt(samples) scaling at the current sampling rate:
    ``elapsed (width / target)^2 - elapsed``; 0 when it already is, NaN when unknown."""
    if not (math.isfinite(width) and math.isfinite(elapsed_s) and target_width > 0 and elapsed_s > 0):
        return math.nan
    if width < target_width:
        return 0.0
    return elapsed_s * ((width / target_width) ** 2 - 1.0)
