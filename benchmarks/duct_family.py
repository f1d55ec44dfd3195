"""More analytic ducts: a check that the method is not tuned to the tunnel (issue 9: "it will also be
checked on ducts you have not seen").  The first three (converging, steep, long) were made when the
staggered default was chosen; the long duct has since guided two automatic choices (the density
amplitude's and the continuity weight's velocity guards).  The last four (mild, diffuser, short_throat,
double_throat) were made afterwards and have set nothing: fresh ducts.

Each is a body of revolution through the analytic oracle (``fisc_ground.reference.analytic``,
quasi-1-D isentropic flow with the streamline-slope radial velocity).  Sweep specs::

    fisc-sim sweep benchmarks/duct_family.toml -o out/duct_family --workers 2        # paper vs default
    fisc-sim sweep benchmarks/duct_family_beta.toml -o out/duct_beta --workers 2     # continuity weight
    fisc-sim sweep benchmarks/duct_fresh.toml -o out/duct_fresh --workers 2          # the fresh four

docs/studies/fidelity.md ("Ducts not seen when the defaults were chosen") has the measured table.
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


def mild_radius_m(x_m):
    """A mild duct with kinks: R piecewise linear through 1.2, 1.1, 0.9, 1.2, 1.4 m at x = 0, 3, 6, 9, 12 m."""
    return np.interp(np.asarray(x_m, dtype=float), [0.0, 3.0, 6.0, 9.0, 12.0], [1.2, 1.1, 0.9, 1.2, 1.4])


def diffuser_radius_m(x_m):
    """A diffuser only: R = 0.9 + 0.6 min(x / 10, 1)^1.5, 0.9 m at the inlet to 1.5 m from x = 10 m."""
    return 0.9 + 0.6 * np.clip(np.asarray(x_m, dtype=float) / 10.0, 0.0, 1.0) ** 1.5


def short_throat_radius_m(x_m):
    """A short Gaussian throat: R = 1.3 - 0.55 exp(-((x - 4) / 1.5)^2), 0.75 m at x = 4 m."""
    return 1.3 - 0.55 * np.exp(-((np.asarray(x_m, dtype=float) - 4.0) / 1.5) ** 2)


def double_throat_radius_m(x_m):
    """Two throats: R = 1 + 0.35 (1 + cos(2 pi x / 8)), 1.7 m at x = 0, 8, 16 m and 1.0 m at x = 4, 12 m."""
    return 1.0 + 0.35 * (1.0 + np.cos(2.0 * np.pi * np.asarray(x_m, dtype=float) / 8.0))


def mild():
    """The mild duct's reference field (12 m, inlet 3 m/s)."""
    return analytic_nozzle(mild_radius_m, length_m=12.0, inlet_velocity_m_s=3.0, name="mild")


def diffuser():
    """The diffuser's reference field (12 m, inlet 4 m/s)."""
    return analytic_nozzle(diffuser_radius_m, length_m=12.0, inlet_velocity_m_s=4.0, name="diffuser")


def short_throat():
    """The short throat's reference field (9 m, inlet 2.5 m/s)."""
    return analytic_nozzle(short_throat_radius_m, length_m=9.0, inlet_velocity_m_s=2.5, name="short_throat")


def double_throat():
    """The double throat's reference field (16 m, inlet 3 m/s)."""
    return analytic_nozzle(double_throat_radius_m, length_m=16.0, inlet_velocity_m_s=3.0, name="double_throat")
