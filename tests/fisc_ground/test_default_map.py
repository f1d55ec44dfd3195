"""The shipped ready-made map equals a fresh fit of the embedded default."""

import numpy as np
import pytest

from fisc_agent.map.codec import REQUIRED_ARRAYS
from fisc_ground.maps.build import build_default_map, load_shipped_default_map


def test_shipped_default_map_matches_a_fresh_fit():
    shipped, fresh = load_shipped_default_map(), build_default_map()
    assert shipped.n_cv == fresh.n_cv == 560  # the designed staircase's CVs of the 741 covered cubes
    for key in ("grid", "n_range", "scale", "kappa", "agent_mass_kg"):
        assert shipped.body[key] == fresh.body[key], key
    for name in REQUIRED_ARRAYS:
        np.testing.assert_allclose(shipped[name], fresh[name], rtol=0, atol=1e-12, err_msg=name)
    # schema 2: the staggered field, the designed density and the recommended flight settings
    assert shipped.schema_version == fresh.schema_version == 2
    assert shipped.body["flight"] == fresh.body["flight"]
    for key in ("continuity_weight", "weight_exponent", "axial_weight", "density_amplitude", "staircase_contrast",
                "staircase_min_step_open"):
        assert shipped.body["staggered"][key] == fresh.body["staggered"][key], key
    for name in ("face_u_x_m_s", "face_u_y_m_s", "face_u_z_m_s", "cv_design_density"):
        np.testing.assert_allclose(shipped[name], fresh[name], rtol=0, atol=1e-9, err_msg=name)
    # issue 37: the separation it is designed for and its budget, at length scale 1
    assert shipped.body["length_scale"] == fresh.body["length_scale"] == 1.0
    assert shipped.body["separation"].keys() == fresh.body["separation"].keys()
    for key, value in fresh.body["separation"].items():
        assert shipped.body["separation"][key] == (value if isinstance(value, (str, int)) else
                                                   pytest.approx(value, rel=1e-9)), key


def test_default_map_carries_the_open_volume_fraction():
    """Optional array cv_open_fraction (A_j dx_j / l^3 of eq. swarm_density): 1 for the near-axis
    CVs, the node share of a full 0.1 m lattice cube (125 nodes; 150 in the folded outlet slice)
    for the wall CVs."""
    cmap = load_shipped_default_map()
    frac = np.asarray(cmap["cv_open_fraction"])
    np.testing.assert_allclose(frac, build_default_map()["cv_open_fraction"], rtol=0, atol=1e-12)
    count = np.asarray(cmap["node_count"])
    full = np.where(np.asarray(cmap["cv_index"])[:, 0] == cmap.grid_shape[0] - 1, 150, 125)
    np.testing.assert_allclose(frac, count / full)
    assert frac.min() > 0 and frac.max() == 1.0 and np.count_nonzero(frac == 1.0) > 200


def test_fit_default_is_the_map_the_simulator_default_run_flies():
    """``fisc-ground fit`` (FitConfig defaults) and ``fisc-sim run`` share the speed limit, so the
    shipped map, a default fit and the map the default run fits itself are the same map."""
    from sim.run import RunConfig, load_command_map

    cfg = RunConfig()
    run_map, shipped = load_command_map(cfg.map, cfg.max_speed_m_s, cfg.preset), load_shipped_default_map()
    assert run_map.scale == shipped.scale and run_map.body["max_speed_m_s"] == shipped.body["max_speed_m_s"] == 2.0
    assert run_map.body["flight"] == shipped.body["flight"]
    for name in ("fit_velocity_m_s", "face_u_x_m_s", "face_u_y_m_s", "face_u_z_m_s", "cv_design_density"):
        np.testing.assert_allclose(run_map[name], shipped[name], rtol=0, atol=1e-9, err_msg=name)
