"""One entry point for every reference source: built-in names and files by extension."""

from __future__ import annotations

from pathlib import Path

from fisc_ground.reference.builtin import builtin_names, load_builtin
from fisc_ground.reference.field import ReferenceError, ReferenceField
from fisc_ground.reference.fluent_csv import normalise_column_name

_CSV = (".csv", ".txt", ".dat")
_VTK = (".vtu", ".vtk")


def _sniff_csv_header(path: Path) -> tuple[str, ...]:
    """Normalised header cells of a CSV (first non-blank line)."""
    from fisc_ground.reference.files import check_text_head

    text = check_text_head(path).decode("utf-8-sig", errors="replace")
    for line in text.split("\n"):
        if line.strip():
            cells = line.split(",") if "," in line else line.split()
            return tuple(normalise_column_name(c) for c in cells if c.strip())
    raise ReferenceError(f"{path}: empty file (no header, no data)")


def load_reference(spec: str | Path, pressure_kind: str = "auto") -> ReferenceField:
    """Load a reference field from a built-in name or a file path.

    * a built-in name (:func:`fisc_ground.reference.builtin.builtin_names`), also as
      ``builtin:<name>``;
    * ``.csv``/``.txt``/``.dat``: the header decides - ``x, r, ...`` (axisymmetric, no z column)
      goes to :func:`read_axisym_csv`, anything else to :func:`read_fluent_csv`;
    * ``.vtu``/``.vtk``: :func:`read_vtk` (axisymmetric wedges are revolved).

    ``pressure_kind`` ('auto' | 'gauge' | 'absolute') is passed to the file importers; built-ins
    are stored as gauge. Missing files and unknown names raise :class:`ReferenceError`.
    """
    s = str(spec)
    name = s[len("builtin:"):] if s.startswith("builtin:") else s
    if name in builtin_names():
        return load_builtin(name)
    if s.startswith("builtin:"):
        return load_builtin(name)  # raises, listing the known names
    path = Path(s)
    suffix = path.suffix.lower()
    if path.exists() and not path.is_file():  # /dev/zero, a FIFO, a directory: say what it is
        from fisc_agent.common.safe_files import check_regular_file
        from fisc_ground.reference.files import MAX_REFERENCE_BYTES

        check_regular_file(path, what="CFD export", max_bytes=MAX_REFERENCE_BYTES, error=ReferenceError)
    if not path.is_file():
        hint = ("" if suffix in _CSV + _VTK else
                f"; not a built-in either (known: {', '.join(builtin_names())})")
        raise ReferenceError(f"{path}: file not found{hint}")
    if suffix in _VTK:
        from fisc_ground.reference.vtk import read_vtk

        return read_vtk(path, pressure_kind=pressure_kind)
    if suffix in _CSV:
        from fisc_ground.reference.axisym import looks_axisymmetric, read_axisym_csv
        from fisc_ground.reference.fluent_csv import read_fluent_csv

        if looks_axisymmetric(_sniff_csv_header(path)):
            return read_axisym_csv(path, pressure_kind=pressure_kind)
        return read_fluent_csv(path, pressure_kind=pressure_kind)
    raise ReferenceError(f"{path}: unsupported file type {suffix!r}; expected one of "
                         f"{', '.join(_CSV + _VTK)} or a built-in name "
                         f"({', '.join(builtin_names())})")
