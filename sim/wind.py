"""Wind for the velocity plant: a mean wind plus first-order Gauss-Markov gusts, per agent.

The plant (``sim.plant.model``) takes any wind array; this module is one simple, seeded way to make
one.  Each agent's gust is an Ornstein-Uhlenbeck process per axis (the first-order core of the
Dryden model, in time rather than space): stationary RMS ``turbulence_rms_m_s``, autocorrelation
``exp(-|t| / correlation_time_s)``, stepped exactly for any ``dt``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class WindParams:
    """Mean wind and gust statistics (NED)."""

    mean_wind_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Steady wind velocity (the air's velocity) [m/s] NED; a headwind for northward flight is -x."""
    turbulence_rms_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Stationary RMS of the gust per axis [m/s]."""
    correlation_time_s: float = 2.0
    """Gust correlation time T [s]: autocorrelation exp(-|t| / T)."""

    def __post_init__(self) -> None:
        for name in ("mean_wind_ned_m_s", "turbulence_rms_m_s"):
            arr = np.asarray(getattr(self, name), dtype=np.float64)
            if arr.shape != (3,) or not np.all(np.isfinite(arr)):
                raise ValueError(f"WindParams.{name}: expected 3 finite values, got {getattr(self, name)!r}")
        if np.any(np.asarray(self.turbulence_rms_m_s) < 0):
            raise ValueError("WindParams.turbulence_rms_m_s: must be >= 0")
        if not (math.isfinite(self.correlation_time_s) and self.correlation_time_s > 0):
            raise ValueError(f"WindParams.correlation_time_s: must be > 0, got {self.correlation_time_s!r}")


def gust_step(
    gust_ned_m_s: np.ndarray, dt_s: float, params: WindParams, rng: np.random.Generator
) -> np.ndarray:
    """Exact Ornstein-Uhlenbeck update of the (N, 3) gusts over ``dt_s``:
    ``g <- g e^{-dt/T} + sigma sqrt(1 - e^{-2 dt/T}) xi``, ``xi ~ N(0, I)``.  Returns a new array."""
    phi = math.exp(-dt_s / params.correlation_time_s)
    sigma = np.asarray(params.turbulence_rms_m_s, dtype=np.float64) * math.sqrt(1.0 - phi * phi)
    g = np.asarray(gust_ned_m_s, dtype=np.float64)
    return g * phi + rng.standard_normal(g.shape) * sigma


class GustWind:
    """Per-agent wind (mean + gust) with the same ``append``/``keep`` population API as
    ``VelocityPlant``.  Gusts start from their stationary distribution."""

    def __init__(self, params: WindParams, n_agents: int, rng: np.random.Generator) -> None:
        self._params = params
        self._rng = rng
        self._gust = self._draw(n_agents)

    def _draw(self, n: int) -> np.ndarray:
        return self._rng.standard_normal((n, 3)) * np.asarray(self._params.turbulence_rms_m_s, dtype=np.float64)

    @property
    def wind_ned_m_s(self) -> np.ndarray:
        """(N, 3) current wind velocity [m/s] NED."""
        return self._gust + np.asarray(self._params.mean_wind_ned_m_s, dtype=np.float64)

    def step(self, dt_s: float) -> np.ndarray:
        """Advance the gusts by ``dt_s``; returns the new (N, 3) wind."""
        self._gust = gust_step(self._gust, dt_s, self._params, self._rng)
        return self.wind_ned_m_s

    def append(self, n: int) -> None:
        """Add ``n`` agents (gusts drawn from the stationary distribution)."""
        self._gust = np.concatenate([self._gust, self._draw(n)])

    def keep(self, index: np.ndarray) -> None:
        """Keep the agents selected by ``index`` (bool mask or integer indices)."""
        self._gust = np.ascontiguousarray(self._gust[np.asarray(index)])
