"""Importer for Ansys-Fluent-style ASCII node exports (``nodenumber, x-coordinate, ...``).

Also home of the small, fast numeric-CSV reader shared with the axisymmetric importer:
a vectorised fast path (``np.fromstring`` over the whole body) and, only when that fails,
a slow per-line pass that names the offending line, column and text.
"""

from __future__ import annotations

import hashlib
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fisc_ground.reference.field import P_REF_PA, ReferenceError, ReferenceField

log = logging.getLogger(__name__)

#: Median pressure above which ``pressure_kind='auto'`` treats a column as absolute [Pa].
AUTO_ABSOLUTE_THRESHOLD_PA = 5.0e4

PRESSURE_KINDS = ("gauge", "absolute", "auto")


@dataclass(frozen=True)
class NumericTable:
    """A parsed all-numeric CSV table."""

    path: str
    """The file it came from (for messages)."""
    columns: tuple[str, ...]
    """Header cells as written (stripped)."""
    keys: tuple[str, ...]
    """Normalised header cells (see :func:`normalise_column_name`)."""
    data: np.ndarray
    """(n_rows, n_columns) float64 values."""
    line_numbers: np.ndarray
    """(n_rows,) int64 1-based file line number of each data row."""
    header_line: int
    """1-based line number of the header."""
    sha256: str
    """sha256 (hex) of the file's bytes."""

    def column_label(self, j: int) -> str:
        """Human-readable name of column ``j`` (1-based index plus header text)."""
        return f"column {j + 1} ({self.columns[j]!r})"


def normalise_column_name(name: str) -> str:
    """Lower-case, strip quotes/units-free whitespace, map ``_``/space runs to ``-``."""
    s = name.strip().strip("\"'").strip().lower()
    s = re.sub(r"\s*\[.*?\]\s*$", "", s)  # trailing unit like "[Pa]"
    s = re.sub(r"[\s_]+", "-", s)
    return s


def read_numeric_table(path: str | Path) -> NumericTable:
    """Read a header + all-numeric CSV (comma or whitespace separated) into a float64 table.

    Blank lines are skipped. Raises :class:`ReferenceError` naming the file, line and column of
    the first problem: missing file, empty file, header only, wrong cell count, non-numeric cell.
    (Non-finite values are parsed; callers check them per required column.)
    """
    from fisc_ground.reference.files import read_text_export

    p = Path(path)
    if not p.is_file():
        raise ReferenceError(f"{p}: file not found")
    raw = read_text_export(p)
    sha = hashlib.sha256(raw).hexdigest()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ReferenceError(f"{p}: not a UTF-8 text file ({exc})") from exc
    lines = text.split("\n")
    nonblank = [i for i, line in enumerate(lines) if line.strip()]
    if not nonblank:
        raise ReferenceError(f"{p}: empty file (no header, no data)")
    h = nonblank[0]
    header_text = lines[h].strip()
    delim = "," if "," in header_text else None
    columns = tuple(c.strip() for c in (header_text.split(delim) if delim else header_text.split()))
    if delim and columns and columns[-1] == "":
        columns = columns[:-1]  # tolerate a trailing delimiter on the header
    keys = tuple(normalise_column_name(c) for c in columns)
    for j, c in enumerate(columns):
        if c == "":
            raise ReferenceError(f"{p}: line {h + 1}: header column {j + 1} is empty")
    rows = nonblank[1:]
    if not rows:
        raise ReferenceError(f"{p}: header only, no data rows (header at line {h + 1})")
    ncol = len(columns)
    line_numbers = np.asarray(rows, dtype=np.int64) + 1
    body = "\n".join(lines[h + 1:])  # blank lines are whitespace to the parser
    aligned = True
    if delim:
        n_delim = body.count(delim)
        aligned = n_delim in (len(rows) * (ncol - 1), len(rows) * ncol)  # optional trailing comma
        body = body.replace(delim, " ")
    values: np.ndarray | None
    try:
        values = np.fromstring(body, sep=" ")
    except ValueError:
        values = None
    if values is None or not aligned or values.size != len(rows) * ncol:
        data = _parse_rows_slowly(p, lines, rows, columns, delim)
    else:
        data = values.reshape(len(rows), ncol)
    return NumericTable(str(p), columns, keys, data, line_numbers, h + 1, sha)


def _parse_rows_slowly(p: Path, lines: list[str], rows: list[int], columns: tuple[str, ...],
                       delim: str | None) -> np.ndarray:
    """Slow path, taken only when the fast parse fails: report the first malformed row (cell
    count or non-numeric cell); if every row is well formed (e.g. trailing delimiters on only
    some rows), return the parsed (n_rows, n_columns) table."""
    ncol = len(columns)
    out = np.empty((len(rows), ncol))
    for n, i in enumerate(rows):
        cells = [c.strip() for c in (lines[i].split(delim) if delim else lines[i].split())]
        if delim and len(cells) == ncol + 1 and cells[-1] == "":
            cells = cells[:-1]
        if len(cells) != ncol:
            raise ReferenceError(
                f"{p}: line {i + 1}: {len(cells)} cells but the header has {ncol} columns")
        for j, c in enumerate(cells):
            try:
                out[n, j] = float(c)
            except ValueError:
                what = "empty cell" if c == "" else f"non-numeric value {c!r}"
                raise ReferenceError(
                    f"{p}: line {i + 1}, column {j + 1} ({columns[j]!r}): {what}") from None
    return out


# --- Fluent column vocabulary --------------------------------------------------------------

_COORD = {
    "x": ("x-coordinate", "x", "x-coord", "coordinate-x", "x-position", "points:0", "points-0"),
    "y": ("y-coordinate", "y", "y-coord", "coordinate-y", "y-position", "points:1", "points-1"),
    "z": ("z-coordinate", "z", "z-coord", "coordinate-z", "z-position", "points:2", "points-2"),
}
_VEL = {
    "u": ("x-velocity", "velocity-x", "u", "ux", "u-x", "u:0", "u-0", "velocity:0", "x-vel"),
    "v": ("y-velocity", "velocity-y", "v", "uy", "u-y", "u:1", "u-1", "velocity:1", "y-vel"),
    "w": ("z-velocity", "velocity-z", "w", "uz", "u-z", "u:2", "u-2", "velocity:2", "z-vel"),
}
_P_GAUGE = ("pressure", "static-pressure", "p", "gauge-pressure", "static-gauge-pressure")
_P_ABS = ("absolute-pressure", "abs-pressure", "p-abs", "static-absolute-pressure")
_RHO = ("density", "rho")


def find_column(table: NumericTable, aliases: tuple[str, ...]) -> int | None:
    """Index of the first column whose normalised name is in ``aliases`` (alias order wins)."""
    for a in aliases:
        if a in table.keys:
            return table.keys.index(a)
    return None


def check_finite(table: NumericTable, cols: dict[str, int]) -> None:
    """Raise naming the first non-finite (NaN/inf) cell among the given columns."""
    idx = list(cols.values())
    bad = ~np.isfinite(table.data[:, idx])
    if bad.any():
        r, c = np.argwhere(bad)[0]
        j = idx[c]
        raise ReferenceError(
            f"{table.path}: line {table.line_numbers[r]}, {table.column_label(j)}: "
            f"non-finite value {table.data[r, j]!r}")


def check_duplicates(table: NumericTable, points: np.ndarray) -> None:
    """Raise naming the lines of the first duplicate pair of points (exact equality)."""
    _, first, inverse = np.unique(points, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    owner = first[inverse]
    dup = np.nonzero(owner != np.arange(points.shape[0]))[0]
    if dup.size:
        b = int(dup.min())
        a = int(owner[b])
        raise ReferenceError(
            f"{table.path}: duplicate point {tuple(float(v) for v in points[b])} at lines "
            f"{table.line_numbers[a]} and {table.line_numbers[b]}")


def to_gauge(pressure_pa: np.ndarray, kind: str, where: str) -> tuple[np.ndarray, str]:
    """Convert a pressure column to gauge per ``kind`` ('gauge'|'absolute'|'auto').

    Returns (gauge pressure [Pa], resolved kind). 'auto' treats the column as absolute when its
    median exceeds ``AUTO_ABSOLUTE_THRESHOLD_PA``.
    """
    if kind not in PRESSURE_KINDS:
        raise ReferenceError(
            f"{where}: pressure_kind must be one of {PRESSURE_KINDS}, got {kind!r}")
    if kind == "auto":
        kind = "absolute" if float(np.median(pressure_pa)) > AUTO_ABSOLUTE_THRESHOLD_PA else "gauge"
    if kind == "absolute":
        return pressure_pa - P_REF_PA, "absolute"
    return pressure_pa, "gauge"


def read_fluent_csv(path: str | Path, pressure_kind: str = "gauge",
                    name: str | None = None) -> ReferenceField:
    """Read an Ansys-Fluent-style ASCII node export into a :class:`ReferenceField`.

    Columns are matched case-insensitively in any order (``x-coordinate``, ``x-velocity``,
    ``pressure``/``static-pressure`` (gauge), ``absolute-pressure`` (absolute, converted with
    ``P_REF_PA``), optional ``density`` and ``nodenumber``); other columns are ignored.
    ``pressure_kind`` ('gauge' default, 'absolute', 'auto': absolute if the median exceeds
    5e4 Pa) applies to a plain ``pressure`` column; an ``absolute-pressure`` column is always
    absolute. Raises :class:`ReferenceError` naming file, line and column on bad input.
    """
    table = read_numeric_table(path)
    src = table.path
    cols: dict[str, int] = {}
    missing = []
    for label, aliases in (("x-coordinate", _COORD["x"]), ("y-coordinate", _COORD["y"]),
                           ("z-coordinate", _COORD["z"]), ("x-velocity", _VEL["u"]),
                           ("y-velocity", _VEL["v"]), ("z-velocity", _VEL["w"])):
        j = find_column(table, aliases)
        if j is None:
            missing.append(label)
        else:
            cols[label] = j
    jp = find_column(table, _P_GAUGE)
    kind = pressure_kind
    if jp is None:
        jp = find_column(table, _P_ABS)
        if jp is not None:
            kind = "absolute"
    if jp is None:
        missing.append("pressure (or static-pressure / absolute-pressure)")
    else:
        cols["pressure"] = jp
    if missing:
        hint = ""
        if "z-coordinate" in missing and "x-coordinate" not in missing and (
                "y-coordinate" not in missing or find_column(table, ("r", "radius")) is not None):
            hint = (" The file looks 2-D (no z column): for an axisymmetric x,r solution use "
                    "read_axisym_csv (fisc_ground.reference.axisym).")
        raise ReferenceError(
            f"{src}: line {table.header_line}: missing required column(s): "
            f"{', '.join(missing)}; header is {list(table.columns)}.{hint}")
    jr = find_column(table, _RHO)
    if jr is not None:
        cols["density"] = jr
    check_finite(table, cols)
    d = table.data
    points = np.ascontiguousarray(d[:, [cols["x-coordinate"], cols["y-coordinate"],
                                        cols["z-coordinate"]]])
    zspan = float(points[:, 2].max() - points[:, 2].min())
    scale = float(np.abs(points).max()) or 1.0
    if table.data.shape[0] > 1 and zspan <= 1e-9 * scale:
        raise ReferenceError(
            f"{src}: {table.column_label(cols['z-coordinate'])}: every z is {points[0, 2]!r}: "
            "the file looks 2-D, not a 3-D node export. For an axisymmetric x,r solution use "
            "read_axisym_csv (fisc_ground.reference.axisym).")
    check_duplicates(table, points)
    velocity = np.ascontiguousarray(d[:, [cols["x-velocity"], cols["y-velocity"],
                                          cols["z-velocity"]]])
    gauge, kind = to_gauge(d[:, cols["pressure"]].copy(), kind, src)
    density = d[:, jr].copy() if jr is not None else None
    log.debug("read %d nodes from %s (pressure %s)", points.shape[0], src, kind)
    return ReferenceField(
        points_m=points, velocity_m_s=velocity, pressure_gauge_pa=gauge, density_kg_m3=density,
        name=name or Path(src).stem, source=src, source_sha256=table.sha256, pressure_kind=kind,
        extras={"format": "fluent-csv", "columns": list(table.columns)})
