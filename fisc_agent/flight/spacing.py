"""Where the vehicles of a swarm stand apart (pure): entry points in the inlet disc, exit holds and
landing spots beyond the outlet, and the distance checks that state their guarantees.

- **Entry.**  ``ENTRY_POINTS`` (64) entry points per inlet disc: agent ids 0..63 each have their own
  point, so no two of them share an entry point, whatever their entry windows
  (``entry_slot_open``).  The points are a Vogel (golden-angle) spiral, area-uniform over
  the disc: 64 of them over a disc of radius rho stand at least ``VOGEL_64_MIN_SPACING`` x rho apart
  (0.193 rho; the densest known packing of 64 points in a disc reaches about 0.24 rho).
- **Exit.**  Hold spots lie on a square lattice of pitch ``spacing_m`` in the horizontal plane
  (map x, y; map z is up, ``fisc_agent.flight.frames``), in the half-plane from ``exit_clearance_m``
  beyond the outlet downstream.  Agent i takes the i-th lattice site in order of its distance from
  the point on the axis where the lattice starts (a half disc that grows with the fleet), so any two
  agents, whatever their ids, hold and land (straight down from their hold) at least ``spacing_m``
  apart horizontally.  The sites are integer pairs, ordered by integer keys: every agent computes
  the same layout, on any machine.
- **Admission.**  ``entry_schedule`` resolves the entry windows an agent uses: given ones, or by
  default the map's admission budget (``fisc_agent.map.separation``): windows of the map's admission
  period, one per vehicle of its ``max_in_tunnel``, so a fleet within the budget is admitted one vehicle
  per period, decentralised (slots by id on the shared clock).
- **Altitude.**  Every hold spot is at one altitude: the tunnel's axis height, raised to at least
  ``HOLD_FLOOR_MARGIN_M`` above the tunnel's floor (its lowest CV face) and to at least a given
  lower bound (the take-off height above the vehicle's home: the ground is not in the map, the home
  is the one point known to stand on it).  So no hold spot lies below the ground or a tunnel floor.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from fisc_agent.map.separation import Separation

ENTRY_POINTS = 64
"""Entry points per inlet disc (``control.entry_points``): agent ids 0..63 have one each."""
VOGEL_64_MIN_SPACING = 0.1932
"""Least distance between two of the 64 points of a Vogel spiral filling a disc of radius 1
(r_k = sqrt((k + 1/2) / 64), theta_k = k x golden angle), rounded down; checked in the tests."""
HOLD_FLOOR_MARGIN_M = 1.0
"""Least height of a hold spot above the tunnel's floor (its lowest CV face) [m]."""
DEFAULT_ENTRY_SLOTS = 8
"""Entry windows per cycle when neither the configuration nor the map's budget gives a number."""
DISTANCE_TOLERANCE_M = 1e-9
"""Rounding allowance of ``check_min_distance``: a layout whose points are exactly the bound apart
passes although floating point puts some pairs 1e-16 m closer [m]."""


def min_pairwise_distance_m(points_m: np.ndarray) -> float:
    """Least distance between two rows of an (n, d) array of points [m]; +inf for fewer than two.

    Pass (n, 2) horizontal coordinates for a horizontal distance, (n, 3) for a 3-D one."""
    p = np.asarray(points_m, dtype=float)
    if p.ndim != 2:
        raise ValueError(f"min_pairwise_distance_m: points must be an (n, d) array, got shape {p.shape}")
    if len(p) < 2:
        return math.inf
    best = math.inf
    for i in range(len(p) - 1):   # row by row: O(n) memory for thousands of points
        best = min(best, float(np.min(np.linalg.norm(p[i + 1:] - p[i], axis=1))))
    return best


def check_min_distance(points_m: np.ndarray, min_m: float, what: str = "layout") -> float:
    """The least pairwise distance of ``points_m`` (``min_pairwise_distance_m``) [m]; ``ValueError``
    naming ``what`` and the distance when it is below ``min_m`` (less ``DISTANCE_TOLERANCE_M``)."""
    d = min_pairwise_distance_m(points_m)
    if d < float(min_m) - DISTANCE_TOLERANCE_M:
        raise ValueError(f"{what}: two points are {d:.6f} m apart, less than the required {min_m} m")
    return d


def hold_sites(n: int) -> np.ndarray:
    """(n, 2) integer lattice sites (i, j) of agents 0..n-1: i >= 0 rows downstream, j columns across.

    Sites in order of i^2 + j^2 (distance from the lattice's start on the axis), then of i (nearer
    the outlet first), then |j|, then j: agents 0, 1, 2 take (0, 0), (0, -1), (0, 1).  Distinct agents
    take distinct sites, so two sites are at least one pitch apart."""
    n = int(n)
    if n < 0:
        raise ValueError(f"hold_sites: the number of agents must be >= 0, got {n}")
    if n == 0:
        return np.zeros((0, 2), dtype=np.int64)
    reach = max(1, math.ceil(math.sqrt(2.0 * n / math.pi)) + 1)   # a half disc of radius reach holds > n sites
    while True:
        i, j = np.meshgrid(np.arange(reach + 1), np.arange(-reach, reach + 1), indexing="ij")
        i, j = i.ravel(), j.ravel()
        d2 = i * i + j * j
        inside = d2 <= reach * reach   # complete rings only: every site nearer than ``reach`` is listed
        if int(inside.sum()) >= n:
            i, j, d2 = i[inside], j[inside], d2[inside]
            order = np.lexsort((j, np.abs(j), i, d2))[:n]
            return np.column_stack([i[order], j[order]]).astype(np.int64)
        reach *= 2


def hold_altitude_m(axis_z_m: float, floor_z_m: float, min_z_m: float | None = None,
                    floor_margin_m: float = HOLD_FLOOR_MARGIN_M) -> float:
    """Altitude (map z, up) of every hold spot [m]: the tunnel's axis height ``axis_z_m``, raised to
    ``floor_z_m + floor_margin_m`` (the tunnel's floor) and to ``min_z_m`` where given (e.g. home z +
    take-off height: the vehicle's own ground)."""
    vals = (axis_z_m, floor_z_m, floor_margin_m) + (() if min_z_m is None else (min_z_m,))
    if not all(math.isfinite(float(v)) for v in vals):
        raise ValueError(f"hold_altitude_m: non-finite input {vals!r}")
    z = max(float(axis_z_m), float(floor_z_m) + float(floor_margin_m))
    return z if min_z_m is None else max(z, float(min_z_m))


def lattice_hold_points(n: int, x0_m: float, y_axis_m: float, z_m: float, pitch_m: float) -> np.ndarray:
    """(n, 3) hold spots of agents 0..n-1 (map frame): site (i, j) of ``hold_sites`` at
    (x0 + i pitch, y_axis + j pitch, z) [m].  Any two are at least ``pitch_m`` apart horizontally."""
    if not (math.isfinite(pitch_m) and pitch_m > 0):
        raise ValueError(f"lattice_hold_points: the pitch must be > 0 m, got {pitch_m!r}")
    if not all(math.isfinite(float(v)) for v in (x0_m, y_axis_m, z_m)):
        raise ValueError(f"lattice_hold_points: non-finite origin {(x0_m, y_axis_m, z_m)!r}")
    s = hold_sites(n).astype(float)
    return np.column_stack([x0_m + s[:, 0] * pitch_m, y_axis_m + s[:, 1] * pitch_m, np.full(len(s), float(z_m))])


ENTRY_OPEN_FRACTION = 0.25
"""Fraction of its entry window in which an agent may start across the inlet (``entry_slot_open``).
Entries in neighbouring windows are then at least ``(1 - ENTRY_OPEN_FRACTION) x stagger`` apart.
With one half, a late arrival in its window entered ``stagger / 2`` before the next agent: on real PX4
(the SITL fleet test, 4 s windows) two vehicles so entered 2.3 s apart at the inlet's 0.45 m/s, and
the one that crossed 1 s faster came within 0.27 m of the other (SIH ground truth; 0.52 m by PX4's
estimates).  With one quarter, the same test's closest approach in the duct was 1.57-2.47 m."""
ENTRY_TIMING_TOLERANCE_S = 1.0
"""How far from its due time a join reaches its staging point and starts across (``speed_for_arrival``
and the 1 s per-leg allowance: up to about 1 s early, then it waits; a stock PX4 with lag 0.9 s).  The
map's admission budget keeps consecutive entries d_min apart despite it (``separation_budget``): with
windows of d_min / ((1 - ENTRY_OPEN_FRACTION) u_in) alone, six real PX4 came within 0.29-0.39 m."""
JOIN_LEG_ALLOWANCE_S = 1.0
"""Added to each leg's time in the join's lead (``Navigator.plan_join``): a vehicle leaves early enough
to arrive when due even with a lag, and the arrival governor (``Navigator._join_speed``) slows it to arrive on
time; arriving late cannot be made up.  Without it, a stock PX4 (lag 0.9 s) 17 m from the inlet
arrived 2.3 s late at 1.5 x the join speed, 0.6 s after the next vehicle's entry (0.29 m apart)."""
MAX_LEAD_LEARNT_S = 20.0
"""Most a join's lead grows by what late arrivals taught it (each of ``Navigator.lead_learnt_s`` and
``Navigator.leg_lead_s``) [s]."""

FINAL_LEG_LEAST_CRAWL = 0.5
"""A timed final leg (``final_leg_speed_m_s``) ahead of its crossing slows down to this fraction of the crawl."""
FINAL_LEG_MOST_CRAWL = 1.5
"""A timed final leg behind its crossing flies up to this multiple of the crawl in its brake zone: a stock PX4
flew 0.30 m/s there for a setpoint of 0.43 (its steady gain at that speed 0.7) and crossed 1.1 s late
(three stock PX4, 2026-12-07, with the crawl as the brake zone's most)."""
FINAL_LEG_MIN_BRAKE_M = 0.5
"""Least distance before the inlet plane from which a join's final leg flies the crawl (one 0.5 m slice) [m]."""


def final_leg_speed_m_s(to_plane_m: float, crawl_m_s: float, lag_s: float, cap_m_s: float,
                        gain_1_s: float = 1.0, time_left_s: float | None = None,
                        vx_m_s: float | None = None) -> float:
    """A join's speed along x on its final leg, ``to_plane_m`` before the inlet plane: the crawl ``crawl_m_s``
    (the flow's own speed at the entry point) from ``brake = max(FINAL_LEG_MIN_BRAKE_M, 2 lag_s crawl)`` before
    the plane on (two of the vehicle's lags at the crawl: a first-order lag's excess speed falls to 14 %), and
    before that a proportional approach to that point on top of the crawl, within ``cap_m_s``.

    ``time_left_s``: the time until the crossing it aims at (the staging point's due time plus the leg at the
    crawl, ``Navigator.join_step``). The speed is then the one that reaches the brake point ``brake / crawl``
    before that crossing (in the brake zone: the plane at it), within ``FINAL_LEG_LEAST_CRAWL`` x the crawl and
    the approach (at least ``FINAL_LEG_MOST_CRAWL`` x the crawl, within ``cap_m_s``); with ``vx_m_s``, the
    vehicle's velocity along x, reckoned from where its lag ``lag_s`` takes it. Recomputed every tick, it makes
    up a lag or a low gain and holds back a vehicle that arrived at its staging point at speed. Without it (the
    approach alone) crossings spread over 3.8 s (-3.5 to +0.3 s from their due times, 52 crossings of stock PX4,
    2026-12-07) for windows of 4.23 s, and two vehicles came 0.45 m apart at the inlet.

    The proportional approach all the way to the entry point crossed the plane still fast (eight stock PX4,
    2026-12-07: 0.70 m/s in the inlet's first 0.25 m for a 0.42 setpoint; the inlet slice read 0.7 of its
    neighbour's density).  The crawl all the way from the staging point crossed it at 0.43 for 0.44 but was slow
    to get there: a stock PX4 early in its flight, its integrator still catching up, took 6 s for 1.6 m and was
    past its crossing's due time (``Navigator._late_across``); it turned back towards the next vehicle coming
    down to its staging point (0.50 m apart by SIH's ground truth)."""
    brake_m = max(FINAL_LEG_MIN_BRAKE_M, 2.0 * lag_s * crawl_m_s)
    if time_left_s is not None and vx_m_s is not None:
        to_plane_m, time_left_s = to_plane_m - vx_m_s * lag_s, time_left_s - lag_s
    approach_m_s = max(crawl_m_s, min(cap_m_s, crawl_m_s + gain_1_s * (to_plane_m - brake_m)))
    if time_left_s is None or to_plane_m <= 0.0:
        return approach_m_s
    if to_plane_m <= brake_m:
        needed_m_s = to_plane_m / time_left_s if time_left_s > 0.0 else math.inf
    else:
        to_brake_s = time_left_s - brake_m / crawl_m_s
        needed_m_s = (to_plane_m - brake_m) / to_brake_s if to_brake_s > 0.0 else math.inf
    most_m_s = max(approach_m_s, min(cap_m_s, FINAL_LEG_MOST_CRAWL * crawl_m_s))
    return max(FINAL_LEG_LEAST_CRAWL * crawl_m_s, min(most_m_s, needed_m_s))


def entry_slot_open(wall_time_s: float, agent_id: int, stagger_s: float, slots: int) -> bool:
    """May agent ``agent_id`` cross the inlet now?  Decentralised staggered entry on a shared clock.

    Time is cut into a cycle of ``slots`` windows of ``stagger_s``; agent i owns window
    ``i mod slots`` and starts across in its first ``ENTRY_OPEN_FRACTION``, so two agents with
    different windows enter at least ``(1 - ENTRY_OPEN_FRACTION) x stagger_s`` apart (the spacing
    they keep is that gap times the flow's speed, least at the inlet and outlet) and no agent waits
    longer than one cycle.  ``stagger_s = 0``: always open (no stagger).
    """
    if stagger_s <= 0.0 or slots <= 1:
        return True
    phase = math.fmod(wall_time_s, stagger_s * slots)
    start = (int(agent_id) % slots) * stagger_s
    return start <= phase < start + ENTRY_OPEN_FRACTION * stagger_s


class ScheduleSource(StrEnum):
    """Where an agent's entry windows come from."""

    GIVEN = "given"
    """``--entry-stagger`` SECONDS (0: none)."""
    MAP = "map"
    """The map's admission budget (``separation.admission_period_s``)."""
    NONE = "none"
    """Auto, but the map records no budget (fitted before issue 37): no stagger."""


@dataclass(frozen=True)
class EntrySchedule:
    """The entry windows one agent uses (``entry_slot_open``'s arguments)."""

    stagger_s: float
    """Window length [s]; 0: no stagger (enter as soon as staged)."""
    slots: int
    """Windows per cycle (agent i owns window i mod slots)."""
    source: ScheduleSource
    """Where they come from."""


def entry_schedule(stagger_s: float | None, slots: int | None, separation: Separation) -> EntrySchedule:
    """The entry windows of an agent configured with ``stagger_s`` / ``slots`` (None: auto) on a map
    with ``separation``.  Auto stagger: the map's admission period, with ``slots`` auto its
    ``max_in_tunnel`` windows per cycle (a cycle of ``max_in_tunnel`` admission periods, at least the
    mean transit time); a map without a budget: no stagger.  Auto slots otherwise: ``DEFAULT_ENTRY_SLOTS``."""
    if stagger_s is not None:
        return EntrySchedule(float(stagger_s), DEFAULT_ENTRY_SLOTS if slots is None else int(slots),
                             ScheduleSource.GIVEN)
    period = separation.admission_period_s
    if period is None:
        return EntrySchedule(0.0, DEFAULT_ENTRY_SLOTS if slots is None else int(slots), ScheduleSource.NONE)
    n = slots if slots is not None else (separation.max_in_tunnel or DEFAULT_ENTRY_SLOTS)
    return EntrySchedule(float(period), int(n), ScheduleSource.MAP)


def schedule_messages(schedule: EntrySchedule, sep: Separation, agent_id: int) -> list[tuple[int, str]]:
    """What an agent says when its entry windows change: (logging level, message) pairs."""
    if schedule.source is ScheduleSource.MAP:
        out = [(logging.INFO, f"entry: the map's admission budget, one window of {schedule.stagger_s:.2f} s per "
                              f"vehicle, {schedule.slots} per cycle (at most {sep.max_in_tunnel} vehicles in the "
                              f"tunnel at d_min {sep.d_min_m:.2f} m)")]
        if agent_id >= schedule.slots:
            out.append((logging.WARNING, f"agent id {agent_id} is beyond the map's {schedule.slots} entry windows: "
                                         f"it shares the window of id {agent_id % schedule.slots} (a fleet larger "
                                         "than the map's budget)"))
        return out
    if schedule.source is ScheduleSource.NONE:
        return [(logging.WARNING, "the map records no admission budget (fitted before issue 37): entering without "
                                  "a stagger; refit it or give --entry-stagger SECONDS")]
    return []
