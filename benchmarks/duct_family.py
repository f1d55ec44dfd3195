"""Three more analytic ducts, none used in choosing any default: a check that the method is not
tuned to the tunnel (issue 9: "it will also be checked on ducts you have not seen").

Each is a body of revolution through the analytic oracle (``fisc_ground.reference.analytic``,
quasi-1-D isentropic flow with the streamline-slope radial velocity).  Sweep specs::

    fisc-sim sweep benchmarks/duct_family.toml -o out/duct_family --workers 2        # paper vs default
    fisc-sim sweep benchmarks/duct_family_beta.toml -o out/duct_beta --workers 2     # continuity weight

docs/simulation.md ("Ducts not seen when the defaults were chosen") has the measured table.
"""

from __future__ import annotations

import numpy as np

from fisc_ground.reference.analytic import analytic_nozzle


def converging_radius_m(x_m):
    """A converging nozzle only: R = 0.9 + 0.3 (1 + cos(pi x / 10)), 1.5 m at the inlet to 0.9 m at x = 10 m."""
    x = np.minimum(np.asarray(x_m, dtype=float), 10.0)
    return 0.9 + 0.3 * (1.0 + np.cos(np.pi * x / 10.0))


def steep_radius_m(x_m):
    """A short steep throat: R = 0.6 + 0.35 (1 + cos(pi (x - 5) / 5)), 1.3 m -> 0.6 m at x = 5 m -> 1.3 m at 10 m."""
    x = np.asarray(x_m, dtype=float)
    return 0.6 + 0.35 * (1.0 + np.cos(np.pi * (x - 5.0) / 5.0))


def long_radius_m(x_m):
    """A long gentle asymmetric duct: 1.6 m -> 1.0 m at x = 12 m (cosine) -> 1.4 m at x = 18 m."""
    x = np.asarray(x_m, dtype=float)
    return np.where(x <= 12.0, 1.0 + 0.3 * (1.0 + np.cos(np.pi * x / 12.0)),
                    1.0 + 0.2 * (1.0 - np.cos(np.pi * (np.minimum(x, 18.0) - 12.0) / 6.0)))


def converging():
    """The converging nozzle's reference field (10 m, inlet 3 m/s)."""
    return analytic_nozzle(converging_radius_m, length_m=10.0, inlet_velocity_m_s=3.0, name="converging")


def steep():
    """The steep throat's reference field (10 m, inlet 2.5 m/s)."""
    return analytic_nozzle(steep_radius_m, length_m=10.0, inlet_velocity_m_s=2.5, name="steep")


def long_duct():
    """The long duct's reference field (18 m, inlet 3 m/s)."""
    return analytic_nozzle(long_radius_m, length_m=18.0, inlet_velocity_m_s=3.0, name="long")
