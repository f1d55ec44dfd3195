"""How agents read the staggered face field inside a cell (``CommandField`` mode ``staggered``), and
the cube-mean axial velocity the fit scores its static field with (``cube_mean_u_axial_m_s``).

Checked on the analytic nozzle's schema-2 map against the face arrays themselves.
"""

from __future__ import annotations

import numpy as np
import pytest

from fisc_agent.map.lookup import CommandField, cube_mean_u_axial_m_s
from fisc_ground.maps.build import FitConfig, build_map_from_reference

#: Gauss-Legendre nodes and weights on [0, 1]: exact for the polynomial shapes integrated here.
_GL_X, _GL_W = np.polynomial.legendre.leggauss(4)
GL_X, GL_W = 0.5 * (_GL_X + 1.0), 0.5 * _GL_W


@pytest.fixture(scope="module")
def field() -> CommandField:
    return CommandField.from_map(build_map_from_reference("analytic", FitConfig()), scale=1.0)


def _cells(field: CommandField) -> np.ndarray:
    """(m, 3) grid indices of the CV cells."""
    return np.argwhere(np.asarray(field.grid_cv) >= 0)


def _at(field: CommandField, cells: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """Command at the points ``frac`` (m, 3) in [0, 1) of ``cells`` (m, 3)."""
    pts = field.origin_m + (cells + frac) * field.cell_size_m
    return field.command(pts, np.zeros(len(pts), dtype=np.int64), "staggered")


def test_each_component_is_linear_between_its_two_faces(field):
    cells = _cells(field)
    fx, fy, fz = field.face_u_m_s
    i, j, k = cells.T
    lo = np.stack([fx[i, j, k], fy[i, j, k], fz[i, j, k]], 1)
    hi = np.stack([fx[i + 1, j, k], fy[i, j + 1, k], fz[i, j, k + 1]], 1)
    frac = np.random.default_rng(0).uniform(0.0, 0.999, size=(len(cells), 3))
    np.testing.assert_allclose(_at(field, cells, frac), (1.0 - frac) * lo + frac * hi, rtol=0, atol=1e-12)


def test_cube_mean_axial_velocity_is_the_flown_rule_averaged_over_the_cube(field):
    """``cube_mean_u_axial_m_s`` (the fit's static-field figure) against the field agents fly, integrated
    over each cube by Gauss-Legendre in all three directions."""
    cells = _cells(field)
    ids = np.asarray(field.grid_cv)[tuple(cells.T)]
    mean = np.zeros(len(cells))
    for xi, wx in zip(GL_X, GL_W):
        for eta, wy in zip(GL_X, GL_W):
            for zeta, wz in zip(GL_X, GL_W):
                frac = np.tile([xi, eta, zeta], (len(cells), 1))
                mean += wx * wy * wz * _at(field, cells, frac)[:, 0]
    expected = np.empty(field.n_cv)
    expected[ids] = mean
    np.testing.assert_allclose(cube_mean_u_axial_m_s(field.grid_cv, field.face_u_m_s[0]), expected,
                               rtol=1e-10, atol=1e-12)
    assert np.ptp(expected) > 0.1 * np.max(expected)  # a converging-diverging field, not a constant
