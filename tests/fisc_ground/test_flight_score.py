"""``score_track``: what counts as a pass, a hold during it and a crossing (pure, synthetic tracks)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from fisc_ground.fields.flight_score import score_track
from fisc_ground.reference.builtin import load_builtin


@pytest.fixture(scope="module")
def ref():
    return load_builtin("cd_nozzle_inviscid")


def track(states: list[str], x: list[float]):
    n = len(states)
    t = np.arange(n, dtype=float)
    pos = np.column_stack([np.asarray(x, float), np.zeros(n), np.zeros(n)])
    vel = np.column_stack([np.full(n, 1.0), np.zeros(n), np.zeros(n)])
    return t, pos, vel, np.asarray(states)


def test_a_hold_before_the_entry_is_not_part_of_the_pass(ref):
    t, pos, vel, st = track(["TAKEOFF", "HOLD", "TAKEOFF", "JOIN", "FLOW", "FLOW", "FLOW", "EXIT"],
                            [-3, -3, -3, -1, 1, 8, 14, 16])
    s = score_track(t, pos, vel, st, ref, 0.5)
    assert s.crossed and not s.held and s.crossing_time_s == pytest.approx(3.0)


def test_a_hold_in_the_flow_before_the_crossing_is_held(ref):
    t, pos, vel, st = track(["JOIN", "FLOW", "HOLD", "FLOW", "FLOW", "EXIT"], [-1, 1, 2, 3, 14, 16])
    s = score_track(t, pos, vel, st, ref, 0.5)
    assert s.held and not s.crossed


def test_a_hold_after_the_crossing_is_the_exit_hold(ref):
    t, pos, vel, st = track(["JOIN", "FLOW", "FLOW", "EXIT", "HOLD"], [-1, 1, 14, 16, 17])
    s = score_track(t, pos, vel, st, ref, 0.5)
    assert s.crossed and not s.held


def test_no_entry_no_crossing(ref):
    t, pos, vel, st = track(["TAKEOFF", "HOLD", "JOIN"], [-3, -3, -1])
    s = score_track(t, pos, vel, st, ref, 0.5)
    assert not s.crossed and not s.held and s.n_samples == 0


@pytest.mark.parametrize("offsets, rms", [
    (None, None),                                       # not given: nan
    ([np.nan] * 3, None),                               # no scored row carries one: nan
    ([0.0, 0.0, 0.0], 0.0),                             # exact on the scored rows (JOIN, EXIT rows off by 4)
    ([0.0, np.nan, 0.5], np.sqrt(0.5 ** 2 / 2)),        # only the rows that carry one count
])
def test_the_gnss_velocity_is_scored_on_the_same_samples(ref, offsets, rms):
    t, pos, vel, st = track(["JOIN", "FLOW", "FLOW", "FLOW", "EXIT", "EXIT"], [-1, 1, 2, 3, 16, 17])
    _, j = cKDTree(ref.points_m).query(pos[1:4])
    target = 0.5 * ref.velocity_m_s[j, 0]
    vel[1:4, 0] = target                                # the estimate flies the target exactly
    g = None
    if offsets is not None:
        g = np.full(6, 4.0)                             # far off where not scored
        g[1:4] = target + np.asarray(offsets)
    s = score_track(t, pos, vel, st, ref, 0.5, gnss_vx_m_s=g)
    assert s.velocity_nrmse == pytest.approx(0.0, abs=1e-12) and s.n_samples == 3
    if rms is None:
        assert np.isnan(s.velocity_nrmse_gnss) and s.as_dict()["velocity_nrmse_gnss"] is None
    else:
        assert s.velocity_nrmse_gnss == pytest.approx(rms / np.max(np.abs(target)), abs=1e-12)
