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
signature signs the 32 raw digest bytes.  This module is the format's one home: the encoder
(``encode_map``) beside the decoder (``decode_map``), numpy, the standard library and PyNaCl
only.  Writing files atomically and key generation live in ``fisc_ground.maps.write``.
"""

from __future__ import annotations

import hashlib
import json
import struct
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np

from fisc_agent.map.separation import map_separation
from fisc_agent.map.wall import WALL_ARRAY, DuctWall

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
#: x faces (nx+1, ny, nz), y faces (nx, ny+1, nz), z faces (nx, ny, nz+1) (``fisc_ground.fit.staggered``).
FACE_ARRAYS = ("face_u_x_m_s", "face_u_y_m_s", "face_u_z_m_s")
#: Keys of a schema-2 body's ``flight`` table (recommended flight settings).
FLIGHT_KEYS = ("mode", "lookahead_s", "persistence_s")
REQUIRED_BODY_KEYS = (
    "schema", "schema_version", "map_version", "n_cv", "grid", "n_range", "scale", "kappa",
    "agent_mass_kg", "arrays",
)
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")


class MapErrorKind(str, Enum):
    """The check a map failed.  The values are the names the telemetry's refusal code carries
    (``telemetry_codec.REJECT_REASONS``) where it has one; the others report as ``other``."""

    TRUNCATED = "truncated"
    MAGIC = "magic"
    CONTAINER = "container"
    SHA256 = "sha256"
    SIGNATURE = "signature"
    SCHEMA = "schema"
    SCHEMA_VERSION = "schema_version"
    HEADER = "header"
    SEAL = "seal"
    TRAILING = "trailing"
    VERSION_MISMATCH = "version_mismatch"
    CHUNKS = "chunks"
    OLD_VERSION = "old_version"
    OTHER = "other"
    # the agent's own checks of a decoded map (``control.check_map``)
    MODE = "mode"
    N_CV = "n_cv"
    GRID = "grid"
    GRID_CV = "grid_cv"
    COMMANDS = "commands"
    N_STAR = "n_star"
    # files
    KEY = "key"
    FILE = "file"


class MapError(ValueError):
    """A map (or key) failed a check: ``kind`` names the check, ``detail`` says what was wrong,
    ``source`` where the map came from (file, key expression; None: unknown).  The message is
    ``"<source>: <kind>: <detail>"``."""

    def __init__(self, kind: MapErrorKind, detail: str, source: str | None = None) -> None:
        self.kind, self.detail, self.source = kind, detail, source
        text = f"{kind.value}: {detail}"
        super().__init__(text if source is None else f"{source}: {text}")

    def at(self, source: str) -> MapError:
        """The same error, located at ``source`` (an outer source comes first)."""
        return MapError(self.kind, self.detail, source if self.source is None else f"{source}: {self.source}")


class MapFileError(MapError):
    """A map or key file that cannot be read at all (missing, not a regular file, too large, wrong
    magic); raised by ``safe_files`` with its complete message."""

    def __init__(self, message: str) -> None:
        ValueError.__init__(self, message)
        self.kind, self.detail, self.source = MapErrorKind.FILE, message, None


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
        raise MapError(MapErrorKind.TRUNCATED, f"file ends inside the {what} length field")
    (n,) = _U64.unpack_from(data, pos)
    pos += 8
    if pos + n > len(data):
        raise MapError(MapErrorKind.TRUNCATED, f"{what} declares {n} bytes, only {len(data) - pos} present")
    return data[pos:pos + n], pos + n


def _verify_signature(digest: bytes, seal: dict, trusted_keys: list[bytes] | None) -> bool:
    sig_hex, key_hex = seal.get("signature"), seal.get("public_key")
    if sig_hex is None:
        if trusted_keys:
            raise MapError(MapErrorKind.SIGNATURE, "map is unsigned but a trusted key was given")
        return False
    from nacl.exceptions import BadSignatureError
    from nacl.signing import VerifyKey

    try:
        signature = bytes.fromhex(sig_hex)
        key = bytes.fromhex(key_hex) if key_hex else b""
    except (TypeError, ValueError) as exc:
        raise MapError(MapErrorKind.SIGNATURE, f"malformed signature or key in seal ({exc})") from exc
    if trusted_keys is not None and key not in trusted_keys:
        raise MapError(MapErrorKind.SIGNATURE, "signed by a key that is not trusted")
    try:
        VerifyKey(key).verify(digest, signature)
    except (BadSignatureError, ValueError) as exc:
        raise MapError(MapErrorKind.SIGNATURE, "Ed25519 signature does not verify") from exc
    return True


def _check_array_entry(name: str, entry: Any, payload_len: int) -> tuple[np.dtype, tuple, int, int]:
    try:
        dtype = np.dtype(entry["dtype"])
        shape = tuple(int(s) for s in entry["shape"])
        offset, nbytes = int(entry["offset"]), int(entry["nbytes"])
    except (KeyError, TypeError, ValueError) as exc:
        raise MapError(MapErrorKind.SCHEMA, f"array {name!r} has a malformed table entry ({exc})") from exc
    if dtype.hasobject or dtype.itemsize == 0 or any(s < 0 for s in shape):
        raise MapError(MapErrorKind.SCHEMA, f"array {name!r} has an invalid dtype or shape")
    if nbytes != int(np.prod(shape, dtype=np.int64)) * dtype.itemsize:
        raise MapError(MapErrorKind.SCHEMA, f"array {name!r} size does not match dtype {dtype.str} and shape {shape}")
    if offset < 0 or offset + nbytes > payload_len:
        raise MapError(MapErrorKind.SCHEMA, f"array {name!r} lies outside the payload")
    return dtype, shape, offset, nbytes


def _check_schema(body: dict, arrays: dict[str, np.ndarray]) -> None:
    if body.get("schema") != SCHEMA:
        raise MapError(MapErrorKind.SCHEMA, f"not a FISC command map (schema={body.get('schema')!r})")
    version = body.get("schema_version")
    if version not in SUPPORTED_SCHEMA_VERSIONS:
        raise MapError(MapErrorKind.SCHEMA_VERSION,
                       f"map has {version!r}, this reader supports {', '.join(map(str, SUPPORTED_SCHEMA_VERSIONS))}"
        )
    missing = [k for k in REQUIRED_BODY_KEYS if k not in body]
    if missing:
        raise MapError(MapErrorKind.SCHEMA, f"header lacks {', '.join(missing)}")
    n_cv = body["n_cv"]
    for name, (dtype, rank) in REQUIRED_ARRAYS.items():
        if name not in arrays:
            raise MapError(MapErrorKind.SCHEMA, f"array {name!r} is missing")
        arr = arrays[name]
        if arr.dtype.str != dtype or arr.ndim != rank:
            raise MapError(MapErrorKind.SCHEMA,
                           f"array {name!r} must be {dtype} of rank {rank}, is {arr.dtype.str} {arr.shape}")
        if name != "grid_cv" and arr.shape[0] != n_cv:
            raise MapError(MapErrorKind.SCHEMA, f"array {name!r} has {arr.shape[0]} rows, header says n_cv={n_cv}")
    if tuple(arrays["grid_cv"].shape) != tuple(body["grid"]["shape"]):
        raise MapError(MapErrorKind.SCHEMA, "grid_cv shape differs from grid.shape")
    if WALL_ARRAY in arrays:  # optional in every version: the duct's real wall (fisc_agent.map.wall)
        wall = arrays[WALL_ARRAY]
        try:
            if wall.dtype.str != "<f8":
                raise ValueError(f"must be <f8, is {wall.dtype.str}")
            DuctWall.from_array(wall)
        except ValueError as exc:
            raise MapError(MapErrorKind.SCHEMA, f"array {WALL_ARRAY!r}: {exc}") from exc
    _check_design_keys(body)
    if version >= 2:
        _check_schema_2(body, arrays)


def _check_design_keys(body: dict) -> None:
    """Optional in every version (issue 37): the ``separation`` table (``fisc_agent.map.separation``)
    and the ``length_scale`` (a finite number > 0); maps without them read as the defaults."""
    if "separation" in body:
        try:
            map_separation(body)
        except (ValueError, TypeError) as exc:
            raise MapError(MapErrorKind.SCHEMA, f"header {exc}") from exc
    if "length_scale" in body:
        v = body["length_scale"]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0 < v < float("inf")):
            raise MapError(MapErrorKind.SCHEMA, f"header length_scale must be a finite number > 0, is {v!r}")


def _check_schema_2(body: dict, arrays: dict[str, np.ndarray]) -> None:
    """Schema 2: face arrays of the right shapes with finite values, and a ``flight`` table."""
    nx, ny, nz = (int(v) for v in body["grid"]["shape"])
    want = {"face_u_x_m_s": (nx + 1, ny, nz), "face_u_y_m_s": (nx, ny + 1, nz), "face_u_z_m_s": (nx, ny, nz + 1),
            "cv_design_density": (int(body["n_cv"]),)}
    for name, shape in want.items():
        if name not in arrays:
            raise MapError(MapErrorKind.SCHEMA, f"version-2 array {name!r} is missing")
        arr = arrays[name]
        if arr.dtype.str != "<f8" or tuple(arr.shape) != shape:
            raise MapError(MapErrorKind.SCHEMA, f"array {name!r} must be <f8 {shape}, is {arr.dtype.str} {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise MapError(MapErrorKind.SCHEMA, f"array {name!r} has non-finite values")
    flight = body.get("flight")
    if not isinstance(flight, dict) or any(k not in flight for k in FLIGHT_KEYS):
        raise MapError(MapErrorKind.SCHEMA, f"version-2 header needs a 'flight' table with {', '.join(FLIGHT_KEYS)}")
    if not isinstance(flight["mode"], str):
        raise MapError(MapErrorKind.SCHEMA, "flight.mode must be a string")
    for k in ("lookahead_s", "persistence_s"):
        v = flight[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (v >= 0) or v != v or v == float("inf"):
            raise MapError(MapErrorKind.SCHEMA, f"flight.{k} must be a finite number >= 0, is {v!r}")


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
        raise exc.at(source) from None


def _decode(data: memoryview, trusted_keys: list[bytes] | None) -> CommandMap:
    if len(data) < 12 or bytes(data[:8]) != MAGIC:
        if len(data) < 12:
            raise MapError(MapErrorKind.TRUNCATED, "file too short")
        raise MapError(MapErrorKind.MAGIC, "not a FISC map file (bad magic bytes)")
    (container,) = _U32.unpack_from(data, 8)
    if container != CONTAINER_VERSION:
        raise MapError(MapErrorKind.CONTAINER, f"version {container} is not supported (expected {CONTAINER_VERSION})")
    body_raw, pos = _read_block(data, 12, "header")
    payload, pos = _read_block(data, pos, "payload")
    sealed_end = pos
    seal_raw, pos = _read_block(data, pos, "seal")
    if pos != len(data):
        raise MapError(MapErrorKind.TRAILING, f"{len(data) - pos} unexpected bytes after the seal")
    try:
        seal = json.loads(bytes(seal_raw))
    except ValueError as exc:
        raise MapError(MapErrorKind.SEAL, f"not valid JSON ({exc})") from exc
    if not isinstance(seal, dict) or set(seal) != SEAL_KEYS:
        raise MapError(MapErrorKind.SEAL, f"expected exactly the keys {sorted(SEAL_KEYS)}")
    digest = hashlib.sha256(data[:sealed_end]).digest()
    if seal["sha256"] != digest.hex():
        raise MapError(MapErrorKind.SHA256, "content hash does not match (map corrupted or modified)")
    signed = _verify_signature(digest, seal, trusted_keys)
    try:
        body = json.loads(bytes(body_raw))
    except ValueError as exc:
        raise MapError(MapErrorKind.HEADER, f"not valid JSON ({exc})") from exc
    if not isinstance(body, dict) or not isinstance(body.get("arrays"), dict):
        raise MapError(MapErrorKind.SCHEMA, "header has no array table")
    arrays = {}
    for name, entry in body["arrays"].items():
        dtype, shape, offset, nbytes = _check_array_entry(name, entry, len(payload))
        arr = np.frombuffer(payload, dtype=dtype, count=nbytes // dtype.itemsize, offset=offset)  # itemsize > 0: checked
        arrays[name] = arr.reshape(shape)
    _check_schema(body, arrays)
    return CommandMap(body=body, arrays=arrays, sha256=digest.hex(), signed=signed,
                      public_key=seal.get("public_key") if signed else None)


def encode_map(meta: dict[str, Any], arrays: dict[str, np.ndarray], signing_key: bytes | None = None) -> bytes:
    """Serialise ``meta`` (header fields without ``arrays``) and ``arrays`` into map bytes.

    The schema version is ``meta["schema_version"]`` if given, else 2 when the face field is among
    the arrays and 1 (the paper's map) otherwise.

    The inverse of ``decode_map``.  Arrays are stored little-endian with the dtypes of
    ``REQUIRED_ARRAYS`` (extra arrays keep their own dtype).  ``signing_key``: a 32-byte Ed25519
    seed; the seal then carries a signature.
    """
    table: dict[str, dict[str, Any]] = {}
    chunks: list[bytes] = []
    offset = 0
    for name in sorted(arrays):
        want = REQUIRED_ARRAYS.get(name, (np.asarray(arrays[name]).dtype.newbyteorder("<").str, None))[0]
        arr = np.ascontiguousarray(arrays[name], dtype=np.dtype(want))
        pad = (-offset) % ALIGN
        chunks.append(b"\0" * pad)
        offset += pad
        table[name] = {"dtype": arr.dtype.str, "shape": list(arr.shape), "offset": offset, "nbytes": arr.nbytes}
        chunks.append(arr.tobytes())
        offset += arr.nbytes
    version = meta.get("schema_version", SCHEMA_VERSION if all(k in arrays for k in FACE_ARRAYS) else 1)
    body = dict(meta, schema=SCHEMA, schema_version=int(version), arrays=table)
    body_raw = canonical_json(body)
    payload = b"".join(chunks)
    sealed = b"".join([MAGIC, _U32.pack(CONTAINER_VERSION), _U64.pack(len(body_raw)), body_raw,
                       _U64.pack(len(payload)), payload])
    digest = hashlib.sha256(sealed).digest()
    seal: dict[str, Any] = {"sha256": digest.hex(), "signature": None, "public_key": None}
    if signing_key is not None:
        from nacl.signing import SigningKey

        key = SigningKey(signing_key)
        seal["signature"] = key.sign(digest).signature.hex()
        seal["public_key"] = key.verify_key.encode().hex()
    seal_raw = canonical_json(seal)
    return sealed + _U64.pack(len(seal_raw)) + seal_raw


#: Largest map file ``load_map`` reads (a 10^6-CV map is about 0.4 GB).
MAX_MAP_FILE_BYTES = 1 << 30
#: Largest key file (64 hex digits and a newline; whitespace tolerated).
MAX_KEY_FILE_BYTES = 4096


def read_hex_key(path: str | Path, what: str) -> bytes:
    """Read a 32-byte Ed25519 key stored as hex text (``keygen``'s ``.pub`` and ``.key`` files)."""
    from fisc_agent.common.safe_files import read_regular_file

    raw = read_regular_file(path, what=f"Ed25519 {what} file", max_bytes=MAX_KEY_FILE_BYTES, error=MapFileError)
    try:
        key = bytes.fromhex(raw.decode("ascii").strip())
    except ValueError as exc:
        raise MapError(MapErrorKind.KEY, f"not a hex Ed25519 {what}", source=str(path)) from exc
    if len(key) != 32:
        raise MapError(MapErrorKind.KEY, f"an Ed25519 {what} has 32 bytes, this has {len(key)}", source=str(path))
    return key


def read_public_key(path: str | Path) -> bytes:
    """Read a ``NAME.pub`` file (hex Ed25519 public key, as written by ``fisc-ground keygen``)."""
    return read_hex_key(path, "public key")


def load_map(path: str | Path, trusted_key: str | Path | bytes | None = None) -> CommandMap:
    """Load and verify a map file.  ``trusted_key``: a ``.pub`` path or raw key bytes."""
    from fisc_agent.common.safe_files import read_regular_file

    path = Path(path)
    data = read_regular_file(path, what="FISC map", max_bytes=MAX_MAP_FILE_BYTES, magic=MAGIC, error=MapFileError)
    keys = None
    if trusted_key is not None:
        keys = [trusted_key if isinstance(trusted_key, bytes) else read_public_key(trusted_key)]
    return decode_map(data, keys, source=str(path))
