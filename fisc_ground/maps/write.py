"""Atomic writing of FISC command maps, and the ground's Ed25519 keys (key generation, signing
keys).  The map format itself, encoder and decoder, is ``fisc_agent.map.codec``."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from fisc_agent.map.codec import decode_map, encode_map, read_hex_key


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
