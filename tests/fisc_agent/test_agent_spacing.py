"""Spacing (issue 36, item 7): entry points and windows unique for ids 0..63, exit holds and landing
spots >= 1.5 m apart horizontally, hold spots never below the tunnel's floor or a given ground."""

import dataclasses
import math

import numpy as np
import pytest

from fisc_agent.config import AgentConfig
from fisc_agent.flight.control import (GOLDEN_ANGLE_RAD, MapGeometry, ScalarField, approach_time_s, entry_point,
                                       entry_points, hold_point, hold_points, distance, speed_for_arrival)
from fisc_agent.flight.routes import OVERFLY_M, exit_waypoints
from fisc_agent.flight.spacing import (final_leg_speed_m_s, ENTRY_POINTS, ENTRY_TIMING_TOLERANCE_S, HOLD_FLOOR_MARGIN_M, JOIN_LEG_ALLOWANCE_S,
                                       VOGEL_64_MIN_SPACING, check_min_distance, entry_slot_open, hold_altitude_m,
                                       hold_sites, lattice_hold_points,
                                       min_pairwise_distance_m, EntrySchedule, ScheduleSource, schedule_messages)
from fisc_agent.flight.navigation import EXIT_SETTLE_SPEED_M_S, Navigator
from fisc_agent.map.lookup import CommandField


@pytest.fixture(scope="module")
def maps(tunnel_map):
    from fisc_ground.maps.build import load_shipped_default_map

    out = {}
    for name, m in (("tunnel", tunnel_map), ("default", load_shipped_default_map())):
        f = CommandField.from_map(m)
        out[name] = (MapGeometry.from_field(f), ScalarField(f))
    return out


def _window(agent_id, stagger_s, slots):
    """The entry window an agent's ``entry_slot_open`` opens in, found from the clock alone."""
    step = stagger_s / 16
    opens = [k for k in range(16 * slots) if entry_slot_open(1e6 * stagger_s * slots + k * step, agent_id,
                                                                stagger_s, slots)]
    assert opens, agent_id
    return opens[0] // 16


# ---- the distance check itself -------------------------------------------------------------
def test_check_min_distance_passes_at_the_bound_and_fails_just_below():
    exact = lattice_hold_points(50, 3.7, -0.3, 2.0, 1.5)[:, :2]   # pitch 1.5 with rounding in the coordinates
    assert check_min_distance(exact, 1.5) == pytest.approx(1.5, abs=1e-12)
    planted = exact.copy()
    planted[7] = planted[0] - [1.5 - 1e-6, 0.0]   # one pair just below the bound (upstream of the lattice)
    assert min_pairwise_distance_m(planted) == pytest.approx(1.5 - 1e-6, abs=1e-12)
    with pytest.raises(ValueError, match="holds: two points are 1.499999 m apart, less than the required 1.5 m"):
        check_min_distance(planted, 1.5, "holds")
    assert min_pairwise_distance_m(np.zeros((1, 2))) == math.inf == min_pairwise_distance_m(np.zeros((0, 2)))
    with pytest.raises(ValueError, match=r"\(n, d\) array"):
        min_pairwise_distance_m(np.zeros(3))


# ---- entry points and windows -----------------------------------------------------------------
def test_vogel_64_min_spacing_holds_and_is_not_loose():
    k = np.arange(ENTRY_POINTS)
    r = np.sqrt((k + 0.5) / ENTRY_POINTS)
    unit = np.column_stack([r * np.cos(k * GOLDEN_ANGLE_RAD), r * np.sin(k * GOLDEN_ANGLE_RAD)])
    d = check_min_distance(unit, VOGEL_64_MIN_SPACING, "Vogel 64")
    assert d < VOGEL_64_MIN_SPACING + 1e-3


@pytest.mark.parametrize("name", ["tunnel", "default"])
@pytest.mark.parametrize("fraction, bound", [(0.6, VOGEL_64_MIN_SPACING), (1.0, 0.165)])
def test_entry_points_are_64_distinct_spread_points_inside_the_inlet(maps, name, fraction, bound):
    # fraction 0.6: every spiral point lies in an inlet CV, so the 64 are the Vogel layout itself;
    # fraction 1 (fisc-sim emulate): points outside the staircase are skipped, a denser spiral fills in
    g, sf = maps[name]
    pts = np.array(entry_points(g, sf, fraction))
    assert pts.shape == (ENTRY_POINTS, 3)
    rho = fraction * g.inlet_radius_m
    check_min_distance(pts[:, 1:], bound * rho, f"entry points of {name} at {fraction}")
    r = np.hypot(pts[:, 1] - g.inlet_center_yz_m[0], pts[:, 2] - g.inlet_center_yz_m[1])
    assert r.max() <= rho + 1e-9
    assert all(sf.cv_of(*p) >= 0 for p in pts)
    assert np.all(pts[:, 0] == g.x_inlet_m + 0.5 * g.cell_size_m)


@pytest.mark.parametrize("slots", [1, 2, 6, 8, 16, 64])
def test_no_two_ids_below_64_share_entry_point_and_window(maps, slots):
    g, sf = maps["tunnel"]
    key = {}
    for i in range(64):
        key[i] = (entry_point(i, g, sf), _window(i, 2.0, slots))
    assert len(set(key.values())) == 64
    assert len({p for p, _ in key.values()}) == 64          # the points alone are unique
    # boundary: 63 is still unique, 64 takes 0's point, and its window whenever slots divides 64
    assert key[63] not in [key[i] for i in range(63)]
    p64 = entry_point(64, g, sf)
    assert p64 == key[0][0]
    assert (_window(64, 2.0, slots) == key[0][1]) == (64 % slots == 0)


def test_entry_windows_are_id_mod_slots(maps):
    assert [_window(i, 1.0, 8) for i in range(17)] == [i % 8 for i in range(17)]


# ---- exit holds and landing spots ----------------------------------------------------------------
def test_hold_sites_are_distinct_nearest_first_and_deterministic():
    s = hold_sites(2000)
    assert len({tuple(r) for r in s.tolist()}) == 2000 and s[:, 0].min() == 0
    assert s[:3].tolist() == [[0, 0], [0, -1], [0, 1]]
    d2 = s[:, 0] ** 2 + s[:, 1] ** 2
    assert np.all(np.diff(d2) >= 0)                        # a half disc growing outwards
    assert hold_sites(50).tolist() == s[:50].tolist()       # a prefix: an agent's site does not depend on n
    assert hold_sites(0).shape == (0, 2)
    with pytest.raises(ValueError, match="must be >= 0"):
        hold_sites(-1)


@pytest.mark.parametrize("name", ["tunnel", "default"])
def test_fifty_holds_are_the_default_spacing_apart_horizontally_beyond_the_outlet(maps, name):
    g, _ = maps[name]
    cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=0)
    assert cfg.exit_spacing_m == 3.0                           # >= 1.5 m (issue 36), 3 m for PX4's Hold wander
    x0 = g.x_outlet_m + cfg.exit_clearance_m
    pts = hold_points(50, g, x0, cfg.exit_spacing_m)
    d = check_min_distance(pts[:, :2], 3.0, "50 exit holds")   # horizontal: landing spots too
    assert d == pytest.approx(3.0, abs=1e-9)                   # the lattice's pitch, not looser
    assert pts[:, 0].min() == pytest.approx(x0) and np.all(pts[:, 0] >= x0 - 1e-12)
    # boundaries: ids 0, 49 and 50 are their rows of the layout; 50 is a pitch or more from all of 0..49
    assert [hold_point(k, g, x0, 3.0) for k in (0, 49)] == [tuple(pts[k]) for k in (0, 49)]
    p50 = np.array(hold_point(50, g, x0, 3.0))
    assert np.linalg.norm(pts[:, :2] - p50[:2], axis=1).min() >= 3.0 - 1e-9
    assert hold_point(0, g, x0, 1.5)[:2] == pytest.approx((x0, g.inlet_center_yz_m[0]))


def test_holds_beyond_fifty_keep_the_pitch_and_a_planted_layout_fails(maps):
    g, _ = maps["tunnel"]
    many = hold_points(1500, g, 5.0, 1.2)
    assert check_min_distance(many[:, :2], 1.2) == pytest.approx(1.2, abs=1e-9)
    too_tight = hold_points(50, g, 5.0, 1.5 - 1e-6)
    with pytest.raises(ValueError, match="less than the required 1.5 m"):
        check_min_distance(too_tight[:, :2], 1.5)
    with pytest.raises(ValueError, match="pitch must be > 0"):
        hold_points(3, g, 5.0, 0.0)
    with pytest.raises(ValueError, match="agent id must be >= 0"):
        hold_point(-1, g, 5.0, 1.5)


# ---- altitude: never below the tunnel's floor or the ground ----------------------------------------
def test_hold_altitude_clamps_to_floor_margin_and_minimum():
    assert hold_altitude_m(0.0, -1.5) == 0.0                              # the axis, well above the floor
    assert hold_altitude_m(-0.5, -1.5) == -0.5                            # axis exactly floor + margin
    assert hold_altitude_m(-0.6, -1.5) == pytest.approx(-0.5)             # just below: raised to it
    assert hold_altitude_m(0.0, -1.5, min_z_m=0.0) == 0.0                 # the minimum, equal
    assert hold_altitude_m(0.0, -1.5, min_z_m=0.01) == 0.01               # just above: raised
    assert hold_altitude_m(0.0, -1.5, min_z_m=-20.0) == 0.0               # a low minimum changes nothing
    assert hold_altitude_m(0.0, -0.2, floor_margin_m=0.0) == 0.0
    with pytest.raises(ValueError, match="non-finite"):
        hold_altitude_m(float("nan"), 0.0)


def test_hold_spots_never_below_the_floor_or_the_home_takeoff_height(maps):
    g, _ = maps["tunnel"]
    assert {p[2] for p in hold_points(50, g, 5.0, 1.5)} == {g.inlet_center_yz_m[1]}   # one plane: the axis
    # a flat duct whose axis is 0.3 m above its floor: raised to the floor + margin
    flat = dataclasses.replace(g, lo_m=(g.lo_m[0], g.lo_m[1], -0.3))
    pts = hold_points(50, flat, 5.0, 1.5)
    assert np.all(pts[:, 2] == pytest.approx(-0.3 + HOLD_FLOOR_MARGIN_M))
    # the ground: home 3 m below the axis, take-off 2.5 m -> no spot below z = -0.5 ...
    home_z, takeoff_m = -3.0, 2.5
    assert hold_point(7, g, 5.0, 1.5, min_z_m=home_z + takeoff_m)[2] == 0.0          # axis already higher
    # ... and with the home 1 m below the axis: 1.5 m above the axis
    assert hold_point(7, g, 5.0, 1.5, min_z_m=-1.0 + takeoff_m)[2] == pytest.approx(1.5)
    assert hold_point(7, g, 5.0, 1.5, min_z_m=1.5)[:2] == hold_point(7, g, 5.0, 1.5)[:2]  # only z moves


# ---- the exit route: over the holding vehicles, never between them ---------------------------------
def _route_clearance_m(path: list, others: np.ndarray) -> float:
    """Least 3-D distance from the polyline ``path`` to any point of ``others`` [m]."""
    best = math.inf
    for a, b in zip(path[:-1], path[1:]):
        s = np.linspace(0.0, 1.0, 200)[:, None]
        seg = np.asarray(a) + s * (np.asarray(b) - np.asarray(a))
        best = min(best, float(np.min(np.linalg.norm(seg[:, None, :] - others[None, :, :], axis=2))))
    return best


@pytest.mark.parametrize("name", ["tunnel", "default"])
def test_every_exit_route_keeps_a_pitch_from_the_other_fifty_spots(maps, name):
    g, _ = maps[name]
    cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=0)
    pitch, clearance = cfg.exit_spacing_m, cfg.exit_clearance_m
    spots = hold_points(50, g, g.x_outlet_m + clearance, pitch)
    rng = np.random.default_rng(0)
    worst = math.inf
    for k in range(50):
        # leaving anywhere across the outlet, just past it (one tick's flight: up to 0.5 m)
        pos = (g.x_outlet_m + rng.uniform(0.0, 0.5), *(np.asarray(g.inlet_center_yz_m) + rng.uniform(-0.7, 0.7, 2)))
        route = exit_waypoints(pos, tuple(spots[k]), g, clearance, pitch, cfg.keepout_margin_m)
        assert route[-1] == tuple(spots[k])
        assert route[-2][:2] == route[-1][:2]                     # the last leg is straight down
        assert route[0][2] == route[1][2] >= max(g.hi_m[2] + cfg.keepout_margin_m, spots[k][2] + OVERFLY_M)
        assert route[0][0] >= g.x_outlet_m + clearance - pitch   # still moving downstream while it climbs
        worst = min(worst, _route_clearance_m([pos] + route, np.delete(spots, k, axis=0)))
    assert worst >= min(pitch, OVERFLY_M) - 1e-9 and OVERFLY_M >= 1.5
    # the old straight route passed between the holding vehicles: id 5's flew within a pitch of id 0's spot
    straight = [(g.x_outlet_m, *g.inlet_center_yz_m), tuple(spots[5])]
    assert _route_clearance_m(straight, np.delete(spots, 5, axis=0)) < pitch


def test_an_exit_carried_past_the_climb_point_climbs_where_it_is(maps):
    g, _ = maps["tunnel"]
    spot = hold_point(3, g, g.x_outlet_m + 2.0, 1.5)
    at = g.x_outlet_m + 0.5                                   # the climb point: clearance - pitch
    assert exit_waypoints((at - 0.1, 0.0, 0.0), spot, g, 2.0, 1.5)[0][0] == at    # moves on to it
    assert exit_waypoints((at, 0.0, 0.0), spot, g, 2.0, 1.5)[0][0] == at          # equal
    assert exit_waypoints((at + 0.1, 0.0, 0.0), spot, g, 2.0, 1.5)[0][0] == at + 0.1   # never back
    # a spot far above the tunnel (a high home): transit OVERFLY_M above it
    high = (spot[0], spot[1], g.hi_m[2] + 5.0)
    assert exit_waypoints((at, 0.0, 0.0), high, g, 2.0, 1.5)[1][2] == pytest.approx(high[2] + OVERFLY_M)


# ---- the join arrives at its staging point when its window opens -----------------------------------
def test_speed_for_arrival_inverts_the_approach_time_within_its_bounds():
    legs = [3.0, 8.0, 1.5]
    t_at = {v: sum(approach_time_s(d, v, 0.3) for d in legs) for v in (0.3, 1.0, 2.0, 3.0)}
    assert speed_for_arrival(legs, t_at[2.0], 0.3, 0.3, 3.0) == pytest.approx(2.0, rel=1e-6)
    assert speed_for_arrival(legs, t_at[1.0], 0.3, 0.3, 3.0) == pytest.approx(1.0, rel=1e-6)
    assert speed_for_arrival(legs, t_at[3.0], 0.3, 0.3, 3.0) == 3.0           # equal: the cap
    assert speed_for_arrival(legs, t_at[3.0] * 0.99, 0.3, 0.3, 3.0) == 3.0    # late even at the cap
    assert speed_for_arrival(legs, 0.0, 0.3, 0.3, 3.0) == 3.0                 # due now
    assert speed_for_arrival(legs, -1.0, 0.3, 0.3, 3.0) == 3.0                # overdue
    assert speed_for_arrival(legs, t_at[0.3] * 1.01, 0.3, 0.3, 3.0) == 0.3    # early even crawling
    assert speed_for_arrival([], 5.0, 0.3, 0.3, 3.0) == 0.3                   # there already
    with pytest.raises(ValueError, match="lo <= hi"):
        speed_for_arrival(legs, 5.0, 0.3, 3.0, 2.0)


def _staging_times_s(maps, lag_s, gain):
    """A vehicle with a first-order lag ``lag_s`` and a steady ``gain`` (stock PX4 on SIH: 0.9 s, 0.84) joins from 8 m below and 8 m beside the inlet:
    when it reaches its staging point and when it crosses the inlet, each minus the time it was due
    at the staging point [s]."""
    g, sfield = maps["tunnel"]
    cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=3, entry_stagger_s=2.89, entry_slots=13,
                      lookahead_auto=False)
    nav = Navigator(cfg)
    nav.set_map(sfield)
    pos = np.array([g.x_inlet_m + 0.6, 8.0, -8.0])
    nav.plan_join(tuple(pos), None, wait_where_planned=True)
    vel, dt, last, at_s = np.zeros(3), 0.05, len(nav.waypoints) - 1, None
    k = 1.0 - math.exp(-dt / lag_s) if lag_s > 0 else 1.0
    for step in range(4000):
        t = step * dt
        cmd = nav.join_step(tuple(pos), sfield.cv_of(*pos), t)
        if nav.wp_index == last and at_s is None:
            at_s = t
        if cmd is None or (at_s is not None and pos[0] >= g.x_inlet_m):
            assert nav.staging_due_s is not None and at_s is not None
            return at_s - nav.staging_due_s, t - nav.staging_due_s
        vel += k * (gain * np.asarray(cmd) - vel)
        pos = pos + vel * dt
    raise AssertionError("never crossed the inlet")


@pytest.mark.parametrize("lag_s, gain", [(0.0, 1.0), (0.9, 0.84), (1.2, 0.75)])
def test_a_lagging_vehicle_reaches_its_staging_point_when_due_and_waits_there_if_early(maps, lag_s, gain):
    """The governor's reach: a vehicle with lag 1.5 s and gain 0.6 arrives 1.5 s late even so."""
    at_s, inlet = _staging_times_s(maps, lag_s, gain)
    assert -1.0 < at_s < 0.3, at_s       # on time: early by under a second (it then waits), never late
    assert 0.0 <= inlet < 5.0, inlet     # across the inlet only once due, at the inlet's crawl


def _cleared_join(maps, agent_id=3, name="tunnel", stagger_s=2.89, **cfg_kw):
    """A Navigator whose join (stagger ``stagger_s``, 13 windows) on map ``name`` has just been cleared at its
    wait point: (navigator, its staging point S, the time it is due there)."""
    g, sfield = maps[name]
    cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=agent_id, entry_stagger_s=stagger_s, entry_slots=13,
                      lookahead_auto=False, **cfg_kw)
    nav = Navigator(cfg)
    nav.set_map(sfield)
    wait = (g.x_inlet_m + 0.6, 8.0, -8.0)
    nav.plan_join(wait, None, wait_where_planned=True)
    t = next(k * 0.05 for k in range(20000)
             if entry_slot_open(k * 0.05 + nav.entry_lead_s, agent_id, stagger_s, 13))
    nav.join_step(wait, -1, t)
    assert nav.entry_cleared and nav.staging_due_s is not None
    for wp in nav.waypoints[nav.wait_index + 1:-2]:   # on its way, in time, up to the staging point S
        nav.join_step(wp, -1, t)
    assert nav.wp_index == len(nav.waypoints) - 2 and not nav.entry_on_time
    return nav, nav.waypoints[-2], nav.staging_due_s


def test_a_join_sure_to_be_late_at_its_staging_point_gives_its_window_up_on_its_way(maps):
    """Decided only at the staging point S, a join late by about one window turned back just as the next
    vehicle arrived at its own.  On its way, once even the rest of its route flown straight at the
    governor's top speed would bring it to S more than the tolerance late, it turns back where it is."""
    g, sfield = maps["tunnel"]

    def half_way():
        cfg = AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=3, entry_stagger_s=2.89, entry_slots=13,
                          lookahead_auto=False)
        nav = Navigator(cfg)
        nav.set_map(sfield)
        wait = (g.x_inlet_m + 0.6, 8.0, -8.0)
        nav.plan_join(wait, None, wait_where_planned=True)
        t = next(k * 0.05 for k in range(20000) if entry_slot_open(k * 0.05 + nav.entry_lead_s, 3, 2.89, 13))
        nav.join_step(wait, -1, t)
        assert nav.entry_cleared and nav.staging_due_s is not None and nav.wp_index == nav.wait_index + 1
        nxt = nav.waypoints[nav.wp_index]
        here = tuple(a + 0.5 * (b - a) for a, b in zip(wait, nxt))
        rest = [here] + nav.waypoints[nav.wp_index:-1]
        rest_m = sum(distance(a, b) for a, b in zip(rest, rest[1:]))
        top = min(cfg.max_speed_m_s, 1.5 * cfg.join_speed_m_s)
        sure_late_at = nav.staging_due_s + ENTRY_TIMING_TOLERANCE_S - rest_m / top  # straight on at top speed
        return nav, here, rest, top, sure_late_at, nav.staging_due_s

    nav, here, _, _, sure_late_at, _ = half_way()
    planned = list(nav.waypoints)
    assert nav.join_step(here, -1, sure_late_at - 1e-6) is not None         # just in time at best: on
    assert nav.waypoints == planned and nav.late_entries == 0 and nav.staging_due_s is not None
    nav, *_, sure_late_at, _ = half_way()
    assert nav.join_step(here, -1, sure_late_at) is not None                 # late by exactly the tolerance: on
    assert nav.waypoints == planned and nav.late_entries == 0
    nav, here, rest, top, sure_late_at, due = half_way()
    t = sure_late_at + 1e-3
    vel = nav.join_step(here, -1, t)                                         # just later: back from here
    assert nav.late_entries == 1 and not nav.entry_cleared and nav.staging_due_s is None
    # back along its own route to its wait point, not on to S
    assert nav.waypoints[nav.wait_index] == planned[0] and nav.waypoints[-1] == planned[-1]
    assert sum(v * (b - a) for v, a, b in zip(vel, here, planned[0])) > 0
    # it learns its lateness at top speed as the lead counts the legs (slowing at each corner): more than sure
    model_s = sum(approach_time_s(distance(a, b), top, nav.cfg.waypoint_radius_m) for a, b in zip(rest, rest[1:]))
    assert nav.lead_learnt_s == pytest.approx(t + model_s - due, abs=1e-9)
    assert nav.lead_learnt_s > ENTRY_TIMING_TOLERANCE_S


def test_a_join_sure_to_be_late_just_short_of_its_staging_point_learns_at_least_its_sure_lateness(maps):
    """Just outside the waypoint radius of S, the leg's modelled time (``approach_time_s``, which stops at
    the radius) is shorter than the straight flight: the lateness learnt and said is still the sure one."""
    nav, s_pt, due = _cleared_join(maps)
    before = nav.waypoints[-3]
    r = nav.cfg.waypoint_radius_m + 0.01
    leg_m = distance(before, s_pt)
    here = tuple(b + r * (a - b) / leg_m for a, b in zip(before, s_pt))
    t = due + ENTRY_TIMING_TOLERANCE_S + 0.05
    sure_s = t + r / nav._top_join_speed_m_s() - due
    assert approach_time_s(r, nav._top_join_speed_m_s(), nav.cfg.waypoint_radius_m) < r / nav._top_join_speed_m_s()
    nav.join_step(here, -1, t)
    assert nav.late_entries == 1 and nav.lead_learnt_s == pytest.approx(sure_s, abs=1e-9)


def test_a_join_at_its_staging_point_within_the_tolerance_enters_and_one_later_does_not(maps):
    """The entry windows keep consecutive entries d_min apart only if each vehicle starts across within
    ENTRY_TIMING_TOLERANCE_S of its due time (``separation_budget``)."""
    nav, s_pt, due = _cleared_join(maps)
    planned = list(nav.waypoints)
    nav.join_step(s_pt, -1, due + ENTRY_TIMING_TOLERANCE_S)              # late by exactly the tolerance: on
    assert nav.entry_on_time and nav.waypoints == planned and nav.late_entries == 0
    nav.join_step(s_pt, -1, due + ENTRY_TIMING_TOLERANCE_S + 1.0)      # once on time, on its way until the crossing's due
    assert nav.waypoints == planned and nav.late_entries == 0
    nav, s_pt, due = _cleared_join(maps)
    lead = nav.entry_lead_s
    vel = nav.join_step(s_pt, -1, due + ENTRY_TIMING_TOLERANCE_S + 1e-6)  # just later: back to the wait point
    assert nav.late_entries == 1 and not nav.entry_cleared and nav.staging_due_s is None
    # ... and its joins leave earlier by the delay (the lead from the same wait point, plus what it learnt)
    assert nav.lead_learnt_s == pytest.approx(ENTRY_TIMING_TOLERANCE_S + 1e-6, abs=1e-9)
    assert nav.entry_lead_s == pytest.approx(lead + nav.lead_learnt_s, abs=1e-9)
    # back by its own route to its wait point again, its leg in the staging plane (where the routes meet)
    # flown OVERFLY_M upstream of it: straight upstream first (routes.give_up_waypoints)
    xb = s_pt[0] - OVERFLY_M
    assert nav.waypoints[:nav.wait_index + 1] == [(xb, *s_pt[1:]), (xb, *planned[1][1:]), planned[0]]
    assert nav.wp_index == 0 and vel[0] < 0 and vel[1] == vel[2] == 0.0
    assert nav.waypoints[-1] == planned[-1]                                   # the same entry point


@pytest.mark.parametrize("early_s, learnt_after", [(ENTRY_TIMING_TOLERANCE_S, 3.0),
                                                   (ENTRY_TIMING_TOLERANCE_S + 1e-6, 3.0 - ENTRY_TIMING_TOLERANCE_S - 1e-6),
                                                   (2.5, 0.5), (3.0, 0.0), (7.0, 0.0)])
def test_an_arrival_more_than_the_tolerance_early_takes_its_earliness_off_the_learnt_lead(maps, early_s, learnt_after):
    nav, s_pt, due = _cleared_join(maps)
    nav.lead_learnt_s = 3.0
    nav.join_step(s_pt, -1, due - early_s)
    assert nav.entry_on_time and nav.late_entries == 0                   # early: it enters (after waiting)
    assert nav.lead_learnt_s == pytest.approx(learnt_after, abs=1e-9)


@pytest.mark.parametrize("to_plane, lag, cap, want", [
    (0.5, 0.0, 2.0, 0.44),                 # at the least braking distance: the crawl
    (0.5 + 1e-9, 0.0, 2.0, 0.44 + 1e-9),   # just before it: the approach on top of the crawl
    (0.3, 0.0, 2.0, 0.44),                 # inside it, and past the plane: the crawl
    (-0.2, 0.0, 2.0, 0.44),
    (1.5, 0.0, 2.0, 1.44),                 # at the staging point (1.5 m out): 1 m/s on top of the crawl
    (1.5, 0.0, 1.0, 1.0),                  # within the governor's cap
    (1.5, 0.0, 0.3, 0.44),                 # a cap below the crawl: the crawl
    (1.5, 0.9, 2.0, 0.44 + 1.5 - 2 * 0.9 * 0.44),  # a stock PX4's lag: brakes two lags at the crawl out
    (2 * 0.9 * 0.44, 0.9, 2.0, 0.44),
])
def test_the_final_leg_approaches_the_inlet_plane_and_crosses_it_at_the_crawl(to_plane, lag, cap, want):
    assert final_leg_speed_m_s(to_plane, 0.44, lag, cap) == pytest.approx(want, abs=1e-12)


CRAWL, BRAKE = 0.44, 0.5   # lag 0: the least braking distance


@pytest.mark.parametrize("to_plane, time_left, want", [
    (1.5, 1.5 / CRAWL, CRAWL),                                   # on time at S: the crawl all the way
    (1.5, 1.5 / CRAWL - 1.0, 1.0 / (1.0 / CRAWL - 1.0)),         # 1 s late: faster, to the brake point in time
    (1.5, BRAKE / CRAWL + 1e-9, 1.44),                           # no time left before the brake point: the
    (1.5, BRAKE / CRAWL, 1.44),                                  # approach (faster than 1.5 x the crawl there),
    (1.5, -1.0, 1.44),                                           # also past the aim
    (1.5, 1.5 / CRAWL + 1.0, 1.0 / (1.0 / CRAWL + 1.0)),         # 1 s early: slower than the crawl ...
    (1.5, BRAKE / CRAWL + 1.0 / (0.5 * CRAWL), 0.5 * CRAWL),     # ... down to half of it
    (1.5, 100.0, 0.5 * CRAWL),
    (BRAKE + 0.01, (BRAKE + 0.01) / CRAWL, CRAWL),               # just before the brake point, on time
    (BRAKE, BRAKE / CRAWL, CRAWL),                               # at it, on time: the crawl
    (BRAKE, BRAKE / CRAWL + 0.5, BRAKE / (BRAKE / CRAWL + 0.5)), # in the brake zone, early: slower
    (0.3, 0.3 / CRAWL, CRAWL),                                   # on time in the brake zone: the crawl
    (0.3, 0.3 / (1.5 * CRAWL) + 1e-9, 0.3 / (0.3 / (1.5 * CRAWL) + 1e-9)),  # late: faster ...
    (0.3, 0.3 / (1.5 * CRAWL), 1.5 * CRAWL),                     # ... up to 1.5 x the crawl
    (0.3, 0.1, 1.5 * CRAWL),
    (0.3, 0.0, 1.5 * CRAWL),
    (0.0, 5.0, CRAWL),                                           # on the plane and past it: the crawl
    (-0.2, 5.0, CRAWL),
])
def test_a_timed_final_leg_reaches_its_brake_point_when_its_crossing_is_due(to_plane, time_left, want):
    assert final_leg_speed_m_s(to_plane, CRAWL, 0.0, 2.0, time_left_s=time_left) == pytest.approx(want, abs=1e-9)


def test_a_timed_final_leg_reckons_from_where_the_vehicles_lag_takes_it():
    lag = 0.6
    for vx, time_left in ((1.0, 4.0), (0.0, 4.0), (1.0, 0.5), (-0.2, 3.0)):
        want = final_leg_speed_m_s(1.5 - vx * lag, CRAWL, lag, 2.0, time_left_s=time_left - lag)
        assert final_leg_speed_m_s(1.5, CRAWL, lag, 2.0, time_left_s=time_left, vx_m_s=vx) == want
    assert final_leg_speed_m_s(1.5, CRAWL, lag, 2.0, vx_m_s=1.0) == final_leg_speed_m_s(1.5, CRAWL, lag, 2.0)


def _crossing_s(maps, lag_s, arrival_m_s, gain=1.0, dt=0.05):
    """A first-order-lag vehicle (lag ``lag_s``, its look-ahead; steady gain ``gain``) reaching its staging
    point when due at
    ``arrival_m_s`` towards its entry point, on the shipped map's admission budget: when it crosses the
    inlet plane, from the crossing its timed final leg aims at (the crawl from S when due)."""
    g, sfield = maps["default"]
    nav, s_pt, due = _cleared_join(maps, name="default", stagger_s=4.23, lookahead_s=lag_s)
    heading = np.subtract(nav.waypoints[-1], s_pt) / distance(nav.waypoints[-1], s_pt)
    pos, vel = np.array(s_pt, float), arrival_m_s * heading
    aim = due + distance(nav.waypoints[-1], s_pt) / nav._crawl_m_s()
    k = 1.0 - math.exp(-dt / lag_s)
    for step in range(2000):
        t = due + step * dt
        cmd = nav.join_step(tuple(pos), sfield.cv_of(*pos), t, tuple(vel))
        if cmd is None:
            assert nav.crossing_due_s == pytest.approx(aim + JOIN_LEG_ALLOWANCE_S)
            return t - aim
        vel += k * (gain * np.asarray(cmd) - vel)
        pos = pos + vel * dt
    raise AssertionError("never crossed")


def test_timed_final_legs_cross_within_half_a_second_of_their_aim_whatever_the_lag_and_arrival_speed(maps):
    """Stock PX4 looks ahead 0.5-0.9 s and reaches its staging point at rest (the first pass, after waiting)
    or at speed (the laps after).  Untimed, the same vehicles crossed 1.0-2.2 s before this aim, a spread
    of 1.2 s; over real flights 3.8 s, in windows of 4.23 s."""
    late = {(lag, v0, g): _crossing_s(maps, lag, v0, g) for lag in (0.3, 0.6, 0.9) for v0 in (0.0, 1.0)
            for g in (0.7, 1.0)}
    assert all(-0.5 <= s <= 0.5 for s in late.values()), late
    assert max(late.values()) - min(late.values()) <= 1.0, late


def test_a_join_on_its_final_leg_flies_final_leg_speed_along_x_and_closes_on_its_entry_point_sideways(maps):
    nav, s_pt, due = _cleared_join(maps)
    entry = nav.waypoints[-1]
    crawl, lag = nav._crawl_m_s(), nav.lookahead_s()
    for frac in (0.0, 0.5, 0.95):  # at S, half way, just short of the entry point
        pos = tuple(a + frac * (b - a) for a, b in zip(s_pt, entry))
        vel = nav.join_step(pos, -1, due)
        aim_s = nav.crossing_due_s - JOIN_LEG_ALLOWANCE_S
        want = final_leg_speed_m_s(nav.geom.x_inlet_m - pos[0], crawl, lag, nav._join_speed(pos, due),
                                   time_left_s=aim_s - due)
        assert vel[0] == pytest.approx(want, abs=1e-12) and vel[1:] == pytest.approx((0.0, 0.0), abs=1e-9)
    off = (entry[0] - 0.3, entry[1] + 0.4, entry[2] - 0.2)  # off the line: sideways back to it
    vel0 = nav.join_step(off, -1, aim_s)                    # its crossing due: the crawl
    assert vel0[0] == pytest.approx(crawl) and vel0[1] < 0 < vel0[2]
    nav.tracker.bias_m_s = (0.1, -0.05, 0.0)  # the velocity estimate's bias comes off both
    vel = nav.join_step(off, -1, aim_s)
    assert vel[0] == pytest.approx(crawl - 0.1) and vel[1] == pytest.approx(vel0[1] + 0.05)


def test_a_join_not_across_the_inlet_by_its_crossing_due_time_gives_its_window_up(maps):
    """Held back on its final leg (the net behind a jam at the inlet), a vehicle on time at its staging
    point would still cross beside the next one: past its crossing due time plus the tolerance it turns
    back and learns the delay as its final leg's lead; once across the inlet plane it is in the flow
    whatever the time."""
    nav, s_pt, due = _cleared_join(maps)
    nav.join_step(s_pt, -1, due)                                        # on time at the staging point
    entry = nav.waypoints[-1]
    assert nav.entry_on_time
    assert nav.crossing_due_s == pytest.approx(due + distance(s_pt, entry) / nav._crawl_m_s() + JOIN_LEG_ALLOWANCE_S)
    assert nav._crawl_m_s() > 0.3                                       # the flow's own speed at the inlet
    planned = list(nav.waypoints)
    mid = tuple((a + b) / 2 for a, b in zip(s_pt, entry))
    late = nav.crossing_due_s + ENTRY_TIMING_TOLERANCE_S
    assert nav.join_step(mid, -1, late)[0] > 0 and nav.waypoints == planned  # exactly the tolerance: on
    assert nav.join_step(entry, 0, late + 5.0) is None                  # across: in the flow
    nav, s_pt, due = _cleared_join(maps)
    nav.join_step(s_pt, -1, due)
    vel = nav.join_step(mid, -1, nav.crossing_due_s + ENTRY_TIMING_TOLERANCE_S + 1e-6)
    assert nav.late_entries == 1 and not nav.entry_cleared and nav.crossing_due_s is None
    assert nav.lead_learnt_s == 0.0                                     # not its way to the staging point...
    assert nav.leg_lead_s == pytest.approx(ENTRY_TIMING_TOLERANCE_S + 1e-6, abs=1e-9)   # ... but its final leg
    # straight upstream from its final leg to OVERFLY_M before the staging plane, then by its route's corner
    # (flown that far upstream) to its wait point
    xb = s_pt[0] - OVERFLY_M
    assert nav.waypoints[:nav.wait_index + 1] == [(xb, *mid[1:]), (xb, *planned[1][1:]), planned[0]]
    assert nav.wp_index == 0 and vel[0] < 0 and vel[1] == vel[2] == 0.0


@pytest.mark.parametrize("early_s, leg_lead_after", [(ENTRY_TIMING_TOLERANCE_S, 3.0),
                                                     (ENTRY_TIMING_TOLERANCE_S + 1e-6, 3.0 - ENTRY_TIMING_TOLERANCE_S - 1e-6),
                                                     (5.0, 0.0)])
def test_a_crossing_more_than_the_tolerance_early_takes_its_earliness_off_the_leg_lead(maps, early_s, leg_lead_after):
    nav, s_pt, due = _cleared_join(maps)
    nav.leg_lead_s = 3.0
    nav.join_step(s_pt, -1, due - 3.0)                                  # starts its final leg 3 s before due
    assert nav.entry_on_time and nav.lead_learnt_s == 0.0
    assert nav.join_step(nav.waypoints[-1], 0, nav.crossing_due_s - early_s) is None
    assert nav.leg_lead_s == pytest.approx(leg_lead_after, abs=1e-9)


def test_a_join_held_up_on_its_way_waits_for_its_next_window_instead_of_entering_late(maps):
    """As the safety net held a real PX4 for 4 s: stopped for 6 s on the way to its staging point, the
    vehicle goes back to its wait point and crosses the inlet in a later window, on time."""
    g, sfield = maps["tunnel"]
    nav, s_pt, first_due = _cleared_join(maps)
    pos, vel, dt = np.array(nav.waypoints[nav.wait_index]), np.zeros(3), 0.05
    t0 = first_due - nav.entry_lead_s
    k = 1.0 - math.exp(-dt / 0.9)
    turned_back_at = None
    for step in range(1, 6000):
        t = t0 + step * dt
        cmd = nav.join_step(tuple(pos), sfield.cv_of(*pos), t)
        if nav.late_entries and turned_back_at is None:
            turned_back_at = tuple(pos)
        if cmd is None:
            break
        if t0 + 2.0 <= t < t0 + 8.0:   # held on the way
            cmd = (0.0, 0.0, 0.0)
        vel += k * (0.84 * np.asarray(cmd) - vel)
        pos = pos + vel * dt
    else:
        raise AssertionError(("never entered", nav.late_entries, nav.lead_learnt_s))
    cycle = 2.89 * 13
    assert nav.late_entries == 1
    assert distance(turned_back_at, s_pt) > 2.0              # on its way, sure to be late: not at its staging point
    assert t - first_due > cycle - 2.89                      # a later window (the next cycle's), not the first
    assert nav.entry_on_time                                 # at its staging point in time, this once


def test_a_vehicle_too_slow_for_its_lead_learns_it_and_enters_on_time_in_a_later_window(maps):
    """Lag 2 s and gain 0.5 (beyond the arrival governor's reach): late, it gives the window up and learns
    the delay, and within three more windows it reaches its staging point in time and crosses the inlet
    when due."""
    g, sfield = maps["tunnel"]
    nav, _, first_due = _cleared_join(maps)
    pos, vel, dt = np.array(nav.waypoints[nav.wait_index]), np.zeros(3), 0.05
    t0 = first_due - nav.entry_lead_s
    k = 1.0 - math.exp(-dt / 2.0)
    for step in range(1, 8000):
        t = t0 + step * dt
        cmd = nav.join_step(tuple(pos), sfield.cv_of(*pos), t)
        if cmd is None:
            break
        vel += k * (0.5 * np.asarray(cmd) - vel)
        pos = pos + vel * dt
    else:
        raise AssertionError(("never entered", nav.late_entries, nav.lead_learnt_s))
    # without the learnt leads it was late at every window (paced to the due time, it flew at half the pace):
    # late at its staging point, it learns the way there; late across the inlet, its final leg
    assert 1 <= nav.late_entries <= 3 and nav.entry_on_time and 1.0 < nav.lead_learnt_s < 10.0, (
        nav.late_entries, nav.lead_learnt_s, t - first_due)
    assert 0.0 < nav.leg_lead_s < 10.0 and t - nav.crossing_due_s <= ENTRY_TIMING_TOLERANCE_S, (nav.leg_lead_s, t)


def test_the_exit_holds_only_on_its_spot_and_once_slow(maps):
    g, sfield = maps["tunnel"]
    nav = Navigator(AgentConfig(mavlink_url="udpin:0.0.0.0:14540", agent_id=4))
    nav.set_map(sfield)
    nav.plan_exit((g.x_outlet_m + 0.1, 0.0, 0.0), None)
    spot, r = nav.target, nav.cfg.waypoint_radius_m
    assert nav.exit_arrived(spot, (0.0, 0.0, 0.0)) and nav.exit_arrived(spot, None)
    assert nav.exit_arrived(spot, (0.0, 0.0, -(EXIT_SETTLE_SPEED_M_S - 1e-6)))      # just slower
    assert not nav.exit_arrived(spot, (0.0, 0.0, -EXIT_SETTLE_SPEED_M_S))           # equal: still settling
    near = (spot[0], spot[1], spot[2] + r - 1e-6)
    assert nav.exit_arrived(near, (0.0, 0.0, 0.0))                                  # just inside the radius
    assert not nav.exit_arrived((spot[0], spot[1], spot[2] + r), (0.0, 0.0, 0.0))   # on it: not yet
    # the route: climb, across above the spot, down onto it
    assert [p[:2] for p in nav.exit_route[1:]] == [spot[:2], spot[:2]] and nav.exit_route[-1] == spot


def test_an_agent_says_where_its_entry_windows_come_from_and_warns_beyond_the_budget():
    import logging

    from fisc_agent.map.separation import Separation

    sep = Separation(admission_period_s=4.23, max_in_tunnel=13)
    budget = EntrySchedule(4.23, 13, ScheduleSource.MAP)
    (level, said), = schedule_messages(budget, sep, 12)                       # the last window of the budget
    assert level == logging.INFO and "one window of 4.23 s per vehicle, 13 per cycle" in said
    assert f"at d_min {sep.d_min_m:.2f} m" in said
    (_, _), (level, said) = schedule_messages(budget, sep, 13)                # one beyond it: shares id 0's
    assert level == logging.WARNING and "agent id 13 is beyond the map's 13 entry windows" in said
    assert "window of id 0" in said
    (level, said), = schedule_messages(EntrySchedule(0.0, 13, ScheduleSource.NONE), Separation(), 3)
    assert level == logging.WARNING and "no admission budget" in said
    assert schedule_messages(EntrySchedule(2.0, 13, ScheduleSource.GIVEN), sep, 3) == []
