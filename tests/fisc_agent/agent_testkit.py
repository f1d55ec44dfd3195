"""Test helpers for the agent tests: a small synthetic tunnel map (imported by conftest and tests)."""

from __future__ import annotations

import numpy as np



def tunnel_arrays(length_m: float = 3.0, radius_m: float = 1.0, cell_m: float = 0.5, speed_m_s: float = 2.0,
                  n_max: int = 3, seed: int = 0) -> tuple[dict, dict]:
    """A cylindrical tunnel of CVs along +x (axis on cell faces), flow speeding up along x."""
    n_side = int(round(2 * radius_m / cell_m))
    nx = int(round(length_m / cell_m))
    origin = np.array([0.0, -radius_m, -radius_m])
    grid = -np.ones((nx, n_side, n_side), dtype=np.int32)
    idx, centers = [], []
    for i in range(nx):
        for j in range(n_side):
            for k in range(n_side):
                c = origin + (np.array([i, j, k]) + 0.5) * cell_m
                if np.hypot(c[1], c[2]) <= radius_m:
                    grid[i, j, k] = len(idx)
                    idx.append((i, j, k))
                    centers.append(c)
    n = len(idx)
    centers = np.array(centers)
    rng = np.random.default_rng(seed)
    mean = np.zeros((n, 3))
    mean[:, 0] = speed_m_s * (1.0 + 0.2 * centers[:, 0] / length_m)
    mean[:, 1] = -0.1 * centers[:, 1]
    mean[:, 2] = -0.1 * centers[:, 2]
    n_star = rng.integers(2, n_max + 1, size=n).astype(np.int32)
    fit = np.full((n, n_max, 3), np.nan)
    for j in range(n):
        dev = rng.normal(0.0, 0.3, size=(n_star[j], 3))
        dev -= dev.mean(axis=0)
        fit[j, :n_star[j]] = mean[j] + dev
    zeros = np.zeros(n)
    arrays = {
        "cv_center_m": centers, "cv_index": np.array(idx, dtype=np.int32), "grid_cv": grid, "n_star": n_star,
        "fit_velocity_m_s": fit, "fit_mean_velocity_m_s": mean, "fit_pressure": zeros, "fit_loss": zeros,
        "target_velocity_m_s": mean, "target_pressure_gauge_pa": zeros, "target_density_kg_m3": zeros + 1.2,
        "swarm_pressure_target": zeros, "node_count": np.ones(n, dtype=np.int32),
    }
    meta = {
        "map_version": 1, "n_cv": n, "grid": {"origin_m": origin.tolist(), "cell_size_m": cell_m,
                                               "shape": list(grid.shape)},
        "n_range": [2, n_max], "scale": 1.0, "kappa": 1.0, "agent_mass_kg": 1.0, "max_speed_m_s": 5.0,
    }
    return meta, arrays


def tunnel_map_bytes(signing_key: bytes | None = None, map_version: int = 1, **kw) -> bytes:
    from fisc_ground.mapwrite import encode_map

    meta, arrays = tunnel_arrays(**kw)
    meta["map_version"] = map_version
    return encode_map(meta, arrays, signing_key)


