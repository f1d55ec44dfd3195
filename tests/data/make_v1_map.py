"""How ``map_v1.fiscmap`` was made (kept for provenance; do NOT re-run to "fix" a failing test).

``map_v1.fiscmap`` is a frozen schema-version-1 map, signed with the fixed test seed below
(``map_v1.pub`` is its public key).  ``tests/fisc_agent/test_contracts.py`` checks that every
later reader still loads it with the same sha256, header and array values: maps written by an
older ground station must keep flying.  Regenerating it would hide exactly the break the test
exists to catch.  Run once, with the software of 2026-12 (schema version 1):

    python tests/data/make_v1_map.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fisc_agent.map.codec import encode_map

SEED = bytes(range(32))  # a public test seed: this key signs nothing real


def parts() -> tuple[dict, dict]:
    nx, ny, nz, cell = 3, 2, 1, 0.5
    origin = np.array([0.0, -0.5, -0.25])
    idx = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
    n = len(idx)
    centers = origin + (idx + 0.5) * cell
    n_star = np.array([2, 3, 2, 3, 2, 3])
    vel = np.zeros((n, 3, 3))
    for j in range(n):
        for k in range(3):
            vel[j, k] = (1.0 + 0.5 * j + 0.25 * k, 0.1 * k - 0.1, 0.05 * (j % 2)) if k < n_star[j] else (np.nan,) * 3
    mean = np.nanmean(vel, axis=1)
    meta = {"map_version": 7, "n_cv": n, "grid": {"origin_m": origin.tolist(), "cell_size_m": cell, "shape": [nx, ny, nz]},
            "n_range": [2, 3], "scale": 1.25, "kappa": 0.002, "agent_mass_kg": 1.5, "max_speed_m_s": 5.0,
            "created_utc": "2026-12-01T00:00:00+00:00", "software_version": "0.1.0",
            "provenance": {"reference": {"name": "test fixture", "source": "tests/data/make_v1_map.py",
                                          "pressure_kind": "gauge"}},
            "fit": {"seconds": 0.001, "velocity_rmse": 0.0, "pressure_rmse": 0.0}}
    arrays = {
        "cv_center_m": centers, "cv_index": idx, "grid_cv": np.arange(n).reshape(nx, ny, nz), "n_star": n_star,
        "fit_velocity_m_s": vel, "fit_mean_velocity_m_s": mean, "fit_pressure": 0.5 + 0.1 * np.arange(n),
        "fit_loss": np.full(n, 1e-9), "target_velocity_m_s": mean, "target_pressure_gauge_pa": 100.0 - 10.0 * np.arange(n),
        "target_density_kg_m3": 1.2 - 0.01 * np.arange(n), "swarm_pressure_target": 0.5 + 0.1 * np.arange(n),
        "node_count": np.full(n, 8),
    }
    return meta, arrays


if __name__ == "__main__":
    from nacl.signing import SigningKey

    here = Path(__file__).parent
    (here / "map_v1.fiscmap").write_bytes(encode_map(*parts(), SEED))
    (here / "map_v1.pub").write_text(SigningKey(SEED).verify_key.encode().hex() + "\n")
