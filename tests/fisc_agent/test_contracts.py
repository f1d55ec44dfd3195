"""Cross-version contracts: fixed slot-hash vectors and a checked-in schema-version-1 map.

Agents of different software versions fly in one swarm and load maps written by older ground
stations.  These values are therefore pinned as literals: a changed hash constant (even if
changed identically in every copy) or a reader that no longer loads a version-1 map breaks a
mixed fleet, and must fail here.  Never "fix" this file by pasting new numbers.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fisc_agent.map.hashing import slot_hash, slot_hash_int, slot_index
from fisc_agent.map.lookup import CommandField
from fisc_agent.map.codec import load_map
from sim.kernels import cell_and_slot_helpers

DATA = Path(__file__).resolve().parents[1] / "data"

#: (agent_id, cv_id) -> (h, [h mod N for N in 2..10]); computed once from the 32-bit mix of
#: DESIGN.md section 3 (constants 0x9E3779B1, 0x85EBCA77, 0x27D4EB2F, 0x2C1B3C6D).
SLOT_VECTORS = {
    (0, 0): (775526073, [1, 0, 1, 3, 3, 0, 1, 6, 3]),
    (1, 0): (1657528889, [1, 2, 1, 4, 5, 2, 1, 5, 9]),
    (0, 1): (1099207315, [1, 1, 3, 0, 1, 3, 3, 1, 5]),
    (1, 1): (4024739389, [1, 1, 1, 4, 1, 6, 5, 4, 9]),
    (7, 42): (3927952812, [0, 0, 0, 2, 0, 0, 4, 3, 2]),
    (123456, 789): (1836877987, [1, 1, 3, 2, 1, 0, 3, 1, 7]),
    (4294967295, 4294967295): (1538986318, [0, 1, 2, 3, 4, 2, 6, 7, 8]),
    (4294967301, 3): (157712305, [1, 1, 1, 0, 1, 2, 1, 4, 5]),  # ids are taken mod 2^32
    (1000, 999999): (3303745390, [0, 1, 2, 0, 4, 1, 6, 1, 0]),
}


def _reference_mix(a: int, j: int) -> int:
    """The documented mix written out once more, independently of the three copies under test."""
    a, j = a % 2**32, j % 2**32
    h = ((a * 2654435761) ^ (j * 2246822519 + 668265263)) % 2**32
    h ^= h >> 15
    h = (h * 739982445) % 2**32
    return h ^ (h >> 12)


@pytest.mark.parametrize("pair", list(SLOT_VECTORS))
def test_slot_hash_fixed_vectors_in_every_copy(pair):
    a, j = pair
    h, slots = SLOT_VECTORS[pair]
    assert _reference_mix(a, j) == h
    assert int(slot_hash(a, j)) == h                                  # onboard, vectorised
    assert slot_hash_int(a, j) == h                                   # onboard, scalar hot path
    assert [int(slot_index(a, j, n)) for n in range(2, 11)] == slots
    _, slot_of = cell_and_slot_helpers()                              # simulator kernels (numba)
    assert [int(slot_of(a, j, n)) for n in range(2, 11)] == slots


def test_numba_slot_twin_equals_the_pure_hash_on_1e5_inputs():
    """``sim.kernels``' jitted slot index is a twin of ``fisc_agent.map.hashing.slot_mix``: equal on 10^5 inputs
    spanning the whole 32-bit id range (and ids beyond it, reduced the same way)."""
    rng = np.random.default_rng(11)
    n = 100_000
    a = rng.integers(0, 2**40, size=n, dtype=np.int64)
    j = rng.integers(0, 2**33, size=n, dtype=np.int64)
    n_star = rng.integers(1, 11, size=n, dtype=np.int64)
    expect = slot_index(a, j, n_star)
    _, slot_of = cell_and_slot_helpers()
    got = _slot_of_many(slot_of, a, j, n_star)
    np.testing.assert_array_equal(got, expect)


def _slot_of_many(slot_of, a, j, n_star):
    import numba

    @numba.njit(cache=False)
    def many(a, j, n_star):
        out = np.empty(a.size, dtype=np.int64)
        for i in range(a.size):
            out[i] = slot_of(a[i], j[i], n_star[i])
        return out

    return many(a, j, n_star)


def test_slot_hash_vectorised_over_arrays_matches_the_vectors():
    pairs = np.array(list(SLOT_VECTORS), dtype=np.uint64)
    expect = [h for h, _ in SLOT_VECTORS.values()]
    assert slot_hash(pairs[:, 0], pairs[:, 1]).tolist() == expect


V1_SHA256 = "4831a74edf954bf2c4d61173968d8a33c195d8affdc59a7653499d36b0a65cbf"


def test_the_checked_in_version_1_map_still_loads_with_the_same_content():
    cmap = load_map(DATA / "map_v1.fiscmap", trusted_key=DATA / "map_v1.pub")
    assert cmap.sha256 == V1_SHA256 and cmap.signed
    assert cmap.body["schema_version"] == 1 and cmap.map_version == 7
    assert cmap.n_cv == 6 and cmap.grid_shape == (3, 2, 1) and cmap.cell_size_m == 0.5
    assert cmap.scale == 1.25 and float(cmap.body["agent_mass_kg"]) == 1.5
    np.testing.assert_array_equal(cmap["n_star"], [2, 3, 2, 3, 2, 3])
    np.testing.assert_allclose(cmap["fit_velocity_m_s"][1, :3], [[1.5, -0.1, 0.05], [1.75, 0.0, 0.05], [2.0, 0.1, 0.05]])
    assert np.isnan(cmap["fit_velocity_m_s"][0, 2]).all()  # slots beyond N* are NaN
    np.testing.assert_allclose(cmap["target_pressure_gauge_pa"], [100, 90, 80, 70, 60, 50])


def test_the_version_1_map_gives_the_same_commands():
    field = CommandField.from_map(load_map(DATA / "map_v1.fiscmap"))
    pts = np.array([[0.1, -0.4, 0.0], [1.4, 0.4, 0.1], [5.0, 0.0, 0.0]])
    np.testing.assert_array_equal(field.cv_of(pts), [0, 5, -1])
    np.testing.assert_allclose(field.command(pts[:2], np.array([3, 4]), "slot"), [[1.5625, 0.0, 0.0],
                                                                                  [4.6875, 0.0, 0.0625]])
    np.testing.assert_allclose(field.command(pts[:2], np.array([3, 4]), "mean"), [[1.40625, -0.0625, 0.0],
                                                                                  [4.6875, 0.0, 0.0625]])


def test_enums_at_the_seams_match_the_wire_tables():
    """Mission states and map-refusal kinds are the names the telemetry codes carry."""
    from fisc_agent.zenoh import telemetry_codec as tc
    from fisc_agent.map.codec import MapErrorKind
    from fisc_agent.flight.mission import State

    assert {s.value for s in State} <= set(tc.STATES)
    assert set(tc.REJECT_REASONS[1:]) <= {k.value for k in MapErrorKind}
