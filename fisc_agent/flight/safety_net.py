"""The separation safety net (issue 37 item 3): keep at least d_min from the neighbours one hears
(pure, numpy; arrays in, a velocity out).

The flow law stays the paper's: no communication, each agent flies the map's velocity at its own
position.  Design (the admission budget, the entry windows, the exit lattice) is meant to hold d_min;
the net is what acts when design alone does not (two vehicles admitted 0.9 s apart by skewed clocks,
a vehicle slower than the one behind it).  It pushes apart only inside a neighbour's keep-out radius,
and outside it only limits how fast a vehicle closes in (below); everywhere else the command is
untouched, so the fluid figures change only where vehicles were about to come too close.

What the agent knows of its neighbours is what they already publish: their telemetry on Zenoh
(position and velocity in the map frame, about 5 Hz).  Each report has an age ``a`` (time since it
was received plus the position's own age when it was sent; no clock is compared across vehicles).
Per neighbour j (``keep_apart``; the vectorised form for a whole swarm is ``keep_apart_pairs``):

- **Where it is.**  ``p_j + v_j min(a, fresh_s)``: extrapolated by its velocity while the report is
  fresh, not beyond.
- **Keep-out radius.**  ``r_j = d_min + growth_m_s max(0, a - fresh_s)``: a neighbour whose reports
  go stale could be anywhere within what it may have flown since, so the spacing kept from it grows
  (the issue's "degrading to larger spacing").  Reports older than ``forget_s`` are dropped: a vehicle
  that has landed or lost its link for that long is not where it was.
- **No closing in.**  With ``n`` the unit vector from the neighbour to this vehicle and ``d`` the
  distance, the commanded speed towards the neighbour, ``c = -v . n``, is cut to
  ``max(0, -v_j . n + max(0, d - r_j) / horizon_s)``: the neighbour's own speed away along the same
  line (zero for a stale report), so a column that moves together keeps moving, plus what reaches the
  keep-out radius no sooner than ``horizon_s``; a neighbour coming towards the vehicle takes its speed off
  that, so the pair together closes no faster than one vehicle would on a still neighbour.  (Until
  2026-12-07 only the speed away counted: head on, each of two vehicles allowed itself the whole
  ``gap / horizon_s``, the pair closed at twice the designed rate on lags of 0.7-0.9 s, and two stock PX4
  meeting on their join routes at 2.1 and 0.9 m/s came 0.48 m apart by SIH's truth.)  A vehicle that is
  not closing fast is left alone; one closing fast starts braking ``horizon_s`` of closing before the radius.
  (Acting only inside d_min is too late: a vehicle closing at 1.5 m/s on a lag of 0.9 s, stock PX4's, is
  through the 0.42 m of margin a 0.92 m d_min leaves between two 0.25 m radii before it has slowed.)
- **Passing is not closing.**  The closing cut applies only to a pair whose straight-line closest
  approach within the horizon (this vehicle at its command, the neighbour at its reported velocity while
  fresh, still otherwise) comes nearer than ``r_j + pass_margin_m``: a vehicle that flies past a
  neighbour, however fast its distance shrinks on the way, is left alone.  (Without it, on eight stock
  PX4 the net acted in 13-22 % of the joins' ticks all over the routes around the inlet, for example on
  a lap's return coming down 3 m beside a waiting vehicle: the joins reached the inlet 2.6-7.8 s late.)
  Head-on it changes nothing: where the closing limit acts, the vehicle would be inside the radius
  within the horizon.
- **Push apart**, only inside the radius: ``push_gain_1_s (r_j - d) n``.
- **One neighbour at a time, nearest first** (``sequential_cuts``).  Each closing limit is a half-space of
  commands (speed towards that neighbour at most what it allows); the limits the command breaks are
  applied one after the other, each to the command as the cuts before it left it, in order of the gap to
  the keep-out radius (then the neighbour's id).  A single cut only slows a vehicle towards its neighbour,
  but cuts in turn can swing a command round (two neighbours 30 degrees above and below the path turn 2
  m/s ahead into 0.5 m/s back and down), so the result then loses any component against the mission's
  command, and is scaled down until it meets every limit again (a cut can break a limit the command met).
  Every limit allows hovering, so the result is never faster than the command, never turned back against
  it, and never closes faster than any limit allows: a queue ahead stops a vehicle, it does not reverse
  it; moving away is the push's job.  (Summing the cuts, each from the mission's command, braked k times
  for k neighbours in a line: two ahead commanded a climbing join backwards, eight at (-11, -3, -6) m/s,
  and in a CI run of the kill lab a join flew backwards down into the ground.)
- The pushes of all neighbours are summed and capped at ``max_push_m_s``; two on opposite sides
  cancel (the vehicle between them holds).
- Two reports at the same point get ``n`` along +x for the smaller id and -x for the larger, so the
  pair always separates.
- **Never through the wall.**  Over the duct's length (``DuctAxis``) the net's correction loses any
  component pointing away from the duct's axis: it slows, turns and pushes along the duct or inwards,
  never outwards.  (Without this rule two vehicles side by side near the wall pushed the outer one
  out, and its way back in then read as closing on its neighbour: ``fisc-sim run --safety-net`` lost
  13-28 % of its vehicles through the wall.)
- **The horizon adapts to the vehicle** (``effective_horizon_s``): at least ``lag_factor`` times the
  velocity lag the agent identified.  A closing speed limited to ``gap / T`` on a first-order lag
  ``tau`` approaches like a second-order system of damping ``sqrt(T / tau) / 2``: ``T >= 4 tau``
  brakes without overshoot.  With 1.5 s on stock PX4's 0.9 s lag two simulated vehicles closing at
  2.3 m/s came within 0.50 m.

The net never adds speed along the flow beyond the push, and the runner's speed and acceleration
clamps still apply after it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from fisc_agent.flight.control import Vec

COINCIDENT_M = 1e-6
"""Two positions closer than this are taken as coincident (the direction is chosen by id)."""
LIMIT_TOL_M_S = 1e-9
"""A closing speed this little over its limit after the cuts is rounding, not a broken limit [m/s] (a cut
lands its command on the limit to within ~1e-16; scaling for that would stop the vehicle)."""


@dataclass(frozen=True)
class SafetyNetConfig:
    """The safety net's settings (``--safety-net``; d_min itself is the map's, ``Separation.d_min_m``)."""

    fresh_s: float = 0.5
    """A neighbour's report younger than this is current: extrapolated by its velocity, keep-out d_min [s]
    (telemetry at 5 Hz plus the position's age is about 0.3 s old)."""
    growth_m_s: float = 2.0
    """Beyond ``fresh_s`` the keep-out radius grows by this much per second of age [m/s] (about the
    fastest the map flies)."""
    forget_s: float = 5.0
    """Reports older than this are dropped [s]."""
    horizon_s: float = 1.5
    """The speed towards a neighbour is limited so that its keep-out radius is reached no sooner than
    this [s] (or ``lag_factor`` times the vehicle's lag, if longer).  0 with no lag known: no limit
    outside the radius (the net acts only inside it)."""
    lag_factor: float = 4.0
    """The horizon is at least this many times the vehicle's identified velocity lag (look-ahead:
    lag plus dead time): 4 brakes a first-order lag without overshoot."""
    pass_margin_m: float = 0.5
    """A pair whose straight-line closest approach within the horizon stays this far beyond the keep-out
    radius is passing: its closing is not limited [m] (how far a vehicle of velocity lag 0.8 s, stock
    PX4's, strays from a straight line when its command turns by 0.6 m/s)."""
    push_gain_1_s: float = 1.0
    """Push apart at this gain times the depth inside the keep-out radius [1/s]."""
    max_push_m_s: float = 0.5
    """Cap of the summed push [m/s]."""

    def __post_init__(self) -> None:
        for name in ("fresh_s", "growth_m_s", "forget_s", "horizon_s", "lag_factor", "pass_margin_m",
                     "push_gain_1_s", "max_push_m_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"safety net: {name} must be a finite number >= 0, is {value!r}")
        if self.forget_s < self.fresh_s:
            raise ValueError(f"safety net: forget_s ({self.forget_s}) must be >= fresh_s ({self.fresh_s})")


@dataclass(frozen=True)
class NeighbourReports:
    """The newest report of each neighbour, as seen now (other vehicles only)."""

    ids: np.ndarray
    """(k,) int agent ids."""
    position_m: np.ndarray
    """(k, 3) reported positions, map frame [m]."""
    velocity_m_s: np.ndarray
    """(k, 3) reported velocities, map frame [m/s]."""
    age_s: np.ndarray
    """(k,) age of each report now [s] (>= 0)."""

    @classmethod
    def empty(cls) -> "NeighbourReports":
        """No neighbour heard."""
        return cls(np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))

    def __len__(self) -> int:
        return int(self.ids.shape[0])


@dataclass(frozen=True)
class DuctAxis:
    """Where the duct is, for the net's wall rule: its length along the map's x axis and its axis."""

    x_lo_m: float
    """Inlet plane [m]."""
    x_hi_m: float
    """Outlet plane [m]."""
    center_yz_m: tuple[float, float] = (0.0, 0.0)
    """(y, z) of the duct's axis [m] (DESIGN.md section 2: the map's x axis)."""


def effective_horizon_s(cfg: SafetyNetConfig, lag_s: float = 0.0) -> float:
    """The net's horizon for a vehicle of velocity lag ``lag_s`` [s]: ``max(horizon_s, lag_factor lag_s)``."""
    lag = lag_s if math.isfinite(lag_s) and lag_s > 0 else 0.0
    return max(cfg.horizon_s, cfg.lag_factor * lag)


def no_outward(position_m: np.ndarray, correction_m_s: np.ndarray, duct: DuctAxis | None) -> np.ndarray:
    """``correction_m_s`` (n, 3) less its component away from the duct's axis for the rows whose
    position (n, 3) lies over the duct's length (inlet <= x <= outlet); unchanged without a duct."""
    if duct is None:
        return correction_m_s
    radial = np.zeros_like(correction_m_s)
    radial[:, 1] = position_m[:, 1] - duct.center_yz_m[0]
    radial[:, 2] = position_m[:, 2] - duct.center_yz_m[1]
    r = np.sqrt(radial[:, 1] ** 2 + radial[:, 2] ** 2)
    over = (position_m[:, 0] >= duct.x_lo_m) & (position_m[:, 0] <= duct.x_hi_m) & (r > COINCIDENT_M)
    radial[over] /= r[over, None]
    outward = np.where(over, np.maximum(0.0, np.einsum("ij,ij->i", correction_m_s, radial)), 0.0)
    return correction_m_s - outward[:, None] * radial


class NeighbourSource(Protocol):
    """Where an agent hears its neighbours (``fisc_agent.zenoh.neighbours.NeighbourTable``)."""

    def reports(self, exclude_id: int) -> NeighbourReports:
        """Every vehicle's newest report but ``exclude_id``'s, with its age now."""


@dataclass(frozen=True)
class NetAction:
    """What the net did to one command."""

    velocity_m_s: Vec
    """The command after the net, map frame [m/s] (the input itself when ``acting`` is empty)."""
    acting: tuple[int, ...]
    """Ids of the neighbours that changed the command: closing too fast on them, or inside their
    keep-out radius (empty: the net did nothing)."""
    nearest_m: float
    """Distance to the nearest neighbour where it is now taken to be [m] (inf: none heard)."""

    @property
    def active(self) -> bool:
        """True when the net changed the command."""
        return bool(self.acting)


def predicted_and_radius(reports: NeighbourReports, d_min_m: float,
                         cfg: SafetyNetConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each report: where the neighbour is taken to be now (k, 3), its keep-out radius (k,) [m],
    and whether it is kept (k,) bool (younger than ``forget_s``)."""
    age = np.asarray(reports.age_s, dtype=float)
    kept = age <= cfg.forget_s
    pos = reports.position_m + reports.velocity_m_s * np.minimum(age, cfg.fresh_s)[:, None]
    radius = d_min_m + cfg.growth_m_s * np.maximum(0.0, age - cfg.fresh_s)
    return pos, radius, kept


def closest_approach_m(rel_m: np.ndarray, rel_vel_m_s: np.ndarray, horizon_s: float) -> np.ndarray:
    """(m,) least distance within ``[0, horizon_s]`` of pairs at relative positions ``rel_m`` (m, 3) moving
    at relative velocities ``rel_vel_m_s`` (m, 3) in straight lines [m] (the distance now for a pair at
    rest relative to each other)."""
    ww = np.einsum("ij,ij->i", rel_vel_m_s, rel_vel_m_s)
    moving = ww > 0.0
    t = np.where(moving, -np.einsum("ij,ij->i", rel_m, rel_vel_m_s) / np.where(moving, ww, 1.0), 0.0)
    t = np.clip(t, 0.0, horizon_s)
    at = rel_m + rel_vel_m_s * t[:, None]
    return np.sqrt(np.einsum("ij,ij->i", at, at))


@dataclass(frozen=True)
class _PairTerms:
    """What each pair (vehicle, neighbour) contributes to the net, (m,) or (m, 3) per pair."""

    unit: np.ndarray
    """(m, 3) ``n``: the unit vector from the neighbour to the vehicle."""
    allowed_m_s: np.ndarray
    """(m,) the speed towards the neighbour the pair allows [m/s] (inf: no limit)."""
    limits: np.ndarray
    """(m,) bool: the closing limit applies (the pair is not passing)."""
    gap_m: np.ndarray
    """(m,) distance minus keep-out radius [m] (negative: inside)."""
    push_m_s: np.ndarray
    """(m, 3) the push apart [m/s] (zero outside the radius)."""


def _pair_terms(rel_m: np.ndarray, tie_sign: np.ndarray, v_m_s: np.ndarray, v_nb_m_s: np.ndarray,
                radius_m: np.ndarray, fresh: np.ndarray, cfg: SafetyNetConfig, horizon_s: float) -> _PairTerms:
    """Per pair: ``rel_m`` own position minus the neighbour's, ``v_m_s`` the vehicle's command (for the
    pass rule), ``tie_sign`` +1 / -1 the x direction of ``n`` for coincident positions."""
    dist = np.linalg.norm(rel_m, axis=1)
    n = np.zeros_like(rel_m)
    apart = dist > COINCIDENT_M
    n[apart] = rel_m[apart] / dist[apart, None]
    n[~apart, 0] = tie_sign[~apart]
    v_nb = np.where(fresh[:, None], v_nb_m_s, 0.0)
    away = -np.einsum("ij,ij->i", v_nb, n)   # the neighbour's speed away from the vehicle (< 0: closing)
    gap = dist - radius_m
    if horizon_s > 0:
        allowed = np.maximum(0.0, away + np.maximum(0.0, gap) / horizon_s)
    else:
        allowed = np.where(gap >= 0, np.inf, np.maximum(0.0, away))
    passing = closest_approach_m(rel_m, v_m_s - v_nb, horizon_s) >= radius_m + cfg.pass_margin_m
    push = (cfg.push_gain_1_s * np.maximum(0.0, -gap))[:, None] * n
    return _PairTerms(n, allowed, ~passing, gap, push)


def _not_back(w_m_s: np.ndarray, command_m_s: np.ndarray) -> np.ndarray:
    """Each row of ``w_m_s`` (n, 3) less its component against the same row of ``command_m_s``."""
    vv = np.einsum("ij,ij->i", command_m_s, command_m_s)
    back = np.minimum(0.0, np.einsum("ij,ij->i", w_m_s, command_m_s)) / np.where(vv > 0.0, vv, 1.0)
    return w_m_s - back[:, None] * command_m_s


def sequential_cuts(command_m_s: np.ndarray, me: np.ndarray, neighbour_id: np.ndarray, unit: np.ndarray,
                    allowed_m_s: np.ndarray, gap_m: np.ndarray) -> np.ndarray:
    """The commands ``command_m_s`` (n, 3) after the closing limits of pairs (``me`` (p,) the vehicle's
    row, ``neighbour_id`` (p,), ``unit`` (p, 3) ``n``, ``allowed_m_s`` (p,), ``gap_m`` (p,)): the limits
    the command breaks are applied one at a time per vehicle, nearest gap first (ties by the neighbour's
    id), each to the command as the cuts before it left it; then each command loses any component
    against the mission's and is scaled down to meet all its limits (module docstring).  Vectorised
    across vehicles: round r applies every vehicle's r-th cut."""
    cmd = np.asarray(command_m_s, dtype=float)
    w = cmd.copy()
    breaks = np.flatnonzero(-np.einsum("ij,ij->i", cmd[me], unit) > allowed_m_s)
    if breaks.size == 0:
        return w
    order = breaks[np.lexsort((neighbour_id[breaks], gap_m[breaks], me[breaks]))]
    first = np.r_[True, me[order][1:] != me[order][:-1]]
    rank = np.arange(order.size) - np.maximum.accumulate(np.where(first, np.arange(order.size), 0))
    for r in range(int(rank.max()) + 1):
        k = order[rank == r]
        rows = me[k]
        excess = np.maximum(0.0, -np.einsum("ij,ij->i", w[rows], unit[k]) - allowed_m_s[k])
        w[rows] += excess[:, None] * unit[k]
    w = _not_back(w, cmd)
    closing = -np.einsum("ij,ij->i", w[me], unit)
    over = closing > allowed_m_s + LIMIT_TOL_M_S
    scale = np.ones(w.shape[0])
    np.minimum.at(scale, me[over], allowed_m_s[over] / closing[over])
    return w * scale[:, None]


def _cap(push_m_s: np.ndarray, max_m_s: float) -> np.ndarray:
    """Scale each row of ``push_m_s`` down to at most ``max_m_s`` long."""
    norm = np.linalg.norm(push_m_s, axis=-1, keepdims=True)
    return push_m_s * np.minimum(1.0, max_m_s / np.maximum(norm, 1e-300))


def keep_apart(position_m: Vec, velocity_m_s: Vec, agent_id: int, reports: NeighbourReports, d_min_m: float,
               cfg: SafetyNetConfig = SafetyNetConfig(), lag_s: float = 0.0, duct: DuctAxis | None = None) -> NetAction:
    """The net applied to one vehicle's command ``velocity_m_s`` at ``position_m`` (module docstring), for
    a vehicle of velocity lag ``lag_s`` in ``duct``.  The single-vehicle form, and the oracle of
    ``keep_apart_pairs``."""
    if len(reports) == 0:
        return NetAction(velocity_m_s, (), math.inf)
    pos_nb, radius, kept = predicted_and_radius(reports, d_min_m, cfg)
    rel = np.asarray(position_m, dtype=float) - pos_nb
    dist = np.sqrt(np.einsum("ij,ij->i", rel, rel))
    v = np.asarray(velocity_m_s, dtype=float)
    # cheap first cut: a pair acts only inside r + horizon (|v| + the neighbour's speed, while fresh)
    horizon = effective_horizon_s(cfg, lag_s)
    fresh = np.asarray(reports.age_s) <= cfg.fresh_s
    nb_speed = np.where(fresh, np.linalg.norm(reports.velocity_m_s, axis=1), 0.0)
    near = kept & (dist < radius + horizon * (math.sqrt(v @ v) + nb_speed))
    nearest = float(dist[kept].min()) if kept.any() else math.inf
    if not near.any():
        return NetAction(velocity_m_s, (), nearest)
    ids = np.asarray(reports.ids)[near]
    t = _pair_terms(rel[near], np.where(int(agent_id) < ids, 1.0, -1.0), np.broadcast_to(v, (len(ids), 3)),
                    reports.velocity_m_s[near], radius[near], fresh[near], cfg,
                    horizon)
    # the oracle of ``sequential_cuts``: the limits the command breaks one at a time, nearest gap first
    w = v.copy()
    acts = t.gap_m < 0
    breaks = t.limits & (-(t.unit @ v) > t.allowed_m_s)
    if breaks.any():  # else no cut: the command meets every limit as it is
        order = np.lexsort((ids, t.gap_m))
        for j in order[breaks[order]]:
            excess = -float(w @ t.unit[j]) - float(t.allowed_m_s[j])
            if excess > 0:
                w = w + excess * t.unit[j]
                acts[j] = True
        w = _not_back(w[None, :], v[None, :])[0]
        closing = -(t.unit @ w)
        over = t.limits & (closing > t.allowed_m_s + LIMIT_TOL_M_S)
        if over.any():
            w = w * float(np.min(t.allowed_m_s[over] / closing[over]))
            acts |= over
    if not acts.any():
        return NetAction(velocity_m_s, (), nearest)
    correction = (w - v) + _cap(t.push_m_s.sum(axis=0), cfg.max_push_m_s)
    out = v + no_outward(np.asarray(position_m, dtype=float)[None, :], correction[None, :], duct)[0]
    return NetAction((float(out[0]), float(out[1]), float(out[2])), tuple(int(i) for i in ids[acts]), nearest)


def keep_apart_pairs(position_m: np.ndarray, velocity_m_s: np.ndarray, command_m_s: np.ndarray, ids: np.ndarray,
                     pairs: np.ndarray, d_min_m: float, cfg: SafetyNetConfig = SafetyNetConfig(), lag_s: float = 0.0,
                     duct: DuctAxis | None = None) -> np.ndarray:
    """The net for a whole swarm whose members hear each other at once (reports of age 0: the
    simulator's view): ``command_m_s`` (n, 3) after the net.  ``pairs`` (m, 2): index pairs (i, j),
    each unordered pair once, to be checked: every pair that can act, i.e. within d_min plus the
    horizon times the fastest commanded speed and the fastest velocity (a vehicle closes at most at its
    own commanded speed, and its limit falls by the neighbour's speed towards it).  ``lag_s``: the
    vehicles' velocity lag; ``duct``: the wall rule.  Agrees with ``keep_apart`` applied to each vehicle with fresh
    reports of all the others."""
    cmd = np.asarray(command_m_s, dtype=float)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if pairs.shape[0] == 0:
        return cmd.copy()
    # both directions: (i hears j) and (j hears i)
    me = np.concatenate([pairs[:, 0], pairs[:, 1]])
    nb = np.concatenate([pairs[:, 1], pairs[:, 0]])
    t = _pair_terms(position_m[me] - position_m[nb], np.where(ids[me] < ids[nb], 1.0, -1.0), cmd[me],
                    velocity_m_s[nb], np.full(me.size, float(d_min_m)), np.ones(me.size, dtype=bool), cfg,
                    effective_horizon_s(cfg, lag_s))
    lim = t.limits
    cut = sequential_cuts(cmd, me[lim], np.asarray(ids)[nb[lim]], t.unit[lim], t.allowed_m_s[lim], t.gap_m[lim])
    total_push = np.zeros_like(cmd)
    np.add.at(total_push, me, t.push_m_s)
    return cmd + no_outward(position_m, (cut - cmd) + _cap(total_push, cfg.max_push_m_s), duct)
