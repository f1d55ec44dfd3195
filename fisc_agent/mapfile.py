"""The FISC command-map container: codec, verification and the in-memory ``CommandMap``.

Layout (all integers little-endian)::

    b"FISCMAP\\0"                     magic, 8 bytes
    u32  container version           (CONTAINER_VERSION)
    u64  body length, body           canonical JSON (UTF-8, sorted keys): schema, grid, fit
                                     parameters, provenance and an ``arrays`` table giving
                                     every array's dtype, shape, offset and size
    u64  payload length, payload     the arrays, each at a 64-byte aligned offset
    u64  seal length, seal           JSON {"sha256", "signature", "public_key"}

``sha256`` covers every byte before the seal-length field.  The optional Ed25519
signature signs the 32 raw digest bytes.  This module is the onboard reader: numpy, the
standard library and PyNaCl only.  The writer lives in ``fisc_ground.mapwrite``.
"""

from __future__ import annotations

import hashlib
import json
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

MAGIC = b"FISCMAP\x00"
CONTAINER_VERSION = 1
SCHEMA = "fisc.command_map"
SCHEMA_VERSION = 2
#: Schema versions this reader accepts.  Version 2 adds the staggered face field (``FACE_ARRAYS``),
#: ``cv_design_density`` and the recommended flight settings (body key ``flight``); version-1 maps
#: (no face field, flown with the paper's settings) still load.
SUPPORTED_SCHEMA_VERSIONS = (1, 2)
ALIGN = 64
SEAL_KEYS = frozenset({"sha256", "signature", "public_key"})

#: Array name -> (dtype, rank) that schema version 1 requires.
REQUIRED_ARRAYS: dict[str, tuple[str, int]] = {
    "cv_center_m": ("<f8", 2),
    "cv_index": ("<i4", 2),
    "grid_cv": ("<i4", 3),
    "n_star": ("<i4", 1),
    "fit_velocity_m_s": ("<f8", 3),
    "fit_mean_velocity_m_s": ("<f8", 2),
    "fit_pressure": ("<f8", 1),
    "fit_loss": ("<f8", 1),
    "target_velocity_m_s": ("<f8", 2),
    "target_pressure_gauge_pa": ("<f8", 1),
    "target_density_kg_m3": ("<f8", 1),
    "swarm_pressure_target": ("<f8", 1),
    "node_count": ("<i4", 1),
}
#: Arrays schema version 2 adds: the staggered (face-centred) command field, unscaled [m/s]:
#: x faces (nx+1, ny, nz), y faces (nx, ny+1, nz), z faces (nx, ny, nz+1) (``fisc_ground.staggered``).
FACE_ARRAYS = ("face_u_x_m_s", "face_u_y_m_s", "face_u_z_m_s")
#: Keys of a schema-2 body's ``flight`` table (recommended flight settings).
FLIGHT_KEYS = ("mode", "lookahead_s", "persistence_s")
REQUIRED_BODY_KEYS = (
    "schema", "schema_version", "map_version", "n_cv", "grid", "n_range", "scale", "kappa",
    "agent_mass_kg", "arrays",
)
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")


class MapError(ValueError):
    """A map failed a check; the message names the check (``truncated``, ``sha256``, ...)."""


@dataclass(frozen=True)
class CommandMap:
    """A verified command map: header (``body``), arrays, and its seal."""

    body: dict[str, Any]
    """The parsed header: schema, grid, fit parameters, provenance, array table."""
    arrays: dict[str, np.ndarray]
    """Read-only arrays by name (see ``REQUIRED_ARRAYS``)."""
    sha256: str
    """Hex content hash (covers header and arrays)."""
    signed: bool
    """True when the map carried an Ed25519 signature that verified."""
    public_key: str | None
    """Hex Ed25519 public key of the signer, if signed."""

    @property
    def n_cv(self) -> int:
        """Number of control volumes."""
        return int(self.body["n_cv"])

    @property
    def map_version(self) -> int:
        """Monotonic map version (newer maps replace older ones)."""
        return int(self.body["map_version"])

    @property
    def cell_size_m(self) -> float:
        """CV edge length l [m]."""
        return float(self.body["grid"]["cell_size_m"])

    @property
    def origin_m(self) -> np.ndarray:
        """Grid origin (3,) in the map frame [m]."""
        return np.asarray(self.body["grid"]["origin_m"], dtype=float)

    @property
    def grid_shape(self) -> tuple[int, int, int]:
        """Grid shape (nx, ny, nz)."""
        return tuple(int(s) for s in self.body["grid"]["shape"])  # type: ignore[return-value]

    @property
    def schema_version(self) -> int:
        """Map schema version (1 or 2)."""
        return int(self.body["schema_version"])

    @property
    def scale(self) -> float:
        """Speed scale S of the commands."""
        return float(self.body["scale"])

    @property
    def n_max(self) -> int:
        """Largest candidate agent count N of the fit."""
        return int(self.body["n_range"][1])

    def __getitem__(self, name: str) -> np.ndarray:
        return self.arrays[name]


def canonical_json(obj: Any) -> bytes:
    """The one JSON serialisation used inside maps (sorted keys, no spaces, UTF-8)."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def _read_block(data: memoryview, pos: int, what: str) -> tuple[memoryview, int]:
    if pos + 8 > len(data):
        raise MapError(f"truncated: file ends inside the {what} length field")
    (n,) = _U64.unpack_from(data, pos)
    pos += 8
    if pos + n > len(data):
        raise MapError(f"truncated: {what} declares {n} bytes, only {len(data) - pos} present")
    return data[pos:pos + n], pos + n


def _verify_signature(digest: bytes, seal: dict, trusted_keys: list[bytes] | None) -> bool:
    sig_hex, key_hex = seal.get("signature"), seal.get("public_key")
    if sig_hex is None:
        if trusted_keys:
            raise MapError("signature: map is unsigned but a trusted key was given")
        return False
    from nacl.exceptions import BadSignatureError
    from nacl.signing import VerifyKey

    try:
        signature = bytes.fromhex(sig_hex)
        key = bytes.fromhex(key_hex) if key_hex else b""
    except (TypeError, ValueError) as exc:
        raise MapError(f"signature: malformed signature or key in seal ({exc})") from exc
    if trusted_keys is not None and key not in trusted_keys:
        raise MapError("signature: signed by a key that is not trusted")
    try:
        VerifyKey(key).verify(digest, signature)
    except (BadSignatureError, ValueError) as exc:
        raise MapError("signature: Ed25519 signature does not verify") from exc
    return True


def _check_array_entry(name: str, entry: Any, payload_len: int) -> tuple[np.dtype, tuple, int, int]:
    try:
        dtype = np.dtype(entry["dtype"])
        shape = tuple(int(s) for s in entry["shape"])
        offset, nbytes = int(entry["offset"]), int(entry["nbytes"])
    except (KeyError, TypeError, ValueError) as exc:
        raise MapError(f"schema: array {name!r} has a malformed table entry ({exc})") from exc
    if dtype.hasobject or any(s < 0 for s in shape):
        raise MapError(f"schema: array {name!r} has an invalid dtype or shape")
    if nbytes != int(np.prod(shape, dtype=np.int64)) * dtype.itemsize:
        raise MapError(f"schema: array {name!r} size does not match dtype {dtype.str} and shape {shape}")
    if offset < 0 or offset + nbytes > payload_len:
        raise MapError(f"schema: array {name!r} lies outside the payload")
    return dtype, shape, offset, nbytes


def _check_schema(body: dict, arrays: dict[str, np.ndarray]) -> None:
    if body.get("schema") != SCHEMA:
        raise MapError(f"schema: not a FISC command map (schema={body.get('schema')!r})")
    version = body.get("schema_version")
    if version not in SUPPORTED_SCHEMA_VERSIONS:
        raise MapError(
            f"schema_version: map has {version!r}, this reader supports {', '.join(map(str, SUPPORTED_SCHEMA_VERSIONS))}"
        )
    missing = [k for k in REQUIRED_BODY_KEYS if k not in body]
    if missing:
        raise MapError(f"schema: header lacks {', '.join(missing)}")
    n_cv = body["n_cv"]
    for name, (dtype, rank) in REQUIRED_ARRAYS.items():
        if name not in arrays:
            raise MapError(f"schema: array {name!r} is missing")
        arr = arrays[name]
        if arr.dtype.str != dtype or arr.ndim != rank:
            raise MapError(f"schema: array {name!r} must be {dtype} of rank {rank}, is {arr.dtype.str} {arr.shape}")
        if name != "grid_cv" and arr.shape[0] != n_cv:
            raise MapError(f"schema: array {name!r} has {arr.shape[0]} rows, header says n_cv={n_cv}")
    if tuple(arrays["grid_cv"].shape) != tuple(body["grid"]["shape"]):
        raise MapError("schema: grid_cv shape differs from grid.shape")
    if version >= 2:
        _check_schema_2(body, arrays)


def _check_schema_2(body: dict, arrays: dict[str, np.ndarray]) -> None:
    """Schema 2: face arrays of the right shapes with finite values, and a ``flight`` table."""
    nx, ny, nz = (int(v) for v in body["grid"]["shape"])
    want = {"face_u_x_m_s": (nx + 1, ny, nz), "face_u_y_m_s": (nx, ny + 1, nz), "face_u_z_m_s": (nx, ny, nz + 1),
            "cv_design_density": (int(body["n_cv"]),)}
    for name, shape in want.items():
        if name not in arrays:
            raise MapError(f"schema: version-2 array {name!r} is missing")
        arr = arrays[name]
        if arr.dtype.str != "<f8" or tuple(arr.shape) != shape:
            raise MapError(f"schema: array {name!r} must be <f8 {shape}, is {arr.dtype.str} {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise MapError(f"schema: array {name!r} has non-finite values")
    flight = body.get("flight")
    if not isinstance(flight, dict) or any(k not in flight for k in FLIGHT_KEYS):
        raise MapError(f"schema: version-2 header needs a 'flight' table with {', '.join(FLIGHT_KEYS)}")
    if not isinstance(flight["mode"], str):
        raise MapError("schema: flight.mode must be a string")
    for k in ("lookahead_s", "persistence_s"):
        v = flight[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (v >= 0) or v != v or v == float("inf"):
            raise MapError(f"schema: flight.{k} must be a finite number >= 0, is {v!r}")


def decode_map(
    data: bytes | bytearray | memoryview,
    trusted_keys: list[bytes] | None = None,
    source: str = "<bytes>",
) -> CommandMap:
    """Verify and decode a map from its bytes.

    ``trusted_keys``: raw 32-byte Ed25519 public keys; when given, the map must be signed by
    one of them.  Raises ``MapError`` naming the failed check (prefixed with ``source``).
    """
    try:
        return _decode(memoryview(data), trusted_keys)
    except MapError as exc:
        raise MapError(f"{source}: {exc}") from None


def _decode(data: memoryview, trusted_keys: list[bytes] | None) -> CommandMap:
    if len(data) < 12 or bytes(data[:8]) != MAGIC:
        raise MapError("magic: not a FISC map file (bad magic bytes)" if len(data) >= 12 else "truncated: file too short")
    (container,) = _U32.unpack_from(data, 8)
    if container != CONTAINER_VERSION:
        raise MapError(f"container: version {container} is not supported (expected {CONTAINER_VERSION})")
    body_raw, pos = _read_block(data, 12, "header")
    payload, pos = _read_block(data, pos, "payload")
    sealed_end = pos
    seal_raw, pos = _read_block(data, pos, "seal")
    if pos != len(data):
        raise MapError(f"trailing: {len(data) - pos} unexpected bytes after the seal")
    try:
        seal = json.loads(bytes(seal_raw))
    except ValueError as exc:
        raise MapError(f"seal: not valid JSON ({exc})") from exc
    if not isinstance(seal, dict) or set(seal) != SEAL_KEYS:
        raise MapError(f"seal: expected exactly the keys {sorted(SEAL_KEYS)}")
    digest = hashlib.sha256(data[:sealed_end]).digest()
    if seal["sha256"] != digest.hex():
        raise MapError("sha256: content hash does not match (map corrupted or modified)")
    signed = _verify_signature(digest, seal, trusted_keys)
    try:
        body = json.loads(bytes(body_raw))
    except ValueError as exc:
        raise MapError(f"header: not valid JSON ({exc})") from exc
    if not isinstance(body, dict) or not isinstance(body.get("arrays"), dict):
        raise MapError("schema: header has no array table")
    arrays = {}
    for name, entry in body["arrays"].items():
        dtype, shape, offset, nbytes = _check_array_entry(name, entry, len(payload))
        arr = np.frombuffer(payload, dtype=dtype, count=nbytes // dtype.itemsize if dtype.itemsize else 0, offset=offset)
        arrays[name] = arr.reshape(shape)
    _check_schema(body, arrays)
    return CommandMap(body=body, arrays=arrays, sha256=digest.hex(), signed=signed,
                      public_key=seal.get("public_key") if signed else None)


#: Largest map file ``load_map`` reads (a 10^6-CV map is about 0.4 GB).
MAX_MAP_FILE_BYTES = 1 << 30
#: Largest key file (64 hex digits and a newline; whitespace tolerated).
MAX_KEY_FILE_BYTES = 4096


def read_hex_key(path: str | Path, what: str) -> bytes:
    """Read a 32-byte Ed25519 key stored as hex text (``keygen``'s ``.pub`` and ``.key`` files)."""
    from fisc_agent.safe_files import read_regular_file

    raw = read_regular_file(path, what=f"Ed25519 {what} file", max_bytes=MAX_KEY_FILE_BYTES, error=MapError)
    try:
        key = bytes.fromhex(raw.decode("ascii").strip())
    except ValueError as exc:
        raise MapError(f"{path}: not a hex Ed25519 {what}") from exc
    if len(key) != 32:
        raise MapError(f"{path}: an Ed25519 {what} has 32 bytes, this has {len(key)}")
    return key


def read_public_key(path: str | Path) -> bytes:
    """Read a ``NAME.pub`` file (hex Ed25519 public key, as written by ``fisc-ground keygen``)."""
    return read_hex_key(path, "public key")


def load_map(path: str | Path, trusted_key: str | Path | bytes | None = None) -> CommandMap:
    """Load and verify a map file.  ``trusted_key``: a ``.pub`` path or raw key bytes."""
    from fisc_agent.safe_files import read_regular_file

    path = Path(path)
    data = read_regular_file(path, what="FISC map", max_bytes=MAX_MAP_FILE_BYTES, magic=MAGIC, error=MapError)
    keys = None
    if trusted_key is not None:
        keys = [trusted_key if isinstance(trusted_key, bytes) else read_public_key(trusted_key)]
    return decode_map(data, keys, source=str(path))
