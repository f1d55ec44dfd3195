"""``fisc_agent.map.wall``: the duct's real wall a map carries, and the kinetic deviation kept inside it."""

import math

import numpy as np
import pytest

from fisc_agent.flight.control import ScalarField
from fisc_agent.map.lookup import CommandField
from fisc_agent.map.codec import MapError, decode_map, encode_map, load_map
from fisc_agent.flight.tracking import ParcelTracker, TrackingConfig, cross_stream
from fisc_agent.map.wall import WALL_ARRAY, DuctWall, map_wall, reflect_at_wall, rejoin_inset_m, rejoin_point
from fisc_ground.maps.duct_wall import duct_wall_from_reference
from fisc_ground.maps.build import default_map_path
from fisc_ground.reference.builtin import load_builtin

CONE = DuctWall(np.array([0.0, 10.0]), np.array([1.0, 2.0]))  # radius 1 + x / 10


def test_the_radius_is_linear_between_stations_and_constant_beyond():
    assert CONE.radius_at(np.array([-5.0, 0.0, 2.5, 10.0, 12.0])) == pytest.approx([1.0, 1.0, 1.25, 2.0, 2.0])
    assert np.array_equal(DuctWall.from_array(CONE.as_array()).radius_m, CONE.radius_m)


@pytest.mark.parametrize("x, r, match", [
    ([0.0], [1.0], ">= 2 stations"), ([0.0, 1.0], [1.0], "two equal"), ([0.0, 0.0], [1.0, 1.0], "ascending"),
    ([1.0, 0.0], [1.0, 1.0], "ascending"), ([0.0, 1.0], [1.0, 0.0], "> 0"), ([0.0, np.nan], [1.0, 1.0], "finite"),
])
def test_a_bad_wall_is_refused_by_what_is_wrong(x, r, match):
    with pytest.raises(ValueError, match=match):
        DuctWall(np.array(x), np.array(r))


def test_only_outward_radial_components_within_the_margin_are_mirrored():
    pts = np.array([[5.0, 1.2, 0.0],     # radius 1.2, wall 1.5: inside a 0.5 m margin
                    [5.0, 1.2, 0.0],     # the same, heading inward
                    [5.0, 0.5, 0.0],     # far from the wall
                    [5.0, 0.0, 1.3],     # on the z side, inside the margin
                    [5.0, 0.0, 0.0]])    # on the axis
    dev = np.array([[0.3, 0.4, 0.1], [0.3, -0.4, 0.1], [0.3, 0.4, 0.1], [0.0, 0.2, 0.5], [0.0, 0.4, 0.0]])
    out = reflect_at_wall(pts, dev, CONE, margin_m=0.5)
    assert out[0] == pytest.approx([0.3, -0.4, 0.1])      # radial mirrored, axial and tangential kept
    assert np.array_equal(out[1:3], dev[1:3]) and np.array_equal(out[4], dev[4])
    assert out[3] == pytest.approx([0.0, 0.2, -0.5])
    assert np.linalg.norm(out, axis=1) == pytest.approx(np.linalg.norm(dev, axis=1))   # a reflection: speed kept
    # a skew point: the radial direction is (y, z) / r
    p, d = np.array([[5.0, 1.0, 1.0]]), np.array([[0.0, 1.0, 0.0]])
    got = reflect_at_wall(p, d, CONE, margin_m=0.5)[0]
    assert got == pytest.approx([0.0, 0.0, -1.0]) and d[0] == pytest.approx([0.0, 1.0, 0.0])  # input untouched


def test_the_fit_writes_the_reference_wall_and_a_malformed_one_is_refused_by_name():
    cmap = load_map(default_map_path())
    ref = load_builtin("cd_nozzle_inviscid")
    wall = map_wall(cmap.arrays)
    assert np.array_equal(wall.as_array(), duct_wall_from_reference(ref).as_array())
    # every CFD node lies inside it, and the throat is narrower than the ends
    p = ref.points_m
    assert np.all(np.hypot(p[:, 1], p[:, 2]) < wall.radius_at(p[:, 0]))
    assert wall.radius_at(6.0) < 0.6 * wall.radius_at(0.0)
    body = {k: v for k, v in cmap.body.items() if k not in ("arrays", "sha256")}
    arrays = {k: np.asarray(v) for k, v in cmap.arrays.items()}
    for bad, match in ((arrays[WALL_ARRAY][::-1].copy(), "ascending"), (arrays[WALL_ARRAY][:, :1].copy(), r"\(k, 2\)"),
                       (arrays[WALL_ARRAY].astype("<f4"), "<f8")):
        with pytest.raises(MapError, match=f"array 'duct_wall_m': .*{match}"):
            decode_map(encode_map(body, {**arrays, WALL_ARRAY: bad}))
    without = {k: v for k, v in arrays.items() if k != WALL_ARRAY}
    assert map_wall(decode_map(encode_map(body, without)).arrays) is None       # optional: older maps load


def _default():
    cmap = load_map(default_map_path())
    wall = map_wall(cmap.arrays)
    return ScalarField(CommandField.from_map(cmap), wall=wall), wall


def test_the_agents_deviation_never_heads_out_within_the_margin_and_is_the_simulators_elsewhere():
    sfield, wall = _default()
    near = (6.0, 0.0, float(wall.radius_at(6.0)) - 0.3)       # 0.3 m inside the throat's wall
    far = (6.0, 0.0, 0.0)
    assert sfield.cv_of(*near) >= 0 and sfield.cv_of(*far) >= 0
    outward = 0
    for agent in range(200):
        plain = ScalarField(sfield.field, wall=wall).deviation(near, None, agent, 0.0)
        kept = ScalarField(sfield.field, wall=wall).deviation(near, None, agent, 0.0, wall_margin_m=0.5)
        assert kept[2] <= 1e-12                                # never toward the wall (+z here)
        assert kept == pytest.approx((plain[0], plain[1], -abs(plain[2])))
        outward += plain[2] > 0
        assert ScalarField(sfield.field, wall=wall).deviation(far, None, agent, 0.0, wall_margin_m=0.5) == \
            ScalarField(sfield.field).deviation(far, None, agent, 0.0)
    assert 60 < outward < 140                                  # about half of the drawn directions head out


def test_a_cross_stream_deviation_is_turned_before_the_mirror_so_it_never_heads_out_beside_a_diverging_wall():
    """The default ``KineticAxes.CROSS_STREAM`` beside the diffuser's wall, where the stream tilts outward: the
    deviation is turned across the stream first and mirrored after, so within the margin it never heads
    out, and it keeps the CV's spread.  Turned after the mirror (the order of a first version), a mostly
    upstream deviation became a full-speed outward one: a real PX4 left the map so near x = 13 m."""
    sfield, wall = _default()
    near = (10.5, 0.0, float(wall.radius_at(10.5)) - 0.3)
    v = sfield.flight(near, None, 0, 0.0, "staggered", 0.0)      # the field steps outward with the staircase
    stream = tuple(c / math.hypot(*v) for c in v)
    assert stream[2] > 0.5                                       # tilted outward by more than 30 degrees
    spread = float(sfield.field.spread_m_s[sfield.cv_of(*near)])
    turned_late = 0
    for agent in range(200):
        plain = ScalarField(sfield.field, wall=wall).deviation(near, None, agent, 0.0)
        mirrored = ScalarField(sfield.field, wall=wall).deviation(near, None, agent, 0.0, wall_margin_m=0.5)
        kept = ScalarField(sfield.field, wall=wall).deviation(near, None, agent, 0.0, wall_margin_m=0.5, stream=stream)
        assert kept[2] <= 1e-12                                  # never toward the wall
        assert math.hypot(*kept) == pytest.approx(spread)       # at the CV's spread
        turned_late += cross_stream(mirrored, stream)[2] > 1e-9
    assert turned_late > 10                                      # the other order heads out for some


def test_a_kinetic_parcel_heading_for_the_wall_stays_inside_it():
    """An ideal vehicle (velocity = command) under streamline tracking whose deviation keeps pointing
    outward: with the wall it stays inside the real duct; reflected at the staircase only (the
    simulator's rule) it leaves it."""
    sfield, wall = _default()

    def fly(margin):
        tracker = ParcelTracker(TrackingConfig(lookahead_s=0.5), x_outlet_m=15.0)
        pos, worst, dt = (1.0, 0.0, 0.0), -math.inf, 0.05

        def outward(p, stream):  # a deviation of 0.4 m/s straight away from the axis (+y on it)
            r = math.hypot(p[1], p[2])
            d = np.array([[0.0, 0.4 * p[1] / r, 0.4 * p[2] / r]]) if r > 0 else np.array([[0.0, 0.4, 0.0]])
            if margin is not None:
                d = reflect_at_wall(np.array([p]), d, wall, margin)
            return tuple(float(v) for v in d[0])

        def field(x, y, z):
            return sfield.flight((x, y, z), None, 0, 0.0, "staggered", 0.0)

        for k in range(int(20.0 / dt)):
            v = tracker.step(k * dt, pos, field, outward)
            if v is None or pos[0] > 14.5:
                break
            pos = tuple(p + dt * c for p, c in zip(pos, v))
            worst = max(worst, math.hypot(pos[1], pos[2]) - float(wall.radius_at(pos[0])))
        return worst, pos[0]

    worst, reached = fly(0.5)
    assert worst < -0.2 and reached > 14.0                  # the whole duct, at least 0.2 m inside the wall
    worst, reached = fly(None)
    assert worst > 0.3                     # the staircase's outer cubes let it out (then the geofence acts)


@pytest.mark.parametrize("radius_m, margin_m, inset_m", [
    (2.0, 0.8, 0.8),      # wide: the margin
    (1.6, 0.8, 0.8),      # the margin equals half the radius
    (1.4, 0.8, 0.7),      # narrower: half the radius
    (1.0, 0.0, 0.0),      # no margin: the wall itself
])
def test_the_rejoin_inset_is_the_margin_capped_at_half_the_local_radius(radius_m, margin_m, inset_m):
    assert rejoin_inset_m(radius_m, margin_m) == pytest.approx(inset_m)


def test_a_vehicle_rejoins_clear_of_the_wall_heading_straight_in():
    # at x = 5 the cone's wall is 1.5 m: inset 0.5 m with a 0.5 m margin, so clear up to r = 1.0
    assert rejoin_point(CONE, (5.0, 1.0, 0.0), 0.5) is None                 # on the line: clear
    assert rejoin_point(CONE, (5.0, 0.0, 0.0), 0.5) is None                 # the axis
    assert rejoin_point(CONE, (5.0, 0.6, -0.8 + 1e-9), 0.5) is None         # r = 1.0 on a skew bearing
    got = rejoin_point(CONE, (5.0, 1.0 + 1e-6, 0.0), 0.5)                   # just outside the line
    assert got == pytest.approx((5.0, 0.5, 0.0))                            # twice the inset inside the wall
    got = rejoin_point(CONE, (5.0, -1.2, 1.6), 0.5)                         # beyond the wall (r 2.0), skew
    assert got == pytest.approx((5.0, -0.3, 0.4))                           # same bearing, r = 0.5
    # a margin wider than half the radius: the inset is half of it, the target the axis
    assert rejoin_point(CONE, (0.0, 0.6, 0.0), 0.8) == pytest.approx((0.0, 0.0, 0.0))
    assert rejoin_point(CONE, (0.0, 0.5, 0.0), 0.8) is None
