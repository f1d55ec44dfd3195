"""The shipped ready-made map equals a fresh fit of the embedded default."""

import numpy as np

from fisc_agent.mapfile import REQUIRED_ARRAYS
from fisc_ground.mapbuild import build_default_map, load_shipped_default_map


def test_shipped_default_map_matches_a_fresh_fit():
    shipped, fresh = load_shipped_default_map(), build_default_map()
    assert shipped.n_cv == fresh.n_cv == 741
    for key in ("grid", "n_range", "scale", "kappa", "agent_mass_kg"):
        assert shipped.body[key] == fresh.body[key], key
    for name in REQUIRED_ARRAYS:
        np.testing.assert_allclose(shipped[name], fresh[name], rtol=0, atol=1e-12, err_msg=name)
