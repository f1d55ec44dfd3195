"""Waypoint routes around the tunnel (pure, map frame): into it, back to the wait point after a lap, out
to a hold spot.

Every route keeps out of the tunnel's keep-out box (the CVs' bounding box grown by a margin) except where it
crosses the inlet plane, and out of the places where the other vehicles wait, join or hold.  The vehicles
fly these routes without talking to each other, so each rule is written from where the others are by design.
"""

from __future__ import annotations

from fisc_agent.flight.control import MapGeometry, Vec


def join_waypoints(pos: Vec, entry: Vec, geom: MapGeometry, staging_m: float = 1.5,
                   margin_m: float = 1.0) -> list[Vec]:
    """Waypoints from ``pos`` to ``entry`` that stay out of the tunnel until the inlet.

    The keep-out region is the CVs' bounding box grown by ``margin_m``.  The staging point S
    lies ``staging_m`` upstream of the inlet plane at the entry point's (y, z); the last leg
    S -> entry crosses the inlet plane along +x.  From downstream of S, the vehicle first moves
    vertically out of the box's z band (below it) if it is inside the band laterally, travels
    along x at that level to the staging plane, then to S.  Returns ``[..., S, entry]``.
    """
    xs = geom.x_inlet_m - staging_m
    stage = (xs, entry[1], entry[2])
    wps: list[Vec] = []
    x, y, z = pos
    if x > xs:
        lat_in = geom.lo_m[1] - margin_m <= y <= geom.hi_m[1] + margin_m
        vert_in = geom.lo_m[2] - margin_m <= z <= geom.hi_m[2] + margin_m
        if lat_in and vert_in:
            z = geom.lo_m[2] - margin_m
            wps.append((x, y, z))
        wps.append((xs, y, z))
    wps += [stage, entry]
    return wps


OVERFLY_M = 1.5
"""Least height of an exit's transit above the hold spots it passes over [m]: d_min (0.92 m by default)
plus the vertical wander of a held PX4 (SIH ground truth against its estimate: up to 0.4 m)."""


def lap_return_waypoints(pos: Vec, wait_at: Vec, geom: MapGeometry, margin_m: float = 1.0,
                         staging_m: float = 1.5) -> list[Vec]:
    """Waypoints of a lap's return from past the outlet ``pos`` to ``wait_at``, the point above the
    vehicle's launch point where its first join waited (exit policy ``loop`` with staggered entry).

    Up at ``pos`` to ``margin_m`` above the tunnel's bounding box, back along x at that height to
    above ``wait_at``'s x at ``pos``'s y, across to above ``wait_at``, and straight down to it.  The
    other agents wait above their own launch points, below that height: the only leg that comes down
    to them is the last, which descends above this vehicle's own launch point.  (Back below the tunnel
    instead, as ``join_waypoints`` routes, a return at the waiting height would fly through them.)

    A vehicle launched under the tunnel or its entry corridor (the bounding box grown by ``margin_m``,
    upstream to ``margin_m`` before the staging plane ``staging_m`` before the inlet) does not come down
    there, through the corridor where the others enter: it comes down ``OVERFLY_M`` further upstream and
    flies the last leg level, at ``wait_at``'s height.  (Eight stock PX4 SITL, 2026-12-07: vehicle 0,
    launched under the inlet, came down through it as vehicle 7 crossed it, 0.25 m apart by SIH's ground
    truth.)  Returns ``[..., wait_at]``."""
    z_top = geom.hi_m[2] + margin_m
    x, y, _ = pos
    x_down = wait_at[0]
    x_corridor = geom.x_inlet_m - staging_m - margin_m
    if (x_corridor <= wait_at[0] <= geom.hi_m[0] + margin_m
            and geom.lo_m[1] - margin_m <= wait_at[1] <= geom.hi_m[1] + margin_m):
        x_down = x_corridor - OVERFLY_M
    wps = [(x, y, z_top), (x_down, y, z_top), (x_down, wait_at[1], z_top)]
    if x_down != wait_at[0]:
        wps.append((x_down, wait_at[1], wait_at[2]))
    return wps + [wait_at]


def exit_waypoints(pos: Vec, spot: Vec, geom: MapGeometry, clearance_m: float, pitch_m: float,
                   margin_m: float = 1.0, overfly_m: float = OVERFLY_M) -> list[Vec]:
    """Waypoints of the exit from past the outlet ``pos`` to the agent's hold spot ``spot``
    (``hold_point``, ``clearance_m`` beyond the outlet, the others ``pitch_m`` apart).

    Over the holding vehicles, never through them: up to the transit height while moving on to
    ``clearance_m - pitch_m`` beyond the outlet (the climb ends one pitch short of the first row of spots),
    across at that height to above ``spot``, and straight down to it.  The transit height is
    ``margin_m`` above the tunnel's bounding box and at least ``overfly_m`` above the spots.  Flown
    straight from the outlet, later vehicles passed between the ones already holding: six PX4 SITL
    vehicles came 0.29 m apart (SIH ground truth).  Returns ``[climb, above spot, spot]``."""
    z_top = max(geom.hi_m[2] + margin_m, spot[2] + overfly_m)
    x, y, _ = pos
    return [(max(x, geom.x_outlet_m + clearance_m - pitch_m), y, z_top), (spot[0], spot[1], z_top), spot]


def give_up_waypoints(pos: Vec, passed: list[Vec], wait_at: Vec, geom: MapGeometry, staging_m: float = 1.5,
                      back_m: float = OVERFLY_M) -> list[Vec]:
    """Waypoints back to ``wait_at`` for a join that gives its entry window up at ``pos``, having passed
    ``passed`` (its route's waypoints after the wait point, in the order flown).

    Back the way it came, its own route, away from the others' wait points; but not through the staging
    plane (``staging_m`` before the inlet): there every join's last legs converge on the inlet, so a leg
    flown back there runs head on into the next vehicle coming up its own, nearly parallel, leg (eight stock
    PX4 SITL, 2026-12-07: 0.48 m apart by SIH's ground truth, the safety net acting on both).  A join that
    reached the plane (a passed waypoint in it) first backs off ``back_m`` upstream of it, straight from
    ``pos``, and flies the part of its route in the plane that far upstream; the legs before the plane it
    flies back as they were.  Returns ``[..., wait_at]``."""
    xs = geom.x_inlet_m - staging_m
    in_plane = [abs(p[0] - xs) <= 1e-9 for p in passed]
    if not any(in_plane):
        return passed[::-1] + [wait_at]
    xb = xs - back_m
    route = [(xb, pos[1], pos[2])] if xb < pos[0] <= geom.x_inlet_m else []
    for p, flat in zip(passed[::-1], in_plane[::-1]):
        q = (xb, p[1], p[2]) if flat else p
        if not route or q != route[-1]:
            route.append(q)
    return route + [wait_at]
