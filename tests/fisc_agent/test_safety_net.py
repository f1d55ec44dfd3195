"""The separation safety net (fisc_agent.flight.safety_net) at its boundaries, its vectorised form
against the single-vehicle oracle, and the neighbour table from raw telemetry bytes on a simulated
clock."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fisc_agent.flight.safety_net import (DuctAxis, NeighbourReports, SafetyNetConfig, closest_approach_m,
                                          effective_horizon_s, keep_apart, keep_apart_pairs, predicted_and_radius,
                                          sequential_cuts)
from fisc_agent.zenoh import telemetry_codec as tc
from fisc_agent.zenoh.neighbours import NeighbourTable

D = 0.92
CFG = SafetyNetConfig()
DUCT = DuctAxis(0.0, 10.0)
EPS = 1e-9


def one(pos, vel=(0.0, 0.0, 0.0), age=0.0, agent_id=7) -> NeighbourReports:
    return NeighbourReports(np.array([agent_id]), np.array([pos], dtype=float), np.array([vel], dtype=float),
                            np.array([age], dtype=float))


def test_no_neighbour_leaves_the_command_alone():
    act = keep_apart((0.0, 0.0, 0.0), (1.0, 0.2, 0.0), 1, NeighbourReports.empty(), D)
    assert act.velocity_m_s == (1.0, 0.2, 0.0) and act.acting == () and act.nearest_m == math.inf


@pytest.mark.parametrize("gap, inside", [(D + EPS, False), (D, False), (D - 1e-6, True), (0.3, True)])
def test_the_push_acts_only_strictly_inside_d_min(gap, inside):
    act = keep_apart((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1, one((gap, 0.0, 0.0)), D)  # not closing
    assert act.active is inside
    assert act.nearest_m == pytest.approx(gap)
    assert act.velocity_m_s[0] == pytest.approx(-min(D - gap, CFG.max_push_m_s) if inside else 0.0)


@pytest.mark.parametrize("speed, acts", [(0.25 - 1e-6, False), (0.25, False), (0.25 + 1e-6, True), (1.0, True)])
def test_outside_d_min_closing_is_limited_to_reach_it_no_sooner_than_the_horizon(speed, acts):
    # d_min 1 m, 0.375 m outside it, horizon 1.5 s: up to 0.25 m/s towards a still neighbour
    act = keep_apart((0.0, 0.0, 0.0), (speed, 0.4, 0.0), 1, one((1.375, 0.0, 0.0)), 1.0)
    assert act.active is acts
    assert act.velocity_m_s == pytest.approx((min(speed, 0.25), 0.4, 0.0), abs=1e-15)


@pytest.mark.parametrize("towards, speed, want", [
    (0.1, 0.15 - 1e-6, None),    # a neighbour coming at 0.1 m/s leaves 0.25 - 0.1 m/s: just under, untouched
    (0.1, 0.15, None),           # exactly the limit: untouched
    (0.1, 0.15 + 1e-6, 0.15),    # just over: cut to it
    (0.25, 0.5, 0.0),            # coming at the whole gap / horizon: stop (not back: moving away is the push's)
    (0.8, 0.5, 0.0),             # faster than that: still stop, never reverse
    (-0.3, 0.5, None),           # moving away at 0.3: 0.25 + 0.3 allowed, 0.5 untouched
    (0.0, 0.3, 0.25),            # still: the whole gap / horizon
])
def test_a_neighbour_coming_towards_the_vehicle_takes_its_speed_off_the_closing_allowed(towards, speed, want):
    # d_min 1 m, 0.375 m outside it, horizon 1.5 s: 0.25 m/s in all for the pair (head on, 0.48 m by SIH's truth
    # on two stock PX4 when each allowed itself the whole 0.25)
    act = keep_apart((0.0, 0.0, 0.0), (speed, 0.4, 0.0), 1, one((1.375, 0.0, 0.0), vel=(-towards, 0.0, 0.0)), 1.0)
    assert act.active is (want is not None)
    assert act.velocity_m_s == pytest.approx((speed if want is None else want, 0.4, 0.0), abs=1e-12)


def test_a_stale_neighbours_velocity_takes_nothing_off_but_its_radius_grows():
    # 0.6 s old (fresh 0.5 s): no velocity, keep-out 1 + 2 x 0.1 m; its position not extrapolated beyond 0.5 s
    act = keep_apart((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 1, one((2.5, 0.0, 0.0), vel=(-0.5, 0.0, 0.0), age=0.6), 1.0)
    pos_then = 2.5 - 0.5 * 0.5
    assert act.velocity_m_s == pytest.approx(((pos_then - 1.2) / 1.5, 0.0, 0.0), abs=1e-12)


def test_a_fast_neighbour_far_out_head_on_is_heard_beyond_the_vehicles_own_reach():
    # 0.5 m/s for 1.5 s reaches 0.75 m beyond d_min; a neighbour 3 m beyond it coming at 2 m/s leaves none
    act = keep_apart((0.0, 0.0, 0.0), (0.5, 0.0, 0.0), 1, one((4.0, 0.0, 0.0), vel=(-2.0, 0.0, 0.0)), 1.0)
    assert act.acting == (7,) and act.velocity_m_s == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)


def test_with_no_horizon_the_net_acts_only_inside_d_min():
    cfg = SafetyNetConfig(horizon_s=0.0)
    assert not keep_apart((0.0, 0.0, 0.0), (5.0, 0.0, 0.0), 1, one((D + 1e-6, 0.0, 0.0)), D, cfg).active
    inside = keep_apart((0.0, 0.0, 0.0), (5.0, 0.0, 0.0), 1, one((D - 0.1, 0.0, 0.0)), D, cfg)
    assert inside.velocity_m_s == pytest.approx((-0.1, 0.0, 0.0))


def test_closing_on_a_still_neighbour_is_cut_and_the_push_backs_off():
    # neighbour 0.5 m ahead, still: the 1 m/s towards it is cut, push 1/s x 0.42 m backwards
    act = keep_apart((0.0, 0.0, 0.0), (1.0, 0.3, 0.0), 1, one((0.5, 0.0, 0.0)), D)
    assert act.acting == (7,)
    assert act.velocity_m_s == pytest.approx((-(D - 0.5), 0.3, 0.0))


def test_a_column_moving_together_keeps_its_speed():
    # the neighbour ahead flies away at 0.6 m/s: closing up to 0.6 m/s is allowed, only the excess is cut
    act = keep_apart((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 1, one((0.8, 0.0, 0.0), vel=(0.6, 0.0, 0.0)), D)
    pred_gap = 0.8  # age 0: no extrapolation
    assert act.velocity_m_s == pytest.approx((0.6 - (D - pred_gap), 0.0, 0.0))


@pytest.mark.parametrize("vx", [-1.0, 0.0])
def test_moving_away_or_across_is_not_cut_only_pushed(vx):
    act = keep_apart((0.0, 0.0, 0.0), (vx, 0.5, 0.0), 1, one((0.5, 0.0, 0.0)), D)
    assert act.velocity_m_s == pytest.approx((vx - (D - 0.5), 0.5, 0.0))


def test_the_sign_of_the_direction_follows_which_side_the_neighbour_is_on():
    ahead = keep_apart((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1, one((0.5, 0.0, 0.0)), D).velocity_m_s
    behind = keep_apart((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1, one((-0.5, 0.0, 0.0)), D).velocity_m_s
    above = keep_apart((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1, one((0.0, 0.0, 0.5)), D).velocity_m_s
    assert ahead[0] < 0 < behind[0] and above[2] < 0 and ahead[0] == pytest.approx(-behind[0])


def test_coincident_positions_separate_by_id():
    lo = keep_apart((1.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1, one((1.0, 0.0, 0.0), agent_id=2), D).velocity_m_s
    hi = keep_apart((1.0, 0.0, 0.0), (0.0, 0.0, 0.0), 2, one((1.0, 0.0, 0.0), agent_id=1), D).velocity_m_s
    assert lo == pytest.approx((CFG.max_push_m_s, 0.0, 0.0)) and hi == pytest.approx((-CFG.max_push_m_s, 0.0, 0.0))


def test_the_summed_push_is_capped():
    reports = NeighbourReports(np.array([2, 3]), np.array([[0.05, 0.0, 0.0], [0.0, 0.05, 0.0]]), np.zeros((2, 3)),
                               np.zeros(2))
    v = np.array(keep_apart((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1, reports, D).velocity_m_s)
    assert np.linalg.norm(v) == pytest.approx(CFG.max_push_m_s)
    assert v[0] < 0 and v[1] < 0


def test_between_two_neighbours_the_pushes_cancel_and_no_closing_survives():
    reports = NeighbourReports(np.array([2, 3]), np.array([[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0]]), np.zeros((2, 3)),
                               np.zeros(2))
    act = keep_apart((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 1, reports, D)
    assert act.acting == (2, 3) and act.velocity_m_s == pytest.approx((0.0, 0.0, 0.0))


def test_a_fresh_report_is_extrapolated_by_its_velocity_up_to_fresh_s():
    # reported 1.4 m ahead coming back at 1 m/s: 0.4 s old -> now 1.0 m ahead (outside d_min 0.92),
    # 0.6 s old -> extrapolated only fresh_s = 0.5 s -> 0.9 m, and the report is stale so its radius grows
    fresh = one((1.4, 0.0, 0.0), vel=(-1.0, 0.0, 0.0), age=0.4)
    assert keep_apart((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1, fresh, D).nearest_m == pytest.approx(1.0)
    older = one((1.4, 0.0, 0.0), vel=(-1.0, 0.0, 0.0), age=0.6)
    pos, radius, kept = predicted_and_radius(older, D, CFG)
    assert pos[0] == pytest.approx((0.9, 0.0, 0.0)) and radius[0] == pytest.approx(D + CFG.growth_m_s * 0.1)


@pytest.mark.parametrize("age, inside", [(CFG.fresh_s, False), (CFG.fresh_s + 0.2, False), (CFG.fresh_s + 0.3, True)])
def test_a_stale_neighbour_is_kept_at_a_growing_distance(age, inside):
    # a still neighbour 1.5 m ahead: d_min + 2 m/s x (age - 0.5 s) reaches 1.5 m at age 0.79 s
    act = keep_apart((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1, one((1.5, 0.0, 0.0), age=age), D)
    assert act.active is inside


def test_a_stale_neighbour_moving_away_allows_no_closing():
    # 0.5 m ahead flying away at 0.6 m/s; fresh: closing at 0.6 m/s is allowed
    fresh = keep_apart((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 1, one((0.5, 0.0, 0.0), vel=(0.6, 0.0, 0.0)), D)
    assert fresh.velocity_m_s[0] == pytest.approx(0.6 - (D - 0.5))
    # 0.01 s past fresh_s: taken 0.3 m farther (0.8 m), radius d_min + 0.02 m, and no closing at all
    age = CFG.fresh_s + 0.01
    stale = keep_apart((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 1, one((0.5, 0.0, 0.0), vel=(0.6, 0.0, 0.0), age=age), D)
    assert stale.velocity_m_s[0] == pytest.approx(-(D + CFG.growth_m_s * 0.01 - 0.8))


@pytest.mark.parametrize("age, kept", [(CFG.forget_s, True), (CFG.forget_s + 1e-6, False)])
def test_reports_older_than_forget_s_are_dropped(age, kept):
    act = keep_apart((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 1, one((0.3, 0.0, 0.0), age=age), D)
    assert act.active is kept and (act.nearest_m < math.inf) is kept


@pytest.mark.parametrize("field, value", [("fresh_s", -0.1), ("growth_m_s", math.nan), ("forget_s", math.inf),
                                          ("max_push_m_s", -1.0), ("pass_margin_m", -0.01)])
def test_bad_settings_are_named(field, value):
    with pytest.raises(ValueError, match=field):
        SafetyNetConfig(**{field: value})


def test_forget_before_fresh_is_refused():
    with pytest.raises(ValueError, match="forget_s"):
        SafetyNetConfig(fresh_s=2.0, forget_s=1.0)


@pytest.mark.parametrize("lag, duct", [(0.0, None), (0.6, DuctAxis(1.0, 5.0, (0.1, -0.2)))])
def test_the_swarm_form_agrees_with_the_single_vehicle_oracle(lag, duct):
    rng = np.random.default_rng(3)
    n = 60
    pos = rng.uniform([0, -1.5, -1.5], [6, 1.5, 1.5], size=(n, 3))
    pos[5] = pos[4]  # one coincident pair
    vel = rng.normal(size=(n, 3))
    cmd = rng.normal(size=(n, 3))
    ids = rng.permutation(1000)[:n]
    i, j = np.triu_indices(n, 1)
    out = keep_apart_pairs(pos, vel, cmd, ids, np.stack([i, j], 1), D, CFG, lag, duct)
    acted = 0
    for a in range(n):
        others = np.arange(n) != a
        rep = NeighbourReports(ids[others], pos[others], vel[others], np.zeros(n - 1))
        act = keep_apart(tuple(pos[a]), tuple(cmd[a]), int(ids[a]), rep, D, CFG, lag, duct)
        acted += act.active
        assert out[a] == pytest.approx(np.array(act.velocity_m_s), abs=1e-12)
    assert 5 <= acted < n  # the check covered both kinds


def test_the_swarm_form_with_no_pairs_returns_a_copy():
    cmd = np.ones((3, 3))
    out = keep_apart_pairs(np.zeros((3, 3)), np.zeros((3, 3)), cmd, np.arange(3), np.zeros((0, 2)), D)
    assert np.array_equal(out, cmd) and out is not cmd


# ---- the neighbour table, from raw telemetry bytes on a simulated clock ----------------------
class Clock:
    def __init__(self):
        self.t = 50.0

    def __call__(self):
        return self.t


def message(agent_id, pos=(1.0, 2.0, 3.0), vel=(0.5, 0.0, 0.0), pos_age_s=0.05, landed="in-air") -> bytes:
    return tc.encode(tc.Telemetry(agent_id=agent_id, seq=1, time_s=1.7e9, position_m=pos, velocity_m_s=vel,
                                  position_age_s=pos_age_s, landed=landed))


def test_the_table_keeps_the_newest_report_per_id_with_its_age_now():
    clock = Clock()
    table = NeighbourTable(clock)
    table.take(message(3, pos=(0.0, 0.0, 0.0)))
    clock.t += 0.2
    table.take(message(3, pos=(1.0, 0.0, 0.0), pos_age_s=0.1))
    table.take(message(4))
    clock.t += 0.3
    rep = table.reports(exclude_id=4)
    assert list(rep.ids) == [3] and rep.position_m[0] == pytest.approx((1.0, 0.0, 0.0))
    assert rep.age_s[0] == pytest.approx(0.3 + 0.1, abs=1e-3)  # ms resolution of the wire
    assert rep.velocity_m_s[0] == pytest.approx((0.5, 0.0, 0.0))
    assert len(table.reports(exclude_id=99)) == 2 and table.messages == 3


def test_a_vehicle_on_the_ground_or_without_a_position_leaves_the_table():
    table = NeighbourTable(Clock())
    table.take(message(3))
    table.take(message(5))
    table.take(message(3, landed="on-ground"))
    table.take(message(5, pos=(math.nan, math.nan, math.nan)))
    assert len(table) == 0 and len(table.reports(0)) == 0


def test_undecodable_bytes_are_counted_not_raised():
    table = NeighbourTable(Clock())
    table.take(b"\x02short")
    table.take(b"")
    assert table.bad_messages == 2 and len(table) == 0


def test_the_table_grows_past_its_first_rows_and_keeps_every_report_in_place():
    clock = Clock()
    table = NeighbourTable(clock)
    for i in range(20):
        table.take(message(100 + i, pos=(float(i), 0.0, 0.0), pos_age_s=0.0))
    table.take(message(105, landed="on-ground"))
    rep = table.reports(exclude_id=100)
    assert sorted(rep.ids) == [i for i in range(101, 120) if i != 105]
    assert all(p[0] == i - 100 for i, p in zip(rep.ids, rep.position_m))
    table.take(message(105, pos=(-1.0, 0.0, 0.0)))  # back in the air
    assert 105 in table.reports(exclude_id=100).ids and len(table) == 20


# ---- the wall rule and the lag-adapted horizon -----------------------------------------------------


def test_over_the_duct_the_net_never_pushes_away_from_its_axis():
    # the neighbour sits nearer the axis (z 0.5) than this vehicle (z 1.0): the push would be outward (+z)
    act = keep_apart((5.0, 0.0, 1.0), (1.0, 0.0, 0.0), 1, one((5.0, 0.0, 0.5)), D, duct=DUCT)
    assert act.active and act.velocity_m_s == pytest.approx((1.0, 0.0, 0.0))
    free = keep_apart((5.0, 0.0, 1.0), (1.0, 0.0, 0.0), 1, one((5.0, 0.0, 0.5)), D)  # no duct: pushed out
    assert free.velocity_m_s[2] == pytest.approx(D - 0.5)


def test_the_wall_rule_keeps_the_inward_and_axial_parts_of_the_correction():
    # neighbour ahead and outside (x + 0.3, z + 0.3): the push is backwards and inwards, both kept
    act = keep_apart((5.0, 0.0, 1.0), (0.0, 0.0, 0.0), 1, one((5.3, 0.0, 1.3)), D, duct=DUCT)
    d = math.hypot(0.3, 0.3)
    push = (D - d) / d * 0.3
    assert act.velocity_m_s == pytest.approx((-push, 0.0, -push))


@pytest.mark.parametrize("x, ruled", [(-1e-6, False), (0.0, True), (10.0, True), (10.0 + 1e-6, False)])
def test_the_wall_rule_holds_over_the_ducts_length_only(x, ruled):
    act = keep_apart((x, 1.0, 0.0), (0.0, 0.0, 0.0), 1, one((x, 0.5, 0.0)), D, duct=DUCT)
    assert act.velocity_m_s[1] == pytest.approx(0.0 if ruled else D - 0.5)


def test_the_wall_rule_follows_the_ducts_own_axis():
    duct = DuctAxis(0.0, 10.0, (2.0, 0.0))  # axis at y = 2: y = 1 lies inside of it, pushing -y is outward
    act = keep_apart((5.0, 1.0, 0.0), (0.0, 0.0, 0.0), 1, one((5.0, 1.5, 0.0)), D, duct=duct)
    assert act.velocity_m_s == pytest.approx((0.0, 0.0, 0.0))


@pytest.mark.parametrize("lag, horizon", [(0.0, 1.5), (1.5 / 4.0, 1.5), (0.5, 2.0), (0.89, 3.56), (math.nan, 1.5),
                                          (-1.0, 1.5)])
def test_the_horizon_is_the_longer_of_horizon_s_and_four_lags(lag, horizon):
    assert effective_horizon_s(CFG, lag) == pytest.approx(horizon)


def test_a_lagging_vehicle_starts_braking_farther_out():
    # 1 m/s at a still neighbour 2.5 m away (1.58 m outside d_min): a 1.5 s horizon allows 1.05 m/s,
    # a 0.89 s lag's 3.56 s horizon only 0.44 m/s
    far = one((2.5, 0.0, 0.0))
    assert not keep_apart((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 1, far, D).active
    slow = keep_apart((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 1, far, D, lag_s=0.89)
    assert slow.velocity_m_s[0] == pytest.approx((2.5 - D) / (4 * 0.89))


# ---- passing is not closing ------------------------------------------------------------------
@pytest.mark.parametrize("rel, w, horizon, expect", [
    ((3.0, 4.0, 0.0), (0.0, 0.0, 0.0), 1.5, 5.0),      # at rest relative to each other: the distance now
    ((3.0, 4.0, 0.0), (1.0, 0.0, 0.0), 1.5, 5.0),      # moving apart: now is the closest
    ((-2.0, 1.0, 0.0), (2.0, 0.0, 0.0), 1.5, 1.0),     # passing within the horizon: the offset
    ((-4.0, 1.0, 0.0), (2.0, 0.0, 0.0), 1.5, math.hypot(1.0, 1.0)),  # beyond it: where the horizon ends
    ((-4.0, 0.0, 0.0), (2.0, 0.0, 0.0), 0.0, 4.0),     # no horizon: now
])
def test_the_closest_approach_within_the_horizon(rel, w, horizon, expect):
    got = closest_approach_m(np.array([rel]), np.array([w]), horizon)
    assert got == pytest.approx([expect], abs=1e-15)


@pytest.mark.parametrize("offset, acts", [(1.5 + 1e-6, False), (1.5, False), (1.5 - 1e-6, True), (0.0, True)])
def test_a_vehicle_flying_past_a_neighbour_is_not_braked(offset, acts):
    # 2 m/s along x, 2 m short of a still neighbour, offset across: closest approach = offset after 1 s;
    # d_min 1 m + the 0.5 m pass margin = 1.5 m.  At 1.5 m the old rule would cut: closing 1.6 m/s, allowed 0.95
    act = keep_apart((-2.0, offset, 0.0), (2.0, 0.0, 0.0), 1, one((0.0, 0.0, 0.0)), 1.0)
    assert act.active is acts
    if not acts:
        assert act.velocity_m_s == (2.0, 0.0, 0.0)


def test_a_vehicle_descending_beside_a_waiting_one_is_left_alone_but_not_one_above_it():
    # eight stock PX4: a lap's return came down at 2 m/s to its wait point 3 m beside a waiting vehicle,
    # braked by the old rule from 3 m above (closing 1.41 m/s, allowed 0.92 m/s over its 3.6 s horizon)
    waiting = one((0.0, 0.0, 0.0))
    beside = keep_apart((0.0, 3.0, 3.0), (0.0, 0.0, -2.0), 1, waiting, D, lag_s=0.9)
    assert not beside.active and beside.velocity_m_s == (0.0, 0.0, -2.0)
    above = keep_apart((0.0, 0.0, 3.0), (0.0, 0.0, -2.0), 1, waiting, D, lag_s=0.9)
    assert above.active and above.velocity_m_s[2] == pytest.approx(-(3.0 - D) / (4 * 0.9))


def test_a_fresh_neighbour_moving_out_of_the_way_lets_a_vehicle_pass_a_stale_one_does_not():
    # heading for where the neighbour is; it reports moving across at 3 m/s.  Fresh: the paths miss; stale
    # (age 1 s): taken as still (extrapolated by fresh_s only) and the closing is cut
    fresh = keep_apart((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 1, one((2.0, 0.0, 0.0), vel=(0.0, 3.0, 0.0)), D)
    assert not fresh.active
    stale = keep_apart((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 1, one((2.0, 0.0, 0.0), vel=(0.0, 3.0, 0.0), age=1.0), D)
    assert stale.active and stale.velocity_m_s[0] < 1.0


@pytest.mark.parametrize("seed", [0, 1])
def test_head_on_the_pass_rule_changes_nothing(seed):
    # straight at a still neighbour: the closing limit (d - d_min) / T wherever it acts, as without the rule
    rng = np.random.default_rng(seed)
    lag = 0.9
    horizon = effective_horizon_s(CFG, lag)
    cut = 0
    for d, v in zip(rng.uniform(D + 1e-3, 10.0, 200), rng.uniform(0.0, 3.0, 200)):
        act = keep_apart((0.0, 0.0, 0.0), (v, 0.0, 0.0), 1, one((d, 0.0, 0.0)), D, lag_s=lag)
        assert act.velocity_m_s[0] == pytest.approx(min(v, (d - D) / horizon), abs=1e-12)
        cut += act.active
    assert 20 < cut < 180   # both sides of the limit were drawn


@pytest.mark.parametrize("k", [2, 4, 8])
def test_a_queue_ahead_stops_the_vehicle_and_never_reverses_it(k):
    v = np.array([2.95, 0.35, 1.54])  # a join climbing forward
    d = v / np.linalg.norm(v)
    pos = np.array([d * (2.6 + 0.05 * i) + np.array([0.0, 0.1 * i, 0.0]) for i in range(k)])
    out = keep_apart((0.0, 0.0, 0.0), tuple(v), 100, NeighbourReports(np.arange(k), pos, np.zeros((k, 3)), np.zeros(k)),
                     0.92, SafetyNetConfig())
    assert float(np.dot(out.velocity_m_s, d)) >= -0.1, out.velocity_m_s


def closing_limits_met(out, v, pos_nb, vel_nb, d, horizon):
    """Each still or fresh neighbour's closing limit, checked on ``out`` directly (the module's rule)."""
    for p, u in zip(pos_nb, vel_nb):
        rel = -np.asarray(p)
        dist = np.linalg.norm(rel)
        n = rel / dist
        allowed = max(0.0, -float(np.dot(u, n))) + max(0.0, dist - d) / horizon
        assert -float(np.dot(out, n)) <= allowed + 1e-12


@pytest.mark.parametrize("k", [1, 2, 4, 8])
def test_a_queue_ahead_brakes_the_vehicle_once_not_once_per_neighbour(k):
    # the kill lab's join: (2.95, 0.35, 1.54) m/s towards a queue 2.6 m ahead.  The nearest sets the limit;
    # the ones behind it allow more and cut nothing, so the command is the same for 1 or 8 in the queue
    v = np.array([2.95, 0.35, 1.54])
    d = v / np.linalg.norm(v)
    pos = np.array([d * (2.6 + 0.05 * i) + np.array([0.0, 0.1 * i, 0.0]) for i in range(k)])
    act = keep_apart((0.0, 0.0, 0.0), tuple(v), 100, NeighbourReports(np.arange(k), pos, np.zeros((k, 3)), np.zeros(k)),
                     D, CFG)
    one_ahead = keep_apart((0.0, 0.0, 0.0), tuple(v), 100, one(tuple(pos[0])), D, CFG)
    assert act.velocity_m_s == pytest.approx(one_ahead.velocity_m_s, abs=1e-12)
    assert float(np.dot(act.velocity_m_s, d)) == pytest.approx((2.6 - D) / CFG.horizon_s, rel=1e-9)
    assert act.acting == (0,)
    closing_limits_met(np.array(act.velocity_m_s), v, pos, np.zeros((k, 3)), D, CFG.horizon_s)


def test_the_nearest_gap_cuts_first_and_a_farther_one_only_what_remains():
    # 2 m/s along x; a still neighbour 2.0 m ahead allows (2.0 - D) / 1.5 = 0.72 m/s; another 1.5 m ahead and
    # 1 m across, nearer by its gap, cuts first along its own line; the first then cuts what remains of x
    reports = NeighbourReports(np.array([5, 6]), np.array([[2.0, 0.0, 0.0], [1.5, 1.0, 0.0]]), np.zeros((2, 3)),
                               np.zeros(2))
    act = keep_apart((0.0, 0.0, 0.0), (2.0, 0.0, 0.0), 1, reports, D)
    n6 = -np.array([1.5, 1.0, 0.0]) / math.hypot(1.5, 1.0)
    allowed6 = (math.hypot(1.5, 1.0) - D) / CFG.horizon_s
    w = np.array([2.0, 0.0, 0.0])
    w = w + (-(w @ n6) - allowed6) * n6
    w[0] = min(w[0], (2.0 - D) / CFG.horizon_s)  # neighbour 5's limit: n = -x
    closing6 = -(w @ n6)
    if closing6 > allowed6:  # the first limit broken again: scaled down to meet both
        w = w * allowed6 / closing6
    assert act.velocity_m_s == pytest.approx(tuple(w), abs=1e-12)
    assert act.acting == (5, 6)


def test_two_neighbours_ahead_either_side_stop_the_vehicle_without_reversing_it():
    # 30 degrees above and below the path, 0.5 m inside d_min: no command towards either is allowed; the
    # summed cuts commanded 1 m/s backwards, one at a time plus the scale leave it still (and the push)
    c, s_ = math.cos(math.radians(30)), math.sin(math.radians(30))
    r = D - 0.5
    reports = NeighbourReports(np.array([2, 3]), np.array([[r * c, 0.0, r * s_], [r * c, 0.0, -r * s_]]),
                               np.zeros((2, 3)), np.zeros(2))
    act = keep_apart((0.0, 0.0, 0.0), (2.0, 0.0, 0.0), 1, reports, D, CFG)
    push = 2 * CFG.push_gain_1_s * 0.5 * c
    assert act.velocity_m_s == pytest.approx((-min(push, CFG.max_push_m_s), 0.0, 0.0), abs=1e-12)
    assert act.acting == (2, 3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_cuts_never_speed_a_vehicle_up_and_meet_every_limit(seed):
    # random crowds without pushes (all outside d_min): |out| <= |command|, and no limit broken
    rng = np.random.default_rng(seed)
    checked = 0
    for _ in range(200):
        k = int(rng.integers(1, 9))
        direction = rng.normal(size=(k, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        pos = direction * rng.uniform(D + 1e-3, 3.0, (k, 1))
        vel = rng.normal(0.0, 0.5, (k, 3))
        v = rng.normal(0.0, 1.5, 3)
        act = keep_apart((0.0, 0.0, 0.0), tuple(v), 1000, NeighbourReports(np.arange(k), pos, vel, np.zeros(k)), D, CFG)
        out = np.array(act.velocity_m_s)
        assert np.linalg.norm(out) <= np.linalg.norm(v) + 1e-12
        assert float(out @ v) >= -1e-12  # never turned back against the command
        passing = closest_approach_m(-pos, v - vel, CFG.horizon_s) >= D + CFG.pass_margin_m
        closing_limits_met(out, v, pos[~passing], vel[~passing], D, CFG.horizon_s)
        checked += act.active
    assert checked > 50


def test_the_sequential_cuts_of_several_vehicles_at_once_match_one_vehicle_at_a_time():
    rng = np.random.default_rng(7)
    cmd = rng.normal(size=(5, 3))
    me = rng.integers(0, 5, 40)
    unit = rng.normal(size=(40, 3))
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    allowed = rng.uniform(0.0, 1.0, 40)
    gap = rng.uniform(0.0, 2.0, 40)
    nb = rng.permutation(100)[:40]
    together = sequential_cuts(cmd, me, nb, unit, allowed, gap)
    for a in range(5):
        mine = me == a
        alone = sequential_cuts(cmd[a:a + 1], np.zeros(mine.sum(), dtype=np.int64), nb[mine], unit[mine], allowed[mine],
                                gap[mine])
        assert together[a] == pytest.approx(alone[0], abs=1e-12)
        assert np.all(-(unit[mine] @ together[a]) <= allowed[mine] + 1e-12)
    assert np.array_equal(sequential_cuts(cmd, me[:0], nb[:0], unit[:0], allowed[:0], gap[:0]), cmd)


@pytest.mark.parametrize("seed", range(4))
def test_inside_d_min_a_cut_keeps_the_sideways_part_however_it_rounds(seed):
    # inside the radius no closing is allowed: the cut lands the command on the limit (closing 0 to within
    # rounding), which is not a broken limit; the sideways part survives and the push is added
    rng = np.random.default_rng(seed)
    for _ in range(50):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)  # from this vehicle to the neighbour
        v = rng.normal(size=3)
        v += (abs(v @ u) + 0.1) * u  # closing on it
        act = keep_apart((0.0, 0.0, 0.0), tuple(v), 1, one(tuple(0.5 * u)), D)
        slide = v - (v @ u) * u
        push = -min(CFG.push_gain_1_s * (D - 0.5), CFG.max_push_m_s) * u
        assert act.velocity_m_s == pytest.approx(tuple(slide + push), abs=1e-12)


# ---- boundaries the mutation run (tools/mutation.sh safety_net) found untested -------------------------
def test_no_neighbour_in_reach_acts_on_nothing_and_still_reports_the_nearest():
    act = keep_apart((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 1, one((0.0, 5.0, 0.0)), D)
    assert act.acting == () and act.velocity_m_s == (1.0, 0.0, 0.0) and act.nearest_m == pytest.approx(5.0)
    passing = keep_apart((-2.0, 1.6, 0.0), (2.0, 0.0, 0.0), 1, one((0.0, 0.0, 0.0)), 1.0)
    assert passing.acting == () and passing.nearest_m == pytest.approx(math.hypot(2.0, 1.6))


@pytest.mark.parametrize("command", [(0.0, 0.0, 0.0), (0.0, 1.0, 0.0)])
def test_exactly_at_d_min_a_vehicle_not_closing_is_not_acted_on(command):
    act = keep_apart((0.0, 0.0, 0.0), command, 1, one((1.0, 0.0, 0.0)), 1.0)
    assert act.acting == () and act.velocity_m_s == command


def test_a_report_exactly_fresh_s_old_still_counts_as_moving_away():
    # 0.5 m ahead moving away at 0.6 m/s, age exactly fresh_s: extrapolated to 0.8 m, radius d_min, and its
    # speed away is allowed; the push adds (D - 0.8) backwards
    act = keep_apart((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 1, one((0.5, 0.0, 0.0), vel=(0.6, 0.0, 0.0), age=CFG.fresh_s), D)
    assert act.velocity_m_s == pytest.approx((0.6 - (D - 0.8), 0.0, 0.0), abs=1e-12)


def test_a_command_swung_round_by_two_cuts_loses_only_its_backward_part():
    # 0.8 m/s along x (|v|^2 = 1 would hide a missing division); the nearer neighbour (inside d_min) turns it
    # along its own limit, the farther one (above) turns it back; the result loses its backward part and is
    # scaled down to meet both limits again, keeping the direction it had
    v = np.array([0.8, 0.0, 0.0])
    pos = np.array([[0.7, 0.0, -0.2], [0.7, -0.2, 0.7]])
    act = keep_apart((0.0, 0.0, 0.0), tuple(v), 1, NeighbourReports(np.array([2, 3]), pos, np.zeros((2, 3)), np.zeros(2)),
                     D, CFG)
    d = np.linalg.norm(pos, axis=1)
    units = -pos / d[:, None]
    allowed = np.maximum(0.0, d - D) / CFG.horizon_s
    w = v.copy()
    for n, a in zip(units, allowed):  # nearest gap first
        w = w + max(0.0, -(w @ n) - a) * n
    assert w @ v < 0  # the cuts swung it back
    w = w - (w @ v) / (v @ v) * v
    closing = -(units @ w)
    scale = min(1.0, *(allowed[closing > allowed] / closing[closing > allowed]))
    assert 0.5 < scale < 1.0
    push = CFG.push_gain_1_s * (D - d[0]) * units[0]
    assert act.velocity_m_s == pytest.approx(tuple(scale * w + push), abs=1e-12)
    assert act.acting == (2, 3)


def test_settings_with_forget_equal_to_fresh_are_accepted():
    assert SafetyNetConfig(fresh_s=1.0, forget_s=1.0).forget_s == 1.0


def test_no_neighbours_heard_is_an_empty_table_of_the_right_shapes():
    e = NeighbourReports.empty()
    assert len(e) == 0 and e.ids.dtype == np.int64
    assert e.position_m.shape == (0, 3) and e.velocity_m_s.shape == (0, 3) and e.age_s.shape == (0,)


def test_an_infinite_lag_is_ignored():
    assert effective_horizon_s(CFG, math.inf) == CFG.horizon_s


def test_the_wall_rule_about_an_axis_off_centre_in_z():
    # axis at (y, z) = (0, 1); the vehicle at (0.5, 1.5): 45 degrees up and out.  The push from a neighbour
    # ahead and below has an outward part along (0, 1, 1) / sqrt 2, removed; the rest kept
    duct = DuctAxis(0.0, 10.0, (0.0, 1.0))
    act = keep_apart((5.0, 0.5, 1.5), (0.0, 0.0, 0.0), 1, one((5.3, 0.5, 1.2)), D, duct=duct)
    d = math.hypot(0.3, 0.3)
    push = (D - d) / d * np.array([-0.3, 0.0, 0.3])
    u = np.array([0.0, 1.0, 1.0]) / math.sqrt(2.0)
    assert act.velocity_m_s == pytest.approx(tuple(push - max(0.0, push @ u) * u), abs=1e-12)


@pytest.mark.parametrize("d, cut", [(1.5, False), (1.0, False), (0.99, True)])
def test_the_swarm_form_with_no_horizon_acts_only_inside_d_min(d, cut):
    # keep_apart_pairs checks every pair it is given (no reach filter): outside or at d_min nothing is allowed
    # to change, inside no closing survives
    cfg = SafetyNetConfig(horizon_s=0.0)
    pos = np.array([[0.0, 0.0, 0.0], [d, 0.0, 0.0]])
    cmd = np.array([[3.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    out = keep_apart_pairs(pos, np.zeros((2, 3)), cmd, np.array([1, 2]), np.array([[0, 1]]), 1.0, cfg)
    if cut:
        assert out[0] == pytest.approx((-cfg.push_gain_1_s * (1.0 - d), 0.0, 0.0))
    else:
        assert np.array_equal(out, cmd)


@pytest.mark.parametrize("gap, untouched", [(0.0, True), (-0.01, False)])
def test_with_no_horizon_the_net_acts_only_inside_d_min(gap, untouched):
    cfg = SafetyNetConfig(horizon_s=0.0)
    act = keep_apart((0.0, 0.0, 0.0), (3.0, 0.0, 0.0), 1, one((1.0 + gap, 0.0, 0.0)), 1.0, cfg)
    if untouched:
        assert act.velocity_m_s == (3.0, 0.0, 0.0)
    else:
        assert act.velocity_m_s == pytest.approx((-cfg.push_gain_1_s * 0.01, 0.0, 0.0))


def test_a_horizon_shorter_than_a_second_limits_closing_to_gap_over_it():
    cfg = SafetyNetConfig(horizon_s=0.5)
    act = keep_apart((0.0, 0.0, 0.0), (3.0, 0.0, 0.0), 1, one((1.3, 0.0, 0.0)), 1.0, cfg)
    assert act.velocity_m_s == pytest.approx((0.3 / 0.5, 0.0, 0.0))


def test_a_pass_that_comes_close_only_after_the_horizon_is_left_alone():
    # 3 m/s along x, 5 m behind a still neighbour and 1.38 m across: within the 1.5 s horizon it gets no nearer
    # than 1.47 m (>= d_min + pass margin 1.42 m); its straight line would pass at 1.38 m only later.  Closing at
    # 2.89 m/s against 2.84 m/s allowed: the horizon alone keeps it from being braked
    act = keep_apart((-5.0, 1.38, 0.0), (3.0, 0.0, 0.0), 1, one((0.0, 0.0, 0.0)), D)
    assert not act.active and act.velocity_m_s == (3.0, 0.0, 0.0)


def test_the_swarm_form_with_one_pair_and_its_default_lag():
    pos = np.array([[0.0, 0.0, 0.0], [2.5, 0.0, 0.0]])
    cmd = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    out = keep_apart_pairs(pos, np.zeros((2, 3)), cmd, np.array([1, 2]), np.array([[0, 1]]), D)
    lone = keep_apart((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 1, one((2.5, 0.0, 0.0)), D, lag_s=0.5)
    assert lone.active  # with a lag the horizon (2 s) brakes it: the default lag is none
    assert out[0] == pytest.approx(cmd[0]) and out[1] == pytest.approx(cmd[1])
    close = keep_apart_pairs(pos * 0.3, np.zeros((2, 3)), cmd, np.array([1, 2]), np.array([[0, 1]]), D)
    assert close[0] == pytest.approx(keep_apart((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 1, one((0.75, 0.0, 0.0), agent_id=2),
                                                D).velocity_m_s)


def test_the_swarm_form_leaves_a_hovering_vehicle_hovering_while_its_neighbour_is_braked():
    # vehicle 0 hovers (a zero command: nothing to turn back against), vehicle 1 closes on it from 2 m
    pos = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    cmd = np.array([[0.0, 0.0, 0.0], [-2.0, 0.0, 0.0]])
    out = keep_apart_pairs(pos, cmd, cmd, np.array([1, 2]), np.array([[0, 1]]), D)
    assert np.array_equal(out[0], (0.0, 0.0, 0.0))
    assert out[1] == pytest.approx((-(2.0 - D) / CFG.horizon_s, 0.0, 0.0))
