"""Score one flown pass through the duct against the CFD (pure: arrays in, a typed result out).

The figures the real-autopilot acceptance asks for, computed from an agent's flight log
(``fisc_agent.flight.flightlog``) and the reference flow the map was fitted from:

- **excursion**: how far the vehicle went outside the duct wall while ``x_lo <= x <= x_hi``,
  from its entry into the map (first FLOW sample) on.
  The wall radius per axial station is the largest radius of the reference's nodes there plus
  half the node spacing (the CFD nodes lie strictly inside the wall), and the duct is taken to
  be axisymmetric about the map's x axis (DESIGN.md section 2).  Positive = outside [m].
- **axial-velocity nRMSE**: RMS over the in-duct FLOW samples of (flown axial velocity -
  S * CFD axial velocity at the nearest CFD node), divided by the largest such target along
  the track.
- **realised spread** (``realised_spread_ratio``): the kinetic deviation a pass flew, over the
  map's fitted spread.
- **crossing**: whether the pass reached ``x > x_hi`` without a hold, and the time it took from
  the inlet plane.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

from fisc_agent.map.lookup import CommandField
from fisc_agent.map.wall import DuctWall
from fisc_ground.maps.duct_wall import duct_wall_from_reference
from fisc_ground.reference.field import ReferenceField

@dataclass(frozen=True)
class FlightScore:
    """How one pass went (map frame)."""

    crossed: bool
    """The pass reached x > x_hi in FLOW/EXIT without a hold before it."""
    held: bool
    """A HOLD began during the pass, after it entered the flow and before it crossed (geofence, failsafe,
    fleet hold); a hold before the entry (a take-off's position-jump hold) is not part of the pass."""
    max_excursion_m: float
    """Largest distance outside the wall for x_lo <= x <= x_hi (negative: always inside) [m]."""
    velocity_nrmse: float
    """Axial-velocity nRMSE of the in-duct FLOW samples (nan without samples)."""
    crossing_time_s: float
    """Time from the inlet plane (x = x_lo) to x_hi [s] (nan if not crossed)."""
    n_samples: int
    """In-duct FLOW samples scored."""
    peak_flown_m_s: float
    """Largest flown axial velocity in the duct [m/s]."""
    peak_target_m_s: float
    """Largest target (S x CFD axial velocity) along the track [m/s]."""
    velocity_nrmse_gnss: float = math.nan
    """The same nRMSE with the GNSS receiver's own axial velocity in place of the autopilot's estimate, over the
    scored samples that carry one (nan: none; flight logs before the ``gnss_vx_m_s`` column).  Beside
    ``velocity_nrmse`` it tells the estimator's share of the figure: PX4 SIH's EKF velocity errs by 0.11-0.16 m/s
    RMS in the duct, its GNSS velocity by 0.05-0.07 (three stock PX4, 2026-12-07)."""

    def as_dict(self) -> dict:
        """JSON-ready fields (non-finite floats as None)."""
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in asdict(self).items()}


def score_track(time_s: np.ndarray, pos_m: np.ndarray, vel_m_s: np.ndarray, states: np.ndarray,
                ref: ReferenceField, scale: float, x_lo_m: float = 0.0, x_hi_m: float = 15.0,
                wall: DuctWall | None = None, gnss_vx_m_s: np.ndarray | None = None) -> FlightScore:
    """Score a pass.  ``pos_m``/``vel_m_s`` (n, 3) map frame, ``states`` (n,) mission state names;
    ``gnss_vx_m_s`` (n,) the GNSS receiver's axial velocity where a row has one (nan elsewhere), scored
    as ``FlightScore.velocity_nrmse_gnss``."""
    wall = wall or duct_wall_from_reference(ref)
    states = np.asarray(states).astype(str)
    x = pos_m[:, 0]
    in_duct = (x >= x_lo_m) & (x <= x_hi_m)
    entered = np.flatnonzero(states == "FLOW")
    after_entry = np.arange(len(states)) >= (entered[0] if entered.size else len(states))
    scored = in_duct & after_entry & np.isin(states, ("FLOW", "EXIT", "HOLD", "RETURN"))
    r = np.hypot(pos_m[:, 1], pos_m[:, 2])
    exc = r[scored] - wall.radius_at(x[scored])
    max_exc = float(exc.max()) if exc.size else math.nan
    crossed_idx = np.flatnonzero((x > x_hi_m) & np.isin(states, ("FLOW", "EXIT")))
    hold_idx = np.flatnonzero((states == "HOLD") & after_entry)
    first_cross = int(crossed_idx[0]) if crossed_idx.size else None
    held = bool(hold_idx.size and (first_cross is None or hold_idx[0] < first_cross))
    crossed = first_cross is not None and not held
    t_cross = math.nan
    if crossed:
        start = np.flatnonzero((x >= x_lo_m) & (states == "FLOW"))
        if start.size:
            t_cross = float(time_s[first_cross] - time_s[start[0]])
    flow = in_duct & (states == "FLOW")
    n = int(flow.sum())
    if n == 0:
        return FlightScore(crossed, held, max_exc, math.nan, t_cross, 0, math.nan, math.nan)
    _, j = cKDTree(ref.points_m).query(pos_m[flow])
    target = scale * ref.velocity_m_s[j, 0]
    flown = vel_m_s[flow, 0]
    peak = float(np.max(np.abs(target)))
    nrmse = _nrmse(flown, target, peak)
    nrmse_gnss = math.nan
    if gnss_vx_m_s is not None:
        g = np.asarray(gnss_vx_m_s, dtype=float)[flow]
        has = np.isfinite(g)
        if has.any():
            nrmse_gnss = _nrmse(g[has], target[has], peak)
    return FlightScore(crossed, held, max_exc, nrmse, t_cross, n, float(flown.max()), peak, nrmse_gnss)


def _nrmse(flown: np.ndarray, target: np.ndarray, peak: float) -> float:
    """RMS of ``flown - target`` over ``peak`` (nan for a zero peak)."""
    return float(np.sqrt(np.mean((flown - target) ** 2)) / peak) if peak > 0 else math.nan


def _track_rows(rows: list[dict[str, str]]) -> list[dict[str, str]]:
    """The rows of a flight log that carry a position and a velocity (the ones a track is made of)."""
    return [r for r in rows if r["x_m"] != "" and r["vx_m_s"] != ""]


def track_from_rows(rows: list[dict[str, str]]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(time_s, pos_m, vel_m_s, states) of the rows of a flight log that carry a position."""
    rows = _track_rows(rows)
    t = np.array([float(r["time_s"]) for r in rows])
    pos = np.array([[float(r["x_m"]), float(r["y_m"]), float(r["z_m"])] for r in rows]).reshape(-1, 3)
    vel = np.array([[float(r["vx_m_s"]), float(r["vy_m_s"]), float(r["vz_m_s"])] for r in rows]).reshape(-1, 3)
    return t, pos, vel, np.array([r["state"] for r in rows])


def gnss_vx_from_rows(rows: list[dict[str, str]]) -> np.ndarray:
    """(n,) the GNSS receiver's axial velocity of the rows ``track_from_rows`` keeps, nan where a row has none
    (an empty cell, or a log written before the ``gnss_vx_m_s`` column)."""
    rows = _track_rows(rows)
    return np.array([float(r["gnss_vx_m_s"]) if r.get("gnss_vx_m_s") else math.nan for r in rows])


def realised_spread_ratio(pos_m: np.ndarray, vel_m_s: np.ndarray, states: np.ndarray, field: CommandField) -> float:
    """How much of the map's fitted spread a flown pass realised (the ``kinetic`` mode's pressure).

    RMS over the FLOW samples inside a CV of ||v - c(x)||, with c the map's staggered field at the
    vehicle (``fisc_agent.map.lookup.CommandField``, mode ``staggered``), over the RMS of the fitted spread
    sigma_j of the samples' CVs.  About 1 for a vehicle flying the kinetic deviations, about its
    tracking error over sigma (~0.2) for one flying the field alone.  NaN without such samples.
    """
    pos = np.asarray(pos_m, dtype=float)
    flow = np.asarray(states).astype(str) == "FLOW"
    cv = field.cv_of(pos)
    ok = flow & (cv >= 0) & np.all(np.isfinite(vel_m_s), axis=1)
    if not ok.any() or field.spread_m_s is None:
        return math.nan
    c = field.command(pos[ok], np.zeros(int(ok.sum()), dtype=np.int64), "staggered", cv_ids=cv[ok])
    dev = np.asarray(vel_m_s, dtype=float)[ok] - c
    sigma = np.asarray(field.spread_m_s)[cv[ok]]
    return float(np.sqrt(np.mean(np.sum(dev ** 2, axis=1))) / np.sqrt(np.mean(sigma ** 2)))


def wall_track_from_rows(rows: list[dict[str, str]]) -> tuple[np.ndarray, np.ndarray]:
    """(wall_time_s, pos_m) of the rows of a flight log that carry a position and a wall-clock time: the
    clock several vehicles' logs share (``fisc_ground.fields.separation_stats.common_time_base``)."""
    rows = [r for r in rows if r["x_m"] != "" and r.get("wall_time_s", "") != ""]
    t = np.array([float(r["wall_time_s"]) for r in rows])
    pos = np.array([[float(r["x_m"]), float(r["y_m"]), float(r["z_m"])] for r in rows]).reshape(-1, 3)
    return t, pos
