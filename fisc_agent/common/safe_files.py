"""Bounded reads of the files named on command lines (maps, keys, recordings, CFD exports).

Every file argument of ``fisc-agent`` and ``fisc-ground`` goes through ``read_regular_file`` (or
``check_regular_file`` for readers that open the file themselves).  Before any byte is read as
data it checks, in this order, on one open file descriptor:

1. the path names a **regular file** (not ``/dev/zero``, a FIFO, a socket or a directory);
   FIFOs are opened non-blocking so that the check itself cannot hang;
2. its size is at most ``max_bytes`` (the caller's cap for that kind of file);
3. its first bytes are the expected ``magic`` (a map is refused after reading 8 bytes, not 2 GB);
4. optionally, that it has **no holes** (``SEEK_HOLE``): a sparse file is never a genuine export,
   and reading gigabytes of zeros only to refuse them takes minutes.

Then it reads at most ``max_bytes`` + 1 bytes, so a file that grows while being read is refused
too.  Each refusal raises the caller's error class (``MapError``, ``RecordingError``, ...) with a
message naming the file and the check.  Standard library only (onboard code).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

KIB = 1 << 10
MIB = 1 << 20
GIB = 1 << 30

_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISSOCK, "a socket"),
)


class FileInputError(ValueError):
    """A file argument was refused (not a regular file, too large, wrong header, sparse)."""


def _human(n: int) -> str:
    for unit, size in (("GiB", GIB), ("MiB", MIB), ("KiB", KIB)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n} bytes"


def _check_kind(mode: int, path: Path, what: str, error: type[Exception]) -> None:
    if not stat.S_ISREG(mode):
        kind = next((name for test, name in _KINDS if test(mode)), "not a regular file")
        raise error(f"{path}: file type: {what} must be a regular file, this is {kind}")


def _open_checked(path: Path, what: str, max_bytes: int, error: type[Exception]) -> tuple[int, int]:
    """Open ``path`` read-only and check it is a regular file within ``max_bytes``: (fd, size)."""
    try:
        _check_kind(os.stat(path).st_mode, path, what, error)  # before open: a FIFO or socket is never opened
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise error(f"{path}: {what} not found") from None
    except OSError as exc:
        raise error(f"{path}: cannot read {what} ({exc.strerror})") from None
    try:
        st = os.fstat(fd)  # again on the open file: the path may have been swapped meanwhile
        _check_kind(st.st_mode, path, what, error)
        if st.st_size > max_bytes:
            raise error(f"{path}: size: {what} is {_human(st.st_size)}, larger than the {_human(max_bytes)} limit")
    except BaseException:
        os.close(fd)
        raise
    return fd, int(st.st_size)


def _check_sparse(fd: int, size: int, path: Path, what: str, error: type[Exception]) -> None:
    seek_hole = getattr(os, "SEEK_HOLE", None)
    if seek_hole is None or size == 0:
        return
    try:
        hole = os.lseek(fd, 0, seek_hole)
    except OSError:  # the file system cannot tell: nothing to check
        return
    finally:
        os.lseek(fd, 0, os.SEEK_SET)
    if hole < size:
        raise error(f"{path}: sparse: {what} is a sparse file (a hole at byte {hole} of {size}); "
                    "a genuine export has no holes")


def _read_upto(fd: int, n: int) -> bytes:
    parts: list[bytes] = []
    left = n
    while left > 0:
        chunk = os.read(fd, min(left, 16 * MIB))
        if not chunk:
            break
        parts.append(chunk)
        left -= len(chunk)
    return b"".join(parts)


def check_regular_file(path: str | Path, *, what: str, max_bytes: int, magic: bytes | tuple[bytes, ...] = (),
                       reject_sparse: bool = False, error: type[Exception] = FileInputError) -> int:
    """Run the checks without reading the body (for readers that open the file themselves);
    returns the size in bytes.  ``magic``: accepted prefixes (any one of them)."""
    fd, size = _open_and_check(Path(path), what, max_bytes, magic, reject_sparse, error)
    os.close(fd)
    return size


def _open_and_check(path: Path, what: str, max_bytes: int, magic: bytes | tuple[bytes, ...], reject_sparse: bool,
                    error: type[Exception]) -> tuple[int, int]:
    """``_open_checked`` plus the magic and sparseness checks; (fd positioned at 0, size)."""
    fd, size = _open_checked(path, what, max_bytes, error)
    try:
        _check_magic(fd, path, what, magic, error)
        if reject_sparse:
            _check_sparse(fd, size, path, what, error)
    except OSError as exc:
        os.close(fd)
        raise error(f"{path}: cannot read {what} ({exc.strerror})") from None
    except BaseException:
        os.close(fd)
        raise
    return fd, size


def _check_magic(fd: int, path: Path, what: str, magic: bytes | tuple[bytes, ...], error: type[Exception]) -> None:
    prefixes = (magic,) if isinstance(magic, bytes) else tuple(magic)
    if not prefixes:
        return
    head = _read_upto(fd, max(len(m) for m in prefixes))
    os.lseek(fd, 0, os.SEEK_SET)
    if not any(head.startswith(m) for m in prefixes):
        expected = " or ".join(repr(m) for m in prefixes)
        raise error(f"{path}: magic: not a {what} (starts with {head[:16]!r}, expected {expected})")


def read_regular_file(path: str | Path, *, what: str, max_bytes: int, magic: bytes | tuple[bytes, ...] = (),
                      reject_sparse: bool = False, error: type[Exception] = FileInputError) -> bytes:
    """The whole file, after the checks of the module docstring; ``error`` is the exception
    class raised for every refusal (its message names the file and the failed check)."""
    path = Path(path)
    fd, _ = _open_and_check(path, what, max_bytes, magic, reject_sparse, error)
    try:
        data = _read_upto(fd, max_bytes + 1)
    except OSError as exc:
        raise error(f"{path}: cannot read {what} ({exc.strerror})") from None
    finally:
        os.close(fd)
    if len(data) > max_bytes:
        raise error(f"{path}: size: {what} grew past the {_human(max_bytes)} limit while being read")
    return data


def read_head(path: str | Path, n: int, *, what: str, error: type[Exception] = FileInputError) -> bytes:
    """The first ``n`` bytes of a regular file (any size), e.g. to sniff a format."""
    path = Path(path)
    fd, _ = _open_checked(path, what, 1 << 62, error)
    try:
        return _read_upto(fd, n)
    finally:
        os.close(fd)
