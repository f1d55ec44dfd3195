"""Writing, signing and key generation for FISC command maps (format: ``fisc_agent.mapfile``)."""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from fisc_agent.mapfile import (
    ALIGN,
    CONTAINER_VERSION,
    FACE_ARRAYS,
    MAGIC,
    REQUIRED_ARRAYS,
    SCHEMA,
    SCHEMA_VERSION,
    _U32,
    _U64,
    canonical_json,
    decode_map,
    read_hex_key,
)


def encode_map(meta: dict[str, Any], arrays: dict[str, np.ndarray], signing_key: bytes | None = None) -> bytes:
    """Serialise ``meta`` (header fields without ``arrays``) and ``arrays`` into map bytes.

    The schema version is ``meta["schema_version"]`` if given, else 2 when the face field is among
    the arrays and 1 (the paper's map) otherwise.

    Arrays are stored little-endian with the dtypes of ``REQUIRED_ARRAYS`` (extra arrays keep
    their own dtype).  ``signing_key``: a 32-byte Ed25519 seed; the seal then carries a signature.
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


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file in the same folder and ``os.replace``.

    A crash or error leaves either the old file or none, never a half-written one.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent or ".")
    try:
        with os.fdopen(fd, "wb") as fh:
            os.fchmod(fh.fileno(), 0o644)  # mkstemp creates 0600; a map is not secret
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_map(path: str | Path, meta: dict[str, Any], arrays: dict[str, np.ndarray],
              signing_key: bytes | None = None) -> str:
    """Encode, self-verify and atomically write a map; returns its sha256 (hex)."""
    data = encode_map(meta, arrays, signing_key)
    verified = decode_map(data, source=str(path))  # refuse to write anything the reader would refuse
    atomic_write_bytes(path, data)
    return verified.sha256


def generate_keypair(stem: str | Path) -> tuple[Path, Path]:
    """Write ``STEM.key`` (hex Ed25519 seed, mode 0600) and ``STEM.pub`` (hex public key)."""
    from nacl.signing import SigningKey

    stem = Path(stem)
    key = SigningKey.generate()
    key_path, pub_path = stem.with_name(stem.name + ".key"), stem.with_name(stem.name + ".pub")
    for p in (key_path, pub_path):
        if p.exists():
            raise FileExistsError(f"{p} exists; refusing to overwrite a key")
    fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(key.encode().hex() + "\n")
    pub_path.write_text(key.verify_key.encode().hex() + "\n")
    return key_path, pub_path


def read_signing_key(path: str | Path) -> bytes:
    """Read a ``NAME.key`` file written by ``generate_keypair`` (hex Ed25519 seed)."""
    return read_hex_key(path, "private key seed")
