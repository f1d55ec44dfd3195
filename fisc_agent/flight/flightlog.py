"""The agent's own flight log: one CSV row per control tick (``fisc-agent --flight-log FILE``).

What the agent saw and did, in the map frame: mission state, position and velocity as the
autopilot reported them, the setpoint it sent, its CV and its tracking parcel.  It is what the
real-autopilot tests score (excursion outside the map, velocity fidelity, hold altitude) and
what a person plots after a flight; the autopilot's own log (ULog, DataFlash) holds the truth
about the estimator.  Rows are flushed once a second, so a killed agent loses at most that.  A log
that already exists is never truncated: it is rotated to ``<file>.1`` (``.1`` to ``.2`` and so on,
``KEEP_ROTATED`` kept), so a restarted agent keeps the flight it was restarted in.
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path
from typing import IO

from fisc_agent.flight.tick import AgentSnapshot

COLUMNS = ("time_s", "wall_time_s", "state", "reason", "x_m", "y_m", "z_m", "vx_m_s", "vy_m_s", "vz_m_s",
           "sp_x_m_s", "sp_y_m_s", "sp_z_m_s", "cv", "parcel_x_m", "parcel_y_m", "parcel_z_m", "mode", "armed",
           "nearest_neighbour_m", "net_ids", "gnss_vx_m_s", "gnss_vy_m_s")
"""Column names, in order (map frame: x along the tunnel axis, z up).  ``vx_m_s`` ... are the autopilot's
velocity estimate; ``gnss_vx_m_s``, ``gnss_vy_m_s`` the GNSS receiver's own horizontal velocity (empty: none
fresh).  ``nearest_neighbour_m``: the safety net's nearest neighbour (empty: none heard); ``net_ids``: the
neighbours it acted on, ``;``-joined."""

KEEP_ROTATED = 9
"""Older logs kept beside a new one (``<file>.1`` newest ... ``<file>.9`` oldest)."""


def rotate(path: Path, keep: int = KEEP_ROTATED) -> Path | None:
    """Move an existing ``path`` to ``path.1`` (shifting older ones up, the oldest beyond ``keep``
    dropped); returns where it went, None when there was nothing to keep."""
    if not path.exists() or path.stat().st_size == 0:
        return None
    for i in range(keep - 1, 0, -1):
        older = path.with_name(f"{path.name}.{i}")
        if older.exists():
            os.replace(older, path.with_name(f"{path.name}.{i + 1}"))
    kept = path.with_name(f"{path.name}.1")
    os.replace(path, kept)
    return kept


def _cells(v: tuple[float, ...] | None, n: int = 3) -> list[str]:
    """The ``n`` components of ``v`` as cells (empty cells for None)."""
    return [""] * n if v is None else [f"{c:.4f}" for c in v]


class FlightLog:
    """CSV writer of ``AgentSnapshot`` rows, one per tick (a previous log at the path is rotated, never truncated)."""

    def __init__(self, path: str | Path, flush_period_s: float = 1.0) -> None:
        self.path = Path(path)
        self.rotated_to = rotate(self.path)
        """Where an existing log at ``path`` was moved (None: there was none)."""
        self._fh: IO[str] = open(self.path, "x", newline="", encoding="utf-8")
        self._w = csv.writer(self._fh)
        self._w.writerow(COLUMNS)
        self._flush_period_s = flush_period_s
        self._last_flush_s = -math.inf

    def write(self, s: AgentSnapshot) -> None:
        """One row for one tick."""
        self._w.writerow([f"{s.time_s:.4f}", f"{s.wall_time_s:.4f}", s.state, s.reason, *_cells(s.position_map_m),
                          *_cells(s.velocity_map_m_s), *_cells(s.setpoint_map_m_s), s.cv_id, *_cells(s.parcel_map_m),
                          s.mode, int(s.armed),
                          f"{s.nearest_neighbour_m:.3f}" if math.isfinite(s.nearest_neighbour_m) else "",
                          ";".join(map(str, s.net_ids)), *_cells(s.gnss_velocity_map_m_s, 2)])
        if s.time_s - self._last_flush_s >= self._flush_period_s:
            self._fh.flush()
            self._last_flush_s = s.time_s

    def close(self) -> None:
        """Flush and close the file."""
        self._fh.close()


def read_flight_log(path: str | Path) -> list[dict[str, str]]:
    """The rows of a flight log as dicts keyed by ``COLUMNS`` (values as written)."""
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))
