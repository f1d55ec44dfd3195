"""The map codec at its boundaries (issue 38): signatures, seal, container and schema refusals named exactly.

Every refusal is checked by its kind and its whole message (``"<source>: <kind>: <detail>"``), and every
limit from both sides: a map one byte short, an array ending exactly at the payload's end, a length scale
just above 0, a schema-2 map with and without its face field.
"""

from __future__ import annotations

import hashlib
import json
import struct

import numpy as np
import pytest

from fisc_agent.map.codec import (MAGIC, MapError, MapErrorKind, MapFileError, canonical_json, decode_map, encode_map,
                                  load_map, read_public_key)
from fisc_ground.maps.write import generate_keypair, read_signing_key
from .test_mapfile import tiny_map_parts

U64 = struct.Struct("<Q")


def split(data: bytes) -> tuple[dict, bytes, dict]:
    """(header, payload, seal) of map bytes."""
    n = U64.unpack_from(data, 12)[0]
    body = json.loads(data[20:20 + n])
    m = U64.unpack_from(data, 20 + n)[0]
    payload = data[28 + n:28 + n + m]
    return body, payload, json.loads(data[36 + n + m:])


def sealed_part(body: dict | bytes, payload: bytes) -> bytes:
    """The bytes the seal's hash covers."""
    raw = body if isinstance(body, bytes) else canonical_json(body)
    return MAGIC + struct.pack("<I", 1) + U64.pack(len(raw)) + raw + U64.pack(len(payload)) + payload


def container(body: dict | bytes, payload: bytes, seal: dict | bytes | None = None) -> bytes:
    """Map bytes around ``body`` and ``payload`` with a correct hash (``seal`` replaces the seal)."""
    sealed = sealed_part(body, payload)
    if seal is None:
        seal = {"sha256": hashlib.sha256(sealed).hexdigest(), "signature": None, "public_key": None}
    seal_raw = seal if isinstance(seal, bytes) else canonical_json(seal)
    return sealed + U64.pack(len(seal_raw)) + seal_raw


def refusal(data: bytes, trusted_keys: list[bytes] | None = None) -> tuple[MapErrorKind, str]:
    with pytest.raises(MapError) as err:
        decode_map(data, trusted_keys)
    return err.value.kind, str(err.value)


def with_body(change) -> bytes:
    """The tiny map with its header changed by ``change(body)`` (rehashed: only the change is wrong)."""
    body, payload, _ = split(encode_map(*tiny_map_parts()))
    change(body)
    return container(body, payload)


def v2_parts() -> tuple[dict, dict]:
    """A valid schema-2 map: the tiny map with a face field, design density and flight table."""
    meta, arrays = tiny_map_parts()
    meta["flight"] = {"mode": "staggered", "lookahead_s": 0.0, "persistence_s": 2.0}
    arrays.update(face_u_x_m_s=np.ones((4, 1, 1)), face_u_y_m_s=np.zeros((3, 2, 1)), face_u_z_m_s=np.zeros((3, 1, 2)),
                  cv_design_density=np.ones(3))
    return meta, arrays


@pytest.fixture()
def keys(tmp_path):
    key, pub = generate_keypair(tmp_path / "ground")
    return read_signing_key(key), pub


# ------------------------------------------------------------------------------ container and seal
def test_container_refusals_name_the_problem_exactly():
    data = encode_map(*tiny_map_parts())
    body_n = U64.unpack_from(data, 12)[0]
    pay_n = U64.unpack_from(data, 20 + body_n)[0]
    seal_at = 28 + body_n + pay_n
    T = MapErrorKind.TRUNCATED
    assert refusal(data[:11]) == (T, "<bytes>: truncated: file too short")
    assert refusal(data[:12]) == (T, "<bytes>: truncated: file ends inside the header length field")  # 12: long enough
    assert refusal(data[:19]) == (T, "<bytes>: truncated: file ends inside the header length field")
    assert refusal(data[:20]) == (T, f"<bytes>: truncated: header declares {body_n} bytes, only 0 present")
    assert refusal(data[:20 + body_n + 8 + 5]) == (T, f"<bytes>: truncated: payload declares {pay_n} bytes, only 5 present")
    assert refusal(data[:seal_at + 7]) == (T, "<bytes>: truncated: file ends inside the seal length field")
    for blob in (b"NOTAMAP\0" + data[8:], b"NOTAMAP\0" + data[8:12]):  # 12 bytes: not too short, just not a map
        assert refusal(blob) == (MapErrorKind.MAGIC, "<bytes>: magic: not a FISC map file (bad magic bytes)")
    assert refusal(data[:8] + b"\x09" + data[9:]) == (MapErrorKind.CONTAINER,
                                                      "<bytes>: container: version 9 is not supported (expected 1)")
    assert refusal(data + b"xyz") == (MapErrorKind.TRAILING, "<bytes>: trailing: 3 unexpected bytes after the seal")
    flipped = bytearray(data)
    flipped[20 + body_n + 8] ^= 1  # the payload's first byte
    assert refusal(bytes(flipped)) == (MapErrorKind.SHA256,
                                       "<bytes>: sha256: content hash does not match (map corrupted or modified)")


def test_a_seal_must_be_a_json_table_of_exactly_its_three_keys():
    body, payload, seal = split(encode_map(*tiny_map_parts()))
    kind, text = refusal(container(body, payload, b"{"))
    assert kind == MapErrorKind.SEAL and text.startswith("<bytes>: seal: not valid JSON (Expecting")
    keys_msg = "<bytes>: seal: expected exactly the keys ['public_key', 'sha256', 'signature']"
    assert refusal(container(body, payload, sorted(seal))) == (MapErrorKind.SEAL, keys_msg)  # the keys, as a list
    assert refusal(container(body, payload, {"sha256": seal["sha256"], "signature": None})) == (MapErrorKind.SEAL,
                                                                                                keys_msg)
    assert refusal(container(body, payload, {**seal, "extra": 1})) == (MapErrorKind.SEAL, keys_msg)


def test_a_header_must_be_json_with_an_array_table():
    _, payload, _ = split(encode_map(*tiny_map_parts()))
    kind, text = refusal(container(b"{", payload))
    assert kind == MapErrorKind.HEADER and text.startswith("<bytes>: header: not valid JSON (Expecting")
    for body in (b"[]", b'{"arrays":5}', b"{}"):
        assert refusal(container(body, payload)) == (MapErrorKind.SCHEMA, "<bytes>: schema: header has no array table")


def test_canonical_json_sorts_keys_and_refuses_nan():
    assert canonical_json({"b": 1, "a": [1.5, None]}) == b'{"a":[1.5,null],"b":1}'
    with pytest.raises(ValueError):
        canonical_json({"x": float("nan")})


def test_map_error_text_and_location():
    assert str(MapError(MapErrorKind.SCHEMA, "bad")) == "schema: bad"
    inner = MapError(MapErrorKind.SCHEMA, "bad", source="chunk 3")
    assert str(inner) == "chunk 3: schema: bad"
    assert str(inner.at("map.fiscmap")) == "map.fiscmap: chunk 3: schema: bad"
    assert str(MapError(MapErrorKind.SCHEMA, "bad").at("m")) == "m: schema: bad"


# ------------------------------------------------------------------------------ signatures
def test_a_signed_map_verifies_without_a_trusted_key_and_reports_its_key_and_hash(keys):
    seed, pub = keys
    data = encode_map(*tiny_map_parts(), signing_key=seed)
    cmap = decode_map(data)
    assert cmap.signed and cmap.public_key == pub.read_text().strip()
    body, payload, seal = split(data)
    assert cmap.sha256 == seal["sha256"] == hashlib.sha256(sealed_part(body, payload)).hexdigest()


def test_a_key_without_a_signature_proves_nothing():
    body, payload, _ = split(encode_map(*tiny_map_parts()))
    digest = hashlib.sha256(sealed_part(body, payload)).hexdigest()
    cmap = decode_map(container(body, payload, {"sha256": digest, "signature": None, "public_key": "ab" * 32}))
    assert not cmap.signed and cmap.public_key is None


def test_signature_refusals_are_named_exactly(keys):
    seed, pub = keys
    trusted = [bytes.fromhex(pub.read_text())]
    data = encode_map(*tiny_map_parts(), signing_key=seed)
    body, payload, seal = split(data)
    S = MapErrorKind.SIGNATURE
    kind, text = refusal(container(body, payload, {**seal, "signature": "zz"}))
    assert (kind, text) == (S, "<bytes>: signature: malformed signature or key in seal (non-hexadecimal number found "
                               "in fromhex() arg at position 0)")
    bad = seal["signature"][:-1] + ("0" if seal["signature"][-1] != "0" else "1")
    forged = container(body, payload, {**seal, "signature": bad})
    assert refusal(forged) == (S, "<bytes>: signature: Ed25519 signature does not verify")  # no trusted key: still checked
    assert refusal(forged, trusted) == (S, "<bytes>: signature: Ed25519 signature does not verify")
    keyless = container(body, payload, {**seal, "public_key": None})  # a signature without its key
    assert refusal(keyless) == (S, "<bytes>: signature: Ed25519 signature does not verify")
    assert refusal(keyless, trusted) == (S, "<bytes>: signature: signed by a key that is not trusted")
    assert refusal(encode_map(*tiny_map_parts()), trusted) == (
        S, "<bytes>: signature: map is unsigned but a trusted key was given")
    assert not decode_map(encode_map(*tiny_map_parts()), []).signed  # an empty key list asks for nothing


# ------------------------------------------------------------------------------ the array table
def test_array_table_entries_are_checked_by_name():
    S = MapErrorKind.SCHEMA
    body, payload, _ = split(encode_map(*tiny_map_parts()))
    entry = body["arrays"]["n_star"]

    def with_entry(**change):
        table = dict(body["arrays"], n_star={k: v for k, v in {**entry, **change}.items() if v is not None})
        return container({**body, "arrays": table}, payload)

    assert refusal(with_entry(dtype=None)) == (S, "<bytes>: schema: array 'n_star' has a malformed table entry ('dtype')")
    invalid = (S, "<bytes>: schema: array 'n_star' has an invalid dtype or shape")
    assert refusal(with_entry(dtype="|O8")) == invalid                           # objects: never from bytes
    assert refusal(with_entry(dtype="|S0", shape=[0], nbytes=0)) == invalid      # no bytes per item
    assert refusal(with_entry(shape=[-3], nbytes=-12)) == invalid
    assert refusal(with_entry(nbytes=16)) == (S, "<bytes>: schema: array 'n_star' size does not match dtype <i4 and "
                                                 "shape (3,)")
    outside = (S, "<bytes>: schema: array 'n_star' lies outside the payload")
    assert refusal(with_entry(offset=-64)) == outside
    assert refusal(with_entry(offset=len(payload) - 8)) == outside  # 12 bytes from 8 before the end
    end = decode_map(with_entry(offset=len(payload) - 12))          # ends exactly at the payload's end
    assert end["n_star"].shape == (3,)


def test_extra_arrays_keep_their_dtype_little_endian_and_may_be_empty():
    meta, arrays = tiny_map_parts()
    cmap = decode_map(encode_map(meta, {**arrays, "extra": np.arange(3, dtype=">f4"), "none": np.zeros((0, 3))}))
    assert cmap["extra"].dtype.str == "<f4" and cmap["extra"].tolist() == [0.0, 1.0, 2.0]
    assert cmap["none"].shape == (0, 3) and cmap["none"].dtype.str == "<f8"


# ------------------------------------------------------------------------------ the schema
def test_schema_refusals_are_named_exactly():
    S = MapErrorKind.SCHEMA
    assert refusal(with_body(lambda b: b.update(schema="other"))) == (
        S, "<bytes>: schema: not a FISC command map (schema='other')")
    assert refusal(with_body(lambda b: b.pop("schema"))) == (S, "<bytes>: schema: not a FISC command map (schema=None)")
    assert refusal(with_body(lambda b: b.update(schema_version=3))) == (
        MapErrorKind.SCHEMA_VERSION, "<bytes>: schema_version: map has 3, this reader supports 1, 2")
    meta, arrays = tiny_map_parts()
    short = {k: v for k, v in meta.items() if k not in ("scale", "kappa")}
    assert refusal(encode_map(short, arrays)) == (S, "<bytes>: schema: header lacks scale, kappa")
    assert refusal(encode_map(meta, {**arrays, "n_star": np.zeros((3, 1))})) == (
        S, "<bytes>: schema: array 'n_star' must be <i4 of rank 1, is <i4 (3, 1)")
    assert refusal(encode_map(meta, {**arrays, "n_star": np.zeros(2)})) == (
        S, "<bytes>: schema: array 'n_star' has 2 rows, header says n_cv=3")
    grid = {**meta["grid"], "shape": [3, 1, 2]}
    assert refusal(encode_map({**meta, "grid": grid}, arrays)) == (S, "<bytes>: schema: grid_cv shape differs from "
                                                                      "grid.shape")


def test_the_grid_may_hold_more_cells_than_cvs():
    meta, arrays = tiny_map_parts()
    grid = np.full((5, 1, 1), -1, dtype=np.int32)  # two empty cells past the CVs: grid_cv has 5 rows, n_cv is 3
    grid[:3, 0, 0] = np.arange(3)
    cmap = decode_map(encode_map({**meta, "grid": {**meta["grid"], "shape": [5, 1, 1]}}, {**arrays, "grid_cv": grid}))
    assert cmap.grid_shape == (5, 1, 1) and cmap.n_cv == 3


def test_the_duct_wall_is_optional_and_checked_when_present():
    meta, arrays = tiny_map_parts()
    wall = np.array([[0.0, 1.0], [1.5, 0.5]])
    np.testing.assert_array_equal(decode_map(encode_map(meta, {**arrays, "duct_wall_m": wall}))["duct_wall_m"], wall)
    S = MapErrorKind.SCHEMA
    assert refusal(encode_map(meta, {**arrays, "duct_wall_m": wall.astype("<f4")})) == (
        S, "<bytes>: schema: array 'duct_wall_m': must be <f8, is <f4")
    assert refusal(encode_map(meta, {**arrays, "duct_wall_m": wall[::-1].copy()})) == (
        S, "<bytes>: schema: array 'duct_wall_m': duct wall: stations must be strictly ascending in x")


def test_design_keys_at_their_limits():
    meta, arrays = tiny_map_parts()
    ok = decode_map(encode_map({**meta, "separation": {"vehicle_radius_m": 0.3}, "length_scale": 0.5}, arrays))
    assert ok.body["separation"] == {"vehicle_radius_m": 0.3} and ok.body["length_scale"] == 0.5
    assert decode_map(encode_map({**meta, "length_scale": 1e-300}, arrays)).body["length_scale"] == 1e-300  # just > 0
    assert decode_map(encode_map({**meta, "length_scale": 3}, arrays)).body["length_scale"] == 3  # an int is a number
    S = MapErrorKind.SCHEMA
    assert refusal(encode_map({**meta, "separation": "wide"}, arrays)) == (
        S, "<bytes>: schema: header separation: must be a table, is str")
    assert refusal(encode_map({**meta, "separation": {"vehicle_radius_m": "big"}}, arrays)) == (
        S, "<bytes>: schema: header separation: vehicle_radius_m must be a number, is 'big'")
    for bad in (0, 0.0, -1.0, True, "1", None):
        assert refusal(encode_map({**meta, "length_scale": bad}, arrays)) == (
            S, f"<bytes>: schema: header length_scale must be a finite number > 0, is {bad!r}")
    body, payload, _ = split(encode_map(meta, arrays))  # infinity is not JSON: written by hand
    raw = canonical_json(body)[:-1] + b',"length_scale":Infinity}'
    assert refusal(container(raw, payload)) == (S, "<bytes>: schema: header length_scale must be a finite number > 0, "
                                                   "is inf")


# ------------------------------------------------------------------------------ schema 2
def test_the_schema_version_follows_the_face_field_unless_given():
    meta, arrays = v2_parts()
    assert decode_map(encode_map(meta, arrays)).schema_version == 2
    assert decode_map(encode_map({**meta, "schema_version": 1}, arrays)).schema_version == 1  # given: kept
    assert decode_map(encode_map(*tiny_map_parts())).schema_version == 1


def test_schema_2_refusals_are_named_exactly():
    meta, arrays = v2_parts()
    S = MapErrorKind.SCHEMA

    def refused(m=meta, **change):
        return refusal(encode_map({**m, "schema_version": 2}, {k: v for k, v in {**arrays, **change}.items()
                                                               if v is not None}))

    assert refused(face_u_y_m_s=None) == (S, "<bytes>: schema: version-2 array 'face_u_y_m_s' is missing")
    assert refused(cv_design_density=None) == (S, "<bytes>: schema: version-2 array 'cv_design_density' is missing")
    assert refused(face_u_x_m_s=np.ones((3, 1, 1))) == (
        S, "<bytes>: schema: array 'face_u_x_m_s' must be <f8 (4, 1, 1), is <f8 (3, 1, 1)")
    assert refused(face_u_z_m_s=np.zeros((3, 1, 2), dtype="<f4")) == (
        S, "<bytes>: schema: array 'face_u_z_m_s' must be <f8 (3, 1, 2), is <f4 (3, 1, 2)")
    assert refused(cv_design_density=np.array([1.0, np.inf, 1.0])) == (
        S, "<bytes>: schema: array 'cv_design_density' has non-finite values")
    need = (S, "<bytes>: schema: version-2 header needs a 'flight' table with mode, lookahead_s, persistence_s")
    assert refused({k: v for k, v in meta.items() if k != "flight"}) == need
    assert refused({**meta, "flight": ["mode", "lookahead_s", "persistence_s"]}) == need
    assert refused({**meta, "flight": {"mode": "slot", "lookahead_s": 0.0}}) == need
    assert refused({**meta, "flight": {**meta["flight"], "mode": 3}}) == (S, "<bytes>: schema: flight.mode must be a string")
    for key in ("lookahead_s", "persistence_s"):
        for bad in (-1e-9, True, "1", None):
            assert refused({**meta, "flight": {**meta["flight"], key: bad}}) == (
                S, f"<bytes>: schema: flight.{key} must be a finite number >= 0, is {bad!r}")
        ok = decode_map(encode_map({**meta, "flight": {**meta["flight"], key: 0}}, arrays))  # 0 itself is allowed
        assert ok.body["flight"][key] == 0
    body, payload, _ = split(encode_map(meta, arrays))
    for text, shown in ((b"NaN", "nan"), (b"Infinity", "inf")):
        raw = canonical_json(body).replace(b'"lookahead_s":0.0', b'"lookahead_s":' + text)
        assert refusal(container(raw, payload)) == (
            S, f"<bytes>: schema: flight.lookahead_s must be a finite number >= 0, is {shown}")


# ------------------------------------------------------------------------------ files and keys
def test_load_map_with_a_key_file_or_raw_key(keys, tmp_path):
    seed, pub = keys
    path = tmp_path / "m.fiscmap"
    path.write_bytes(encode_map(*tiny_map_parts(), signing_key=seed))
    assert load_map(path).n_cv == 3 and load_map(path).signed
    assert load_map(path, trusted_key=pub).signed
    assert load_map(str(path), trusted_key=bytes.fromhex(pub.read_text())).signed
    unsigned = tmp_path / "u.fiscmap"
    unsigned.write_bytes(encode_map(*tiny_map_parts()))
    with pytest.raises(MapError) as err:
        load_map(unsigned, trusted_key=pub)
    assert err.value.source == str(unsigned)
    assert str(err.value) == f"{unsigned}: signature: map is unsigned but a trusted key was given"


def test_a_file_that_is_not_a_map_is_refused_before_it_is_read(tmp_path):
    path = tmp_path / "x.fiscmap"
    path.write_bytes(b"not a map at all, and long enough")
    with pytest.raises(MapFileError) as err:
        load_map(path)
    assert err.value.kind == MapErrorKind.FILE
    assert str(err.value) == f"{path}: magic: not a FISC map (starts with b'not a ma', expected {MAGIC!r})"


def test_key_files_are_checked_by_name(keys, tmp_path):
    _, pub = keys
    spaced = tmp_path / "spaced.pub"
    spaced.write_text("\n  " + pub.read_text().strip() + "  \n")
    assert read_public_key(spaced) == bytes.fromhex(pub.read_text())
    for name, text, detail in (("hex.pub", "zz" * 32, "not a hex Ed25519 public key"),
                               ("short.pub", "ab" * 31, "an Ed25519 public key has 32 bytes, this has 31")):
        (tmp_path / name).write_text(text)
        with pytest.raises(MapError) as err:
            read_public_key(tmp_path / name)
        assert err.value.kind == MapErrorKind.KEY and str(err.value) == f"{tmp_path / name}: key: {detail}"
    with pytest.raises(MapFileError) as err:
        load_map(tmp_path / "missing.fiscmap")
    assert str(err.value) == f"{tmp_path / 'missing.fiscmap'}: FISC map not found"
    with pytest.raises(MapFileError) as err:
        read_public_key(tmp_path / "missing.pub")
    assert str(err.value) == f"{tmp_path / 'missing.pub'}: Ed25519 public key file not found"
