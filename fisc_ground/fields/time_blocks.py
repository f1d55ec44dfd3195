"""Per-CV moments summed per contiguous block of time, for the block bootstrap (issue 37, item 7).

A ``BlockAccumulator`` keeps, for every block of ``block_s`` seconds that received samples, the additive
per-CV moments of ``fisc_ground.fields.swarm_fields`` (count, mass, momentum, sum m v^2, sum m ||v - v_ref||^2)
and the number of time samples.  Summed over all blocks they are exactly a ``FieldAccumulator``'s sums;
summed over a resample of blocks (``fisc_ground.fields.bootstrap``) they are one bootstrap replicate, so
the bootstrap needs no raw samples.  Memory: one set of per-CV sums per block.
"""

from __future__ import annotations

import math

import numpy as np

from fisc_ground.fields.swarm_fields import CVMoments, FieldAccumulator

DEFAULT_BLOCK_S = 10.0
"""Default block length [s]: about the time an agent takes through the 15 m tunnel (its samples within
a block are correlated; blocks this long are nearly independent)."""
SUM_NAMES = ("count", "mass_kg", "momentum_kg_m_s", "m_v2_kg_m2_s2", "m_dev2_kg_m2_s2", "n_time_samples",
             "n_ref_samples")
"""Keys of ``BlockAccumulator.sums()``."""


class BlockAccumulator:
    """Additive per-CV moments per time block of ``block_s`` seconds (blocks counted from ``t0_s``, the
    first sample's time by default).  Samples must come in time order."""

    def __init__(self, n_cv: int, block_s: float = DEFAULT_BLOCK_S, t0_s: float | None = None) -> None:
        if not (math.isfinite(block_s) and block_s > 0):
            raise ValueError(f"block length must be a finite number > 0 s, is {block_s!r}")
        if int(n_cv) < 0:
            raise ValueError(f"n_cv must be >= 0, got {n_cv}")
        self.n_cv = int(n_cv)
        self.block_s = float(block_s)
        self.t0_s = None if t0_s is None else float(t0_s)
        self._blocks: list[dict[str, np.ndarray]] = []
        self._index: list[int] = []
        self.first_t_s = math.nan
        """Time of the first sample [s]."""
        self.last_t_s = math.nan
        """Time of the newest sample [s]."""

    @property
    def n_blocks(self) -> int:
        """Blocks that received samples."""
        return len(self._blocks)

    def _new_block(self) -> dict[str, np.ndarray]:
        n = self.n_cv
        return {"count": np.zeros(n), "mass_kg": np.zeros(n), "momentum_kg_m_s": np.zeros((n, 3)),
                "m_v2_kg_m2_s2": np.zeros(n), "m_dev2_kg_m2_s2": np.zeros(n), "n_time_samples": np.zeros(()),
                "n_ref_samples": np.zeros(())}

    def add_moments(self, t_s: float, mom: CVMoments) -> None:
        """Add one time sample's per-CV moments (``swarm_fields.cv_moments``) taken at ``t_s``."""
        if not math.isfinite(t_s):
            raise ValueError(f"sample time must be finite, is {t_s!r}")
        if mom.count.shape != (self.n_cv,):
            raise ValueError(f"moments of {mom.count.shape[0]} CVs added to blocks of {self.n_cv}")
        if self.t0_s is None:
            self.t0_s = float(t_s)
        if math.isfinite(self.last_t_s) and t_s < self.last_t_s:
            raise ValueError(f"samples must come in time order: {t_s} after {self.last_t_s}")
        k = math.floor((t_s - self.t0_s) / self.block_s + 1e-9)
        if not self._index or self._index[-1] != k:
            self._blocks.append(self._new_block())
            self._index.append(k)
        b = self._blocks[-1]
        b["count"] += mom.count
        b["mass_kg"] += mom.mass_kg
        b["momentum_kg_m_s"] += mom.momentum_kg_m_s
        b["m_v2_kg_m2_s2"] += mom.m_v2_kg_m2_s2
        if mom.m_dev2_kg_m2_s2 is not None:
            b["m_dev2_kg_m2_s2"] += mom.m_dev2_kg_m2_s2
            b["n_ref_samples"] += 1
        b["n_time_samples"] += 1
        if not math.isfinite(self.first_t_s):
            self.first_t_s = float(t_s)
        self.last_t_s = float(t_s)

    def sums(self) -> dict[str, np.ndarray]:
        """Every block's sums stacked on a leading block axis: ``SUM_NAMES`` -> (n_blocks, ...)."""
        if not self._blocks:
            n = self.n_cv
            return {"count": np.zeros((0, n)), "mass_kg": np.zeros((0, n)), "momentum_kg_m_s": np.zeros((0, n, 3)),
                    "m_v2_kg_m2_s2": np.zeros((0, n)), "m_dev2_kg_m2_s2": np.zeros((0, n)),
                    "n_time_samples": np.zeros(0), "n_ref_samples": np.zeros(0)}
        return {k: np.stack([b[k] for b in self._blocks]) for k in SUM_NAMES}


def accumulator_from_sums(sums: dict[str, np.ndarray], template: FieldAccumulator) -> FieldAccumulator:
    """A ``FieldAccumulator`` with ``template``'s CVs, volumes and drift holding the (already summed over
    blocks) ``sums``; its ``result()`` is the time-averaged fields of those samples."""
    acc = FieldAccumulator(template.n_cv, template.cell_volume_m3, template.drift_dir, template.params)
    for name in SUM_NAMES[:5]:
        setattr(acc, name, np.asarray(sums[name], dtype=float))
    acc.n_time_samples = int(round(float(sums["n_time_samples"])))
    acc.n_ref_samples = int(round(float(sums["n_ref_samples"])))
    return acc
