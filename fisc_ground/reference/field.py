"""The in-memory reference flow field every importer produces and every later stage consumes."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Reference (ambient) static pressure used to turn absolute pressure into gauge pressure [Pa].
P_REF_PA = 101325.0


class ReferenceError(ValueError):
    """A reference flow field could not be read or is invalid.

    The message always names the source (file or built-in name) and, where known, the
    line and column of the problem.
    """


@dataclass(frozen=True)
class ReferenceField:
    """A steady 3-D flow solution sampled at nodes, in the reference (CFD) frame, SI units."""

    points_m: np.ndarray
    """(n, 3) float64 node positions [m]; the tunnel axis is +x."""
    velocity_m_s: np.ndarray
    """(n, 3) float64 flow velocity at the nodes [m/s]."""
    pressure_gauge_pa: np.ndarray
    """(n,) float64 static pressure relative to ``P_REF_PA`` [Pa] (absolute inputs are converted)."""
    density_kg_m3: np.ndarray | None
    """(n,) float64 fluid density [kg/m^3], or None when the source has none."""
    name: str
    """Short name of the field (built-in name or file stem)."""
    source: str
    """Where it came from: a file path or ``builtin:<name>``."""
    source_sha256: str
    """sha256 (hex) of the source file's bytes (or of the built-in data)."""
    pressure_kind: str = "gauge"
    """How the source stated pressure: ``gauge`` or ``absolute`` (converted to gauge here)."""
    extras: dict = field(default_factory=dict)
    """Free-form provenance (solver, case, notes) recorded in the map."""

    def __post_init__(self) -> None:
        n = self.points_m.shape[0]
        if self.points_m.shape != (n, 3) or self.velocity_m_s.shape != (n, 3):
            raise ReferenceError(f"{self.source}: points and velocity must be (n, 3) arrays")
        if self.pressure_gauge_pa.shape != (n,):
            raise ReferenceError(f"{self.source}: pressure must be an (n,) array")
        if self.density_kg_m3 is not None and self.density_kg_m3.shape != (n,):
            raise ReferenceError(f"{self.source}: density must be an (n,) array")

    @property
    def n_nodes(self) -> int:
        """Number of reference nodes."""
        return int(self.points_m.shape[0])
