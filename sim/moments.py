"""The per-CV moments of a swarm's current sample (``fisc_ground.fields.swarm_fields.cv_moments`` of
its CVs and map-frame velocities), in one numba pass when numba is installed.

``cv_moments`` is the reference: it sums with ``np.bincount`` (agent by agent, in order) and forms
``||v||^2`` with ``np.einsum``; the kernel (``sim.jit_kernels.cv_moment_sums``) adds the same terms in
the same order, so both give the same bits (tests/sim/test_moments.py), without the dozen small numpy
passes that cost more than the sums at 10^3 agents.
"""

from __future__ import annotations

import numpy as np

from fisc_ground.fields.swarm_fields import CVMoments, cv_moments
from sim.kernels import jit_kernels


def swarm_moments(cv: np.ndarray, vel_ned_m_s: np.ndarray, map_to_ned: np.ndarray, mass_kg: float, n_cv: int,
                  reference_velocity_m_s: np.ndarray) -> CVMoments:
    """``cv_moments(cv, vel_ned_m_s * map_to_ned, mass_kg, n_cv, reference_velocity_m_s)``.

    ``cv`` (n,) CV ids (-1: outside, ignored); ``vel_ned_m_s`` (n, 3) NED velocities and ``map_to_ned``
    (3,) the +-1 axis signs to the map frame; ``mass_kg`` one mass for every agent (> 0);
    ``reference_velocity_m_s`` (n_cv, 3) the per-CV reference of the dispersion moment."""
    jk = jit_kernels()
    if jk is None:
        return cv_moments(cv, vel_ned_m_s * map_to_ned, mass_kg, n_cv, reference_velocity_m_s)
    mass = float(mass_kg)
    if not mass > 0.0:
        raise ValueError("masses must be finite and > 0")
    ref = np.ascontiguousarray(reference_velocity_m_s, dtype=float)
    if ref.shape != (n_cv, 3):
        raise ValueError(f"reference_velocity must be ({n_cv}, 3) (one per CV), got shape {ref.shape}")
    cv = np.ascontiguousarray(cv, dtype=np.int64)
    vel = np.ascontiguousarray(vel_ned_m_s, dtype=float)
    if vel.shape != (cv.shape[0], 3):
        raise ValueError(f"velocities must be ({cv.shape[0]}, 3), got shape {vel.shape}")
    count, mass_sum, m_v2, m_dev2 = (np.zeros(n_cv) for _ in range(4))
    momentum = np.zeros((n_cv, 3))
    bad, finite = jk.cv_moment_sums(cv, vel, np.ascontiguousarray(map_to_ned, dtype=float), mass, ref, count, mass_sum,
                                    momentum, m_v2, m_dev2)  # the checks of cv_moments in the same pass
    if bad:
        raise ValueError(f"cv_ids must be in [-1, n_cv = {n_cv}), got {int(cv.min())}..{int(cv.max())}")
    if not finite:
        raise ValueError("velocities of agents inside the map must be finite")
    return CVMoments(count=count, mass_kg=mass_sum, momentum_kg_m_s=momentum, m_v2_kg_m2_s2=m_v2,
                     m_dev2_kg_m2_s2=m_dev2)
