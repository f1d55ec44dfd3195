"""Control core: the scalar fast path agrees with lookup.CommandField; clamps; entry and join plans."""

import dataclasses
import math

import numpy as np
import pytest

from fisc_agent.flight.control import (MapGeometry, ScalarField, check_map, clamp_speed, clamp_velocity, entry_point,
                                goto_velocity, max_command_speed)
from fisc_agent.flight.routes import OVERFLY_M, give_up_waypoints, join_waypoints
from fisc_agent.map.hashing import slot_hash, slot_hash_int
from fisc_agent.map.lookup import CommandField, return_command
from fisc_agent.map.codec import MapError


@pytest.fixture(scope="module")
def field(tunnel_map):
    return CommandField.from_map(tunnel_map)


@pytest.fixture(scope="module")
def sfield(field):
    return ScalarField(field)


def test_slot_hash_int_equals_vectorised():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 2**32, size=500)
    j = rng.integers(0, 5000, size=500)
    expect = slot_hash(a, j)
    assert [slot_hash_int(int(x), int(y)) for x, y in zip(a, j)] == expect.tolist()


@pytest.mark.parametrize("mode", ["mean", "slot", "interpolated"])
def test_scalar_fast_path_agrees_with_lookup(field, sfield, mode):
    rng = np.random.default_rng(42)
    lo = field.origin_m - 0.7
    hi = field.origin_m + np.array(field.grid_cv.shape) * field.cell_size_m + 0.7
    pts = rng.uniform(lo, hi, size=(1500, 3))
    # include points exactly on cell faces (half-open cells)
    pts[:40] = field.origin_m + rng.integers(0, 6, size=(40, 3)) * field.cell_size_m
    ids = rng.integers(0, 1000, size=len(pts))
    cv = field.cv_of(pts)
    expect = field.command(pts, ids, mode)
    for p, i, c, e in zip(pts, ids, cv, expect):
        assert sfield.cv_of(*p) == c
        got = sfield.command(*p, int(i), mode)
        if c < 0:
            assert got is None
        else:
            np.testing.assert_allclose(got, e, rtol=1e-12, atol=1e-12)
    assert (cv >= 0).sum() > 200 and (cv < 0).sum() > 200


def test_unknown_mode_rejected(sfield):
    with pytest.raises(ValueError, match="unknown command mode"):
        sfield.command(0.25, 0.25, 0.25, 0, "bogus")


def test_nearest_cv_uses_neighbourhood_then_global(field, sfield):
    j = sfield.nearest_cv(-0.3, 0.1, 0.1)
    assert j == int(field.nearest_cv_within(np.array([[-0.3, 0.1, 0.1]]))[0]) and j >= 0
    far = sfield.nearest_cv(-20.0, 0.2, 0.2)  # nothing within 2 cells: global nearest centre
    d = np.linalg.norm(field.centers_m - [-20.0, 0.2, 0.2], axis=1)
    assert far == int(np.argmin(d))


def test_clamp_speed_bounds_and_rejects_nonfinite():
    assert clamp_speed((3.0, 4.0, 0.0), 2.5) == pytest.approx((1.5, 2.0, 0.0))
    assert clamp_speed((1.0, 0.0, 0.0), 2.5) == (1.0, 0.0, 0.0)
    assert clamp_speed((float("nan"), 0.0, 0.0), 2.5) == (0.0, 0.0, 0.0)
    assert clamp_speed((float("inf"), 0.0, 0.0), 2.5) == (0.0, 0.0, 0.0)


def test_clamp_velocity_speed_and_acceleration():
    dt, vmax, amax = 0.05, 3.0, 2.0
    v = clamp_velocity((10.0, 0.0, 0.0), (0.0, 0.0, 0.0), dt, vmax, amax)
    assert v == pytest.approx((amax * dt, 0.0, 0.0))
    rng = np.random.default_rng(3)
    prev = (0.0, 0.0, 0.0)
    for _ in range(500):
        want = tuple(rng.normal(size=3) * 6)
        v = clamp_velocity(want, prev, dt, vmax, amax)
        assert math.hypot(*v) <= vmax + 1e-9
        assert math.dist(v, prev) / dt <= amax + 1e-9
        prev = v


def test_goto_velocity_caps_and_points_at_target():
    v = goto_velocity((0.0, 0.0, 0.0), (10.0, 0.0, 0.0), 2.0)
    assert v == pytest.approx((2.0, 0.0, 0.0))
    v = goto_velocity((0.0, 0.0, 0.0), (0.1, 0.0, 0.0), 2.0)
    assert v == pytest.approx((0.1, 0.0, 0.0))


def test_map_geometry(field):
    g = MapGeometry.from_field(field)
    assert g.x_inlet_m == pytest.approx(0.0) and g.x_outlet_m == pytest.approx(3.0)
    assert g.inlet_center_yz_m == pytest.approx((0.0, 0.0), abs=1e-12)
    assert 0.8 < g.inlet_radius_m <= 1.1


def test_entry_points_deterministic_distinct_and_inside_first_slice(field, sfield):
    g = MapGeometry.from_field(field)
    pts = [entry_point(i, g, sfield) for i in range(16)]
    assert pts == [entry_point(i, g, sfield) for i in range(16)]
    assert len({(round(p[1], 6), round(p[2], 6)) for p in pts}) >= 12
    for p in pts:
        c = sfield.cv_of(*p)
        assert c >= 0 and field.centers_m[c][0] == pytest.approx(0.25)


def test_entry_points_over_the_whole_inlet_are_area_uniform_over_its_cvs():
    # radius fraction 1: spiral points outside the staircase are skipped, not snapped onto a CV
    # centre, so the entries spread over every inlet CV about in proportion to its area
    from fisc_ground.maps.build import build_default_map

    f = CommandField.from_map(build_default_map())
    g, sf = MapGeometry.from_field(f), ScalarField(f)
    inlet = np.flatnonzero(f.centers_m[:, 0] == f.centers_m[:, 0].min())
    pts = np.array([entry_point(i, g, sf, 1.0, n_points=8 * inlet.size) for i in range(8 * inlet.size)])
    cv = np.array([sf.cv_of(*p) for p in pts])
    assert np.all(np.isin(cv, inlet))
    counts = np.bincount(np.searchsorted(inlet, cv), minlength=inlet.size)
    assert counts.min() >= 4 and counts.max() <= 12           # 8 per CV on average
    assert not np.any(np.all(np.isclose(pts[:, None, 1:], f.centers_m[None, inlet, 1:]), axis=2))
    # the default 0.6 keeps to the inner disc, clear of a real duct's wall
    inner = np.array([entry_point(i, g, sf) for i in range(32)])
    r = np.hypot(inner[:, 1] - g.inlet_center_yz_m[0], inner[:, 2] - g.inlet_center_yz_m[1])
    assert r.max() <= 0.6 * g.inlet_radius_m + 1e-9 < np.abs(pts[:, 1:]).max()


def _segment_enters_box(a, b, g, margin):
    for s in np.linspace(0.0, 1.0, 200):
        p = tuple(np.asarray(a) + s * (np.asarray(b) - np.asarray(a)))
        if g.in_box(p, margin - 1e-6) and p[0] > g.x_inlet_m:
            return True
    return False


@pytest.mark.parametrize("start", [(0.0, 0.0, -2.0), (1.5, 0.0, -2.0), (4.0, 0.0, 0.0), (2.0, 0.0, 0.2),
                                   (1.0, 3.0, 0.0), (-5.0, 1.0, 4.0)])
def test_join_waypoints_stay_outside_the_tunnel_until_the_inlet(field, sfield, start):
    g = MapGeometry.from_field(field)
    entry = entry_point(5, g, sfield)
    wps = join_waypoints(start, entry, g, staging_m=1.5, margin_m=0.5)
    assert wps[-1] == entry and wps[-2] == (g.x_inlet_m - 1.5, entry[1], entry[2])
    path = [start] + wps[:-1]
    starts_inside = g.in_box(start, 0.5)
    for a, b in zip(path[:-1], path[1:]):
        if starts_inside and a == start:
            continue  # leaving the box is the first move
        assert not _segment_enters_box(a, b, g, 0.5), (a, b)


def _dense(path, step_m=0.02):
    """Points every ``step_m`` along a polyline, as an (n, 3) array."""
    out = []
    for a, b in zip(path[:-1], path[1:]):
        a, b = np.asarray(a, float), np.asarray(b, float)
        s = np.linspace(0.0, 1.0, max(2, int(np.linalg.norm(b - a) / step_m) + 1))[:, None]
        out.append(a + s * (b - a))
    return np.vstack(out)


def _length_near(path, others, within_m, step_m=0.02):
    """Length of ``path`` [m] closer than ``within_m`` to any of the polylines ``others``."""
    from scipy.spatial import cKDTree

    pts = _dense(path, step_m)
    tree = cKDTree(np.vstack([_dense(other, step_m) for other in others]))
    return float(np.sum(tree.query(pts)[0] < within_m)) * step_m


def test_a_give_up_in_the_staging_plane_backs_off_and_does_not_fly_down_the_next_joins_leg(field, sfield):
    """The loop's fleet (PX4 SITL launches it so): eight vehicles waiting 3 m apart in a row under the inlet.
    Their joins' legs in the staging plane converge on the inlet, nearly parallel.  Flown back the way it came,
    a join giving its window up on that leg ran along the next one's for metres (eight stock PX4: 0.48 m by
    SIH's ground truth, head on); backing off upstream first, its way back comes within d_min of another
    join's leg in the plane only where it leaves the plane, and where it crosses the plane at its own corner
    (as every join of its own does)."""
    g = MapGeometry.from_field(field)
    d_min, staging = 0.924, 1.5
    waits = [(g.x_inlet_m, 3.0 * k, g.lo_m[2] - 6.0) for k in range(8)]
    routes = [[w] + join_waypoints(w, entry_point(k, g, sfield), g, staging, 1.0) for k, w in enumerate(waits)]
    assert all(len(r) == 4 for r in routes)                         # wait, corner, S, entry
    worst_back, worst_new = 0.0, 0.0
    for k, (wait, corner, s_pt, _) in enumerate(routes):
        legs = [r[1:3] for j, r in enumerate(routes) if j != k]     # the others' legs in the staging plane
        for frac in (0.3, 0.6, 0.9, 1.0):
            pos = tuple(a + frac * (b - a) for a, b in zip(corner, s_pt))
            passed = [corner, s_pt] if frac == 1.0 else [corner]
            back = [pos] + passed[::-1] + [wait]
            new = [pos] + give_up_waypoints(pos, passed, wait, g, staging)
            worst_back = max(worst_back, _length_near(back, legs, d_min))
            # its joins fly to their corner (``own``); coming back it crosses the plane there, as far again
            own = _length_near([corner, wait], legs, d_min)
            worst_new = max(worst_new, _length_near(new, legs, d_min) - 2 * own)
            assert new[-1] == wait and new[1][0] == corner[0] - OVERFLY_M
    assert worst_back > 10.0 and worst_new <= d_min + 0.05, (worst_back, worst_new)


def test_give_up_waypoints_at_the_boundaries(field):
    g = MapGeometry.from_field(field)
    xs = g.x_inlet_m - 1.5
    xb = xs - OVERFLY_M
    wait = (g.x_inlet_m + 0.6, 8.0, -8.0)
    low = (wait[0], wait[1], g.lo_m[2] - 1.0)          # a descent under the tunnel before the plane
    corner, s_pt = (xs, 8.0, -8.0), (xs, 0.2, 0.1)
    # not yet in the staging plane: back the way it came, as it came
    assert give_up_waypoints((xs + 0.5, 8.0, -8.0), [], wait, g) == [wait]
    assert give_up_waypoints((xs + 0.5, 8.0, -8.0), [low], wait, g) == [low, wait]
    # at its corner in the plane: straight upstream, then to the wait point
    assert give_up_waypoints(corner, [corner], wait, g) == [(xb, 8.0, -8.0), wait]
    # on the leg in the plane and at S: the leg flown OVERFLY_M upstream
    mid = (xs, 4.0, -4.0)
    assert give_up_waypoints(mid, [corner], wait, g) == [(xb, 4.0, -4.0), (xb, 8.0, -8.0), wait]
    assert give_up_waypoints(s_pt, [corner, s_pt], wait, g) == [(xb, 0.2, 0.1), (xb, 8.0, -8.0), wait]
    # the descent before the plane is kept as it was flown
    route = give_up_waypoints(s_pt, [(wait[0], 8.0, low[2]), (xs, 8.0, low[2]), s_pt], wait, g)
    assert route == [(xb, 0.2, 0.1), (xb, 8.0, low[2]), (wait[0], 8.0, low[2]), wait]
    # where it is: on the final leg up to the inlet plane (equal included) it backs off; at the back-off
    # plane or upstream of it, it does not move there first
    for x, moved in ((g.x_inlet_m, True), (g.x_inlet_m - 0.1, True), (xb + 1e-6, True), (xb, False),
                     (xb - 0.1, False)):
        route = give_up_waypoints((x, 0.2, 0.1), [corner, s_pt], wait, g)
        assert route[0] == (xb, 0.2, 0.1) and len(route) == 3, x        # the same first point either way ...
        assert give_up_waypoints((x, 0.3, 0.1), [corner, s_pt], wait, g)[0] == ((xb, 0.3, 0.1) if moved
                                                                             else (xb, 0.2, 0.1)), x
    # past the inlet plane (in the flow, never a give-up): not moved
    assert give_up_waypoints((g.x_inlet_m + 1e-6, 0.3, 0.1), [corner, s_pt], wait, g)[0] == (xb, 0.2, 0.1)
    # the back-off distance is the parameter's
    assert give_up_waypoints(corner, [corner], wait, g, back_m=2.5)[0] == (xs - 2.5, 8.0, -8.0)


@pytest.mark.parametrize("exit_yz", [(0.0, 0.0), (1.0, -0.8), (-1.2, 1.0)])
def test_a_laps_return_flies_over_the_tunnel_and_comes_down_only_above_its_own_wait_point(field, exit_yz):
    from fisc_agent.flight.routes import lap_return_waypoints

    g = MapGeometry.from_field(field)
    pos = (g.x_outlet_m + 0.2, *exit_yz)
    wait_at = (g.x_inlet_m - 1.0, 3.0, g.lo_m[2] - 2.0)
    wps = lap_return_waypoints(pos, wait_at, g, margin_m=0.5)
    assert wps[-1] == wait_at
    top = g.hi_m[2] + 0.5
    assert all(p[2] == top for p in wps[:-1])                        # over the tunnel's keep-out box
    assert wps[-2][:2] == wait_at[:2]                                 # the last leg is straight down
    path = [pos] + wps
    for a, b in zip(path[1:-2], path[2:-1]):                          # the legs at the top stay out of the box
        assert not _segment_enters_box(a, b, g, 0.5), (a, b)
    # another agent waiting 3 m beside it, at its height: only the last leg comes down, 3 m away
    other = np.array([wait_at[0], wait_at[1] - 3.0, wait_at[2]])
    for a, b in zip(path[:-1], path[1:]):
        s = np.linspace(0.0, 1.0, 400)[:, None]
        seg = np.asarray(a) + s * (np.asarray(b) - np.asarray(a))
        assert np.linalg.norm(seg - other, axis=1).min() >= 3.0 - 1e-9


@pytest.mark.parametrize("wait_xy", [(0.0, 0.0), (3.0, -1.0), ("corridor", 0.5), ("outlet", 0.0)])
def test_a_return_to_a_wait_point_under_the_tunnel_comes_down_upstream_of_the_entry_corridor(field, wait_xy):
    """Launched under the inlet (PX4 SITL's instance 0 is), a vehicle coming down above its wait point would
    descend through the corridor where the others enter: it comes down upstream of it and flies in level."""
    from fisc_agent.flight.routes import OVERFLY_M, lap_return_waypoints

    g = MapGeometry.from_field(field)
    margin, staging = 0.5, 1.5
    x_corridor = g.x_inlet_m - staging - margin
    wx = {"corridor": x_corridor, "outlet": g.hi_m[0] + margin}.get(wait_xy[0], wait_xy[0])
    wait_at = (wx, wait_xy[1], g.lo_m[2] - 5.0)
    wps = lap_return_waypoints((g.x_outlet_m + 0.2, 0.3, -0.2), wait_at, g, margin_m=margin, staging_m=staging)
    assert wps[-1] == wait_at and len(wps) == 5
    down_x = x_corridor - OVERFLY_M
    assert wps[-3] == (down_x, wait_at[1], g.hi_m[2] + margin)          # above a point upstream of the corridor
    assert wps[-2] == (down_x, wait_at[1], wait_at[2])                  # straight down there
    # no leg enters the corridor: the tunnel's box grown by the margin, extended upstream to x_corridor
    lo = np.array([x_corridor, g.lo_m[1] - margin, g.lo_m[2] - margin])
    hi = np.array([g.hi_m[0] + margin, g.hi_m[1] + margin, g.hi_m[2] + margin])
    path = [wps[0]] + wps[1:]
    for a, b in zip(path[:-1], path[1:]):
        s = np.linspace(0.0, 1.0, 2001)[:, None]
        seg = np.asarray(a) + s * (np.asarray(b) - np.asarray(a))
        inside = np.all((seg > lo + 1e-9) & (seg < hi - 1e-9), axis=1)
        assert not inside.any(), (a, b)


@pytest.mark.parametrize("dx, dy", [(-1e-6, 0.0), (0.0, 1e-6)])
def test_a_wait_point_just_outside_the_corridor_is_reached_straight_down(field, dx, dy):
    from fisc_agent.flight.routes import lap_return_waypoints

    g = MapGeometry.from_field(field)
    margin, staging = 0.5, 1.5
    x = g.x_inlet_m - staging - margin + dx
    y = (g.hi_m[1] + margin + dy) if dy else 0.0
    wait_at = (x, y, g.lo_m[2] - 5.0)
    wps = lap_return_waypoints((g.x_outlet_m + 0.2, 0.0, 0.0), wait_at, g, margin_m=margin, staging_m=staging)
    assert len(wps) == 4 and wps[-2][:2] == wait_at[:2]


@pytest.mark.parametrize("dist", [0.2, 0.8, 1.9, 6.0])
def test_approach_time_is_the_time_goto_velocity_takes(dist):
    from fisc_agent.flight.control import approach_time_s

    pos, target, dt, t = (0.0, 0.0, 0.0), (dist, 0.0, 0.0), 1e-3, 0.0
    while math.dist(pos, target) >= 0.3:
        v = goto_velocity(pos, target, 2.0)
        pos = tuple(p + dt * u for p, u in zip(pos, v))
        t += dt
    assert approach_time_s(dist, 2.0, 0.3) == pytest.approx(t, abs=2 * dt)


def test_check_map_accepts_good_and_names_bad(field):
    assert check_map(field, "slot") == []
    bad = dataclasses.replace(field, mean_cmd_m_s=np.where(np.arange(field.n_cv)[:, None] == 3, np.nan,
                                                           field.mean_cmd_m_s))
    with pytest.raises(MapError, match="commands: non-finite mean command in CV 3"):
        check_map(bad, "mean")
    bad = dataclasses.replace(field, n_star=np.zeros(field.n_cv, dtype=np.int32))
    with pytest.raises(MapError, match="n_star"):
        check_map(bad, "slot")
    with pytest.raises(MapError, match="mode"):
        check_map(field, "warp")


def test_max_command_speed(field):
    assert max_command_speed(field, "mean") == pytest.approx(np.linalg.norm(field.mean_cmd_m_s, axis=1).max())
    assert max_command_speed(field, "slot") >= max_command_speed(field, "mean") - 1e-9


def test_onboard_return_rejoins_a_flowing_cv_not_a_stagnant_neighbour(field):
    # the onboard geofence return passes over stagnant CVs (the simulator's table too: tests/sim/test_swarm.py)
    g = np.asarray(field.grid_cv)
    i, j, k = np.argwhere(g >= 0)[0]
    pos = field.origin_m + (np.array([i, j, k]) + 0.5) * field.cell_size_m
    pos[2] -= field.cell_size_m  # the cell below a CV of the first slice
    assert field.cv_of(pos[None])[0] == -1
    near = int(field.nearest_cv_within(pos[None])[0])
    mean = np.asarray(field.mean_cmd_m_s, dtype=float).copy()
    mean[near] *= 1e-3
    stagnant = dataclasses.replace(field, mean_cmd_m_s=mean)
    target = int(stagnant.return_cv_within(pos[None])[0])
    assert target >= 0 and target != near and not stagnant.stagnant[target]
    got = ScalarField(stagnant).return_command(tuple(pos))
    np.testing.assert_allclose(got, return_command(stagnant, pos[None], [target])[0])
