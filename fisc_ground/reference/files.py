"""Checks on CFD export files before any importer parses them (``fisc-ground fit FILE``).

Built on ``fisc_agent.common.safe_files``: a regular file, at most ``MAX_REFERENCE_BYTES``, without
holes (a sparse file is no genuine export), and a plausible start: a text export has no NUL
byte and a header line within its first ``HEAD_BYTES``; a ``.vtu`` starts with XML, a legacy
``.vtk`` with ``# vtk DataFile``.  So a 2 GB sparse or zero-filled file is refused in
milliseconds with the reason, instead of being read and parsed whole.
"""

from __future__ import annotations

from pathlib import Path

from fisc_agent.common.safe_files import GIB, check_regular_file, read_head, read_regular_file
from fisc_ground.reference.field import ReferenceError

#: Largest CFD export read (the importers hold it in memory several times over).
MAX_REFERENCE_BYTES = 1 * GIB
#: Bytes sniffed for the header line / format signature.
HEAD_BYTES = 64 * 1024


def _head(path: Path, what: str) -> bytes:
    check_regular_file(path, what=what, max_bytes=MAX_REFERENCE_BYTES, reject_sparse=True, error=ReferenceError)
    return read_head(path, HEAD_BYTES, what=what, error=ReferenceError)


def check_text_head(path: str | Path) -> bytes:
    """The first ``HEAD_BYTES`` of a CSV export after the checks above (``ReferenceError`` says which failed)."""
    path = Path(path)
    head = _head(path, "CSV export")
    nul = head.find(b"\0")
    if nul >= 0:
        raise ReferenceError(f"{path}: not a text CSV export (NUL byte at offset {nul})")
    if len(head) == HEAD_BYTES and b"\n" not in head:
        raise ReferenceError(f"{path}: no line break in the first {HEAD_BYTES} bytes; not a CSV export")
    return head


def read_text_export(path: str | Path) -> bytes:
    """The whole CSV export after ``check_text_head`` (and no NUL byte anywhere)."""
    path = Path(path)
    check_text_head(path)
    raw = read_regular_file(path, what="CSV export", max_bytes=MAX_REFERENCE_BYTES, error=ReferenceError)
    nul = raw.find(b"\0")
    if nul >= 0:
        raise ReferenceError(f"{path}: not a text CSV export (NUL byte at offset {nul})")
    return raw


def check_vtk_head(path: str | Path) -> None:
    """Refuse a ``.vtu``/``.vtk`` that is not a regular, non-sparse file with the format's signature."""
    path = Path(path)
    head = _head(path, "VTK export")
    text = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    if path.suffix.lower() == ".vtu":
        if not text.startswith(b"<"):
            raise ReferenceError(f"{path}: cannot read as VTK: not a VTU file (an XML VTKFile must start with '<', "
                                 f"this starts with {head[:16]!r})")
    elif not text.startswith(b"# vtk DataFile"):
        raise ReferenceError(f"{path}: cannot read as VTK: not a legacy VTK file (must start with '# vtk DataFile', "
                             f"this starts with {head[:16]!r})")
