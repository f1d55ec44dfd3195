"""Deployment transform and geodetic anchor: defaults, yaw convention, round trips, scalar = array."""

import math

import numpy as np
import pytest

from fisc_agent.flight.frames import DeploymentTransform, GeodeticAnchor, parse_floats


def test_default_maps_x_north_y_east_z_up_axis_10m_up():
    tf = DeploymentTransform()
    assert tf.map_to_ned_xyz(0, 0, 0) == (0.0, 0.0, -10.0)
    np.testing.assert_allclose(tf.map_to_ned([[1.0, 2.0, 3.0]]), [[1.0, 2.0, -13.0]])
    np.testing.assert_allclose(tf.vel_map_to_ned([2.0, 0.5, 1.0]), [2.0, 0.5, -1.0])
    # a vehicle on the ground at the EKF origin is 10 m below the tunnel axis
    np.testing.assert_allclose(tf.ned_to_map([0.0, 0.0, 0.0]), [0.0, 0.0, -10.0])


def test_yaw_is_clockwise_from_north():
    tf = DeploymentTransform(origin_ned_m=(5.0, -3.0, -12.0), yaw_deg=90.0)
    # map +x points East; map +y then points South
    np.testing.assert_allclose(tf.vel_map_to_ned_xyz(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), atol=1e-12)
    np.testing.assert_allclose(tf.vel_map_to_ned_xyz(0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), atol=1e-12)
    np.testing.assert_allclose(tf.map_to_ned_xyz(2.0, 0.0, 1.0), (5.0, -1.0, -13.0), atol=1e-12)


@pytest.mark.parametrize("yaw", [0.0, 33.0, -120.0, 270.0])
def test_round_trips_and_scalar_agrees_with_array(yaw):
    rng = np.random.default_rng(1)
    tf = DeploymentTransform(origin_ned_m=tuple(rng.normal(size=3) * 10), yaw_deg=yaw)
    pts = rng.normal(size=(50, 3)) * 20
    np.testing.assert_allclose(tf.ned_to_map(tf.map_to_ned(pts)), pts, atol=1e-9)
    np.testing.assert_allclose(tf.vel_ned_to_map(tf.vel_map_to_ned(pts)), pts, atol=1e-9)
    for p in pts[:10]:
        np.testing.assert_allclose(tf.map_to_ned_xyz(*p), tf.map_to_ned(p), atol=1e-9)
        np.testing.assert_allclose(tf.ned_to_map_xyz(*p), tf.ned_to_map(p), atol=1e-9)
        np.testing.assert_allclose(tf.vel_map_to_ned_xyz(*p), tf.vel_map_to_ned(p), atol=1e-9)
        np.testing.assert_allclose(tf.vel_ned_to_map_xyz(*p), tf.vel_ned_to_map(p), atol=1e-9)


def test_velocities_ignore_translation():
    tf = DeploymentTransform(origin_ned_m=(100.0, 50.0, -30.0), yaw_deg=45.0)
    v = tf.vel_map_to_ned_xyz(1.0, 0.0, 0.0)
    assert math.isclose(math.hypot(*v), 1.0)
    np.testing.assert_allclose(v, (math.sqrt(0.5), math.sqrt(0.5), 0.0))


def test_invalid_transform_rejected():
    with pytest.raises(ValueError):
        DeploymentTransform(origin_ned_m=(0.0, float("nan"), 0.0))


def test_geodetic_anchor_distances_and_round_trip():
    a = GeodeticAnchor(47.3977, 8.5456, 488.0, 0.0)
    # 1e-4 deg latitude is about 11.1 m at 47 deg N; longitude shrinks with cos(lat)
    n, e, d = a.geodetic_to_ned(47.3978, 8.5456, 490.0)
    assert 11.0 < n < 11.3 and abs(e) < 1e-9 and d == pytest.approx(-2.0)
    n, e, d = a.geodetic_to_ned(47.3977, 8.5457, 488.0)
    assert e == pytest.approx(7.53, abs=0.03) and abs(n) < 1e-9
    for ned in [(12.0, -40.0, 3.0), (-150.0, 80.0, -20.0)]:
        np.testing.assert_allclose(a.geodetic_to_ned(*a.ned_to_geodetic(*ned)), ned, atol=1e-6)


def test_geodetic_anchor_heading_gives_the_transform():
    a = GeodeticAnchor.parse("47.0, 8.0, 500, 90")
    tf = a.transform()
    assert tf.origin_ned_m == (0.0, 0.0, 0.0) and tf.yaw_deg == 90.0
    # the anchor itself is the map origin; 10 m East is 10 m along the tunnel axis
    ned = a.geodetic_to_ned(*a.ned_to_geodetic(0.0, 10.0, 0.0))
    np.testing.assert_allclose(tf.ned_to_map_xyz(*ned), (10.0, 0.0, 0.0), atol=1e-6)


def test_parse_helpers_name_the_option():
    assert parse_floats("1, 2,-3", 3, "--origin") == (1.0, 2.0, -3.0)
    with pytest.raises(ValueError, match="--origin"):
        parse_floats("1,2", 3, "--origin")
    with pytest.raises(ValueError, match="anchor"):
        GeodeticAnchor.parse("1,2,x,4")
    with pytest.raises(ValueError):
        GeodeticAnchor(95.0, 0.0, 0.0, 0.0)


# ------------------------------------------------------------------ boundaries (issue 38)
# Published WGS-84 radii of curvature (e.g. NGA TR8350.2; Wikipedia "Earth radius"), not this module's formula:
# meridional M and prime-vertical N at the equator and at 45 deg.
PUBLISHED_RADII_M = {0.0: (6_335_439.3, 6_378_137.0), 45.0: (6_367_381.8, 6_388_838.3)}


@pytest.mark.parametrize("lat", sorted(PUBLISHED_RADII_M))
@pytest.mark.parametrize("alt_m", [0.0, 1000.0])
def test_north_and_east_use_the_meridian_and_the_prime_vertical_radii(lat, alt_m):
    """Catches the two radii swapped, the ellipsoid terms miscomputed and the altitude left out."""
    m, n = PUBLISHED_RADII_M[lat]
    a = GeodeticAnchor(lat, 10.0, alt_m, 0.0)
    step = 1e-3  # deg
    north, east, down = a.geodetic_to_ned(lat + step, 10.0, alt_m)
    assert north == pytest.approx(math.radians(step) * (m + alt_m), abs=2e-6) and east == 0.0 and down == 0.0
    north, east, down = a.geodetic_to_ned(lat, 10.0 + step, alt_m)
    assert east == pytest.approx(math.radians(step) * (n + alt_m) * math.cos(math.radians(lat)), abs=2e-6)
    assert north == 0.0
    assert a.geodetic_to_ned(lat - step, 10.0 - step, alt_m + 5.0)[2] == -5.0  # above is negative down


def test_longitude_differences_wrap_across_the_antimeridian():
    a = GeodeticAnchor(0.0, 179.9995, 0.0, 0.0)
    east = a.geodetic_to_ned(0.0, -179.9995, 0.0)[1]
    assert east == pytest.approx(math.radians(0.001) * 6_378_137.0, abs=1e-6)  # 111.3 m east, not around the world
    assert a.geodetic_to_ned(0.0, 179.9985, 0.0)[1] == pytest.approx(-east, abs=1e-6)


@pytest.mark.parametrize("lat, lon, ok", [
    (89.0, 0.0, True), (-89.0, 0.0, True), (math.nextafter(89.0, 90.0), 0.0, False), (-89.5, 0.0, False),
    (0.0, 180.0, True), (0.0, -180.0, True), (0.0, math.nextafter(180.0, 181.0), False), (0.0, -180.5, False),
])
def test_anchor_latitude_and_longitude_limits(lat, lon, ok):
    if ok:
        assert GeodeticAnchor(lat, lon, 0.0, 0.0).lat_deg == lat
    else:
        with pytest.raises(ValueError, match=r"geodetic anchor: invalid \(lat, lon, alt, heading\)"):
            GeodeticAnchor(lat, lon, 0.0, 0.0)


def test_errors_name_what_was_wrong():
    with pytest.raises(ValueError, match="^geodetic anchor LAT,LON,ALT,HEADING: '1,2,x,4' is not 4 numbers$"):
        GeodeticAnchor.parse("1,2,x,4")
    with pytest.raises(ValueError, match="^--origin: '1,nan,2' has a non-finite value$"):
        parse_floats("1,nan,2", 3, "--origin")
    with pytest.raises(ValueError, match=r"^deployment transform: invalid origin \(0.0, nan, 0.0\) or yaw 0.0$"):
        DeploymentTransform(origin_ned_m=(0.0, float("nan"), 0.0))


def test_the_origin_is_kept_as_a_tuple_of_floats():
    tf = DeploymentTransform(origin_ned_m=[1, 2, 3])
    assert tf.origin_ned_m == (1.0, 2.0, 3.0) and type(tf.origin_ned_m) is tuple
