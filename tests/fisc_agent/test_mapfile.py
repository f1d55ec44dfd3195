"""The map container: what a valid map is, and that every corruption is refused with its reason."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fisc_agent.map.codec import MapError, MapErrorKind, decode_map, encode_map, load_map
from fisc_ground.maps.write import generate_keypair, read_signing_key, write_map


def tiny_map_parts(n_cv: int = 3, n_max: int = 4) -> tuple[dict, dict]:
    """A small, valid map: n_cv CVs in a row along x."""
    rng = np.random.default_rng(1)
    grid = np.full((n_cv, 1, 1), -1, dtype=np.int32)
    grid[:, 0, 0] = np.arange(n_cv)
    vel = rng.normal(size=(n_cv, n_max, 3))
    vel[:, -1] = np.nan
    meta = {"map_version": 7, "n_cv": n_cv,
            "grid": {"origin_m": [0.0, -0.5, -0.5], "cell_size_m": 0.5, "shape": [n_cv, 1, 1]},
            "n_range": [2, n_max], "scale": 0.5, "kappa": 1e-3, "agent_mass_kg": 1.0}
    arrays = {
        "cv_center_m": np.c_[0.25 + 0.5 * np.arange(n_cv), np.full(n_cv, -0.25), np.full(n_cv, -0.25)],
        "cv_index": np.c_[np.arange(n_cv), np.zeros(n_cv), np.zeros(n_cv)],
        "grid_cv": grid,
        "n_star": np.full(n_cv, n_max - 1),
        "fit_velocity_m_s": vel,
        "fit_mean_velocity_m_s": np.nanmean(vel, axis=1),
        "fit_pressure": np.ones(n_cv),
        "fit_loss": np.zeros(n_cv),
        "target_velocity_m_s": np.nanmean(vel, axis=1),
        "target_pressure_gauge_pa": -np.arange(n_cv, dtype=float),
        "target_density_kg_m3": np.full(n_cv, 1.2),
        "swarm_pressure_target": np.ones(n_cv),
        "node_count": np.full(n_cv, 5),
    }
    return meta, arrays


@pytest.fixture()
def keys(tmp_path):
    key, pub = generate_keypair(tmp_path / "ground")
    return read_signing_key(key), pub


def test_round_trip_preserves_header_and_arrays():
    meta, arrays = tiny_map_parts()
    cmap = decode_map(encode_map(meta, arrays))
    assert cmap.n_cv == 3 and cmap.map_version == 7 and cmap.cell_size_m == 0.5
    assert cmap.grid_shape == (3, 1, 1)
    np.testing.assert_array_equal(cmap["fit_velocity_m_s"], arrays["fit_velocity_m_s"])
    assert cmap["grid_cv"].dtype == np.dtype("<i4")
    assert not cmap.signed
    for entry in cmap.body["arrays"].values():
        assert entry["offset"] % 64 == 0


def test_arrays_are_read_only_views():
    cmap = decode_map(encode_map(*tiny_map_parts()))
    with pytest.raises(ValueError):
        cmap["n_star"][0] = 1


def test_signed_map_verifies_with_the_trusted_key(keys):
    seed, pub = keys
    data = encode_map(*tiny_map_parts(), signing_key=seed)
    cmap = decode_map(data, trusted_keys=[bytes.fromhex(pub.read_text())])
    assert cmap.signed and cmap.public_key == pub.read_text().strip()


def test_stranger_signed_map_is_refused(keys, tmp_path):
    _, pub = keys
    stranger, _ = generate_keypair(tmp_path / "stranger")
    data = encode_map(*tiny_map_parts(), signing_key=read_signing_key(stranger))
    with pytest.raises(MapError, match="signature: signed by a key that is not trusted"):
        decode_map(data, trusted_keys=[bytes.fromhex(pub.read_text())])


def test_unsigned_map_is_refused_when_a_key_is_required(keys):
    _, pub = keys
    with pytest.raises(MapError, match="signature: map is unsigned"):
        decode_map(encode_map(*tiny_map_parts()), trusted_keys=[bytes.fromhex(pub.read_text())])


def test_forged_signature_is_refused(keys):
    seed, pub = keys
    data = bytearray(encode_map(*tiny_map_parts(), signing_key=seed))
    seal_at = data.rindex(b'"signature":"') + len(b'"signature":"')
    data[seal_at] = ord("0") if data[seal_at] != ord("0") else ord("1")
    with pytest.raises(MapError, match="signature"):
        decode_map(bytes(data), trusted_keys=[bytes.fromhex(pub.read_text())])


def test_flipped_payload_byte_fails_the_hash():
    data = bytearray(encode_map(*tiny_map_parts()))
    data[len(data) // 2] ^= 0x40
    with pytest.raises(MapError, match="sha256|header|schema"):
        decode_map(bytes(data))


def test_refusals_carry_their_kind_and_source():
    data = encode_map(*tiny_map_parts())
    cases = ((b"NOTAMAP\0" + data[8:], MapErrorKind.MAGIC), (data[:5], MapErrorKind.TRUNCATED),
             (data + b"x", MapErrorKind.TRAILING), (data[:8] + b"\x09" + data[9:], MapErrorKind.CONTAINER))
    for blob, kind in cases:
        with pytest.raises(MapError) as info:
            decode_map(blob, source="m.fiscmap")
        assert info.value.kind == kind and info.value.source == "m.fiscmap"
        assert str(info.value).startswith(f"m.fiscmap: {kind.value}: ")


def test_truncated_map_is_refused_naming_truncation():
    data = encode_map(*tiny_map_parts())
    for cut in (5, 20, len(data) // 2, len(data) - 1):
        with pytest.raises(MapError, match="truncated"):
            decode_map(data[:cut])


def test_wrong_schema_version_is_refused_even_when_rehashed():
    meta, arrays = tiny_map_parts()
    data = encode_map(meta, arrays)
    body_len = struct.unpack_from("<Q", data, 12)[0]
    body = json.loads(data[20:20 + body_len])
    body["schema_version"] = 99
    from fisc_agent.map.codec import canonical_json
    import hashlib

    raw = canonical_json(body)
    rest = data[20 + body_len:]
    payload_len = struct.unpack_from("<Q", rest, 0)[0]
    sealed = data[:12] + struct.pack("<Q", len(raw)) + raw + rest[:8 + payload_len]
    seal = canonical_json({"sha256": hashlib.sha256(sealed).hexdigest(), "signature": None, "public_key": None})
    with pytest.raises(MapError, match="schema_version: map has 99"):
        decode_map(sealed + struct.pack("<Q", len(seal)) + seal)


def test_missing_array_is_refused_by_the_writer():
    meta, arrays = tiny_map_parts()
    del arrays["n_star"]
    with pytest.raises(MapError, match="array 'n_star' is missing"):
        decode_map(encode_map(meta, arrays))


def test_write_map_is_atomic_and_leaves_no_partial_file(tmp_path):
    meta, arrays = tiny_map_parts()
    good = tmp_path / "m.fiscmap"
    write_map(good, meta, arrays)
    before = good.read_bytes()
    bad_arrays = dict(arrays, n_star=np.zeros(99, dtype=np.int32))  # wrong row count
    with pytest.raises(MapError):
        write_map(good, meta, bad_arrays)
    assert good.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.fiscmap"]


def test_load_map_names_the_file(tmp_path):
    path = tmp_path / "x.fiscmap"
    path.write_bytes(b"not a map at all")
    with pytest.raises(MapError, match=r"x\.fiscmap: magic"):
        load_map(path)


def test_keygen_refuses_to_overwrite(tmp_path):
    generate_keypair(tmp_path / "k")
    with pytest.raises(FileExistsError):
        generate_keypair(tmp_path / "k")
    assert oct((tmp_path / "k.key").stat().st_mode & 0o777) == "0o600"


VALID = encode_map(*tiny_map_parts())


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.integers(0, len(VALID) - 1), st.integers(1, 255)), min_size=1, max_size=4,
                unique_by=lambda flip: flip[0]))
def test_fuzz_any_byte_corruption_is_refused(flips):
    data = bytearray(VALID)
    for pos, xor in flips:
        data[pos] ^= xor
    with pytest.raises(MapError):
        decode_map(bytes(data))


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=400))
def test_fuzz_arbitrary_bytes_never_crash_the_reader(blob):
    with pytest.raises(MapError):
        decode_map(blob)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, len(VALID) - 1), st.binary(min_size=0, max_size=50))
def test_fuzz_truncation_and_garbage_tail_are_refused(cut, tail):
    data = VALID[:cut] + tail
    if data == VALID:
        return
    with pytest.raises(MapError):
        decode_map(data)
