"""Fleet alarms on vehicle health, authority and silence (pure: telemetry records in, alarm lines out).

Shared by the monitor (``TelemetryAggregator.view``: terminal, Foxglove ``/fisc/alarms``, MCAP log)
and ``fisc-ground status``.  Every alarm names its agents:

- ``every agent stale``: the ground hears none of the agents it heard before (the radio, the
  router or the ground's own link is down, or the whole fleet is off);
- ``stale``: some agents not heard for the stale time (the others still are);
- ``low battery``: battery below ``low_battery_pct``, or the agent itself reports its battery low;
- ``unhealthy <kind>``: the agent reports a health problem of that kind (estimator, system,
  position, gps, origin, takeoff, other);
- ``hands-off``: someone else (pilot, ground station, autopilot failsafe) changed the vehicle's
  mode: the agent no longer commands it;
- ``refused a fleet command``: the agent refused a command (the newest reason is given: a
  ``stale`` or ``future`` one usually means a clock far off).

Health, authority and refusals are judged on live agents only (a stale agent's are old news).
"""

from __future__ import annotations

import numpy as np

from fisc_agent.zenoh import telemetry_codec as tc

LOW_BATTERY_PCT = 30.0
"""Default battery level below which the ground raises ``low battery`` [%]."""
UNHEALTHY_KINDS = ("estimator", "system", "position", "gps", "origin", "takeoff", "other")
"""Health kinds that raise ``unhealthy <kind>`` (a low battery has its own alarm)."""


def id_list(ids: np.ndarray, limit: int = 12) -> str:
    """``"1, 2, 3 ... (+n)"`` of at most ``limit`` sorted ids."""
    ids = sorted(int(i) for i in ids)
    text = ", ".join(str(i) for i in ids[:limit])
    return text + (f" ... (+{len(ids) - limit})" if len(ids) > limit else "")


def fleet_alarms(ids: np.ndarray, records: np.ndarray, live: np.ndarray, stale_after_s: float,
                 low_battery_pct: float = LOW_BATTERY_PCT) -> list[str]:
    """Alarm lines for agents ``ids`` with their newest ``telemetry_codec.DTYPE`` ``records`` and
    ``live`` mask (heard within ``stale_after_s``)."""
    ids = np.asarray(ids, dtype=np.int64)
    live = np.asarray(live, dtype=bool)
    out: list[str] = []
    if len(ids) and not live.any():
        out.append(f"every agent stale: none of the {len(ids)} agents heard in the last {stale_after_s:g} s")
    elif (~live).any():
        out.append(f"stale (not heard for {stale_after_s:g} s): agents {id_list(ids[~live])}")
    if not live.any():
        return out
    health = records["health"].astype(np.int64)
    battery = tc.battery_pct(records)
    with np.errstate(invalid="ignore"):
        low = live & ((battery < low_battery_pct) | ((health & tc.HEALTH_BATTERY) != 0))
    if low.any():
        levels = ", ".join(f"{i} ({b:.0f} %)" if np.isfinite(b) else f"{i}" for i, b in
                           sorted(zip(ids[low].tolist(), battery[low].tolist()))[:12])
        out.append(f"low battery (< {low_battery_pct:g} %): agents {levels}")
    for kind in UNHEALTHY_KINDS:
        bad = live & ((health & tc.HEALTH_NAMES[kind]) != 0)
        if bad.any():
            out.append(f"unhealthy {kind}: agents {id_list(ids[bad])}")
    hands_off = live & (records["authority"] == tc.AUTHORITIES.index("hands-off"))
    if hands_off.any():
        out.append(f"hands-off (the vehicle's mode was changed by someone else): agents {id_list(ids[hands_off])}")
    refused = live & (records["cmds_refused"] > 0)
    if refused.any():
        reasons = sorted({tc.COMMAND_REFUSALS[c] if c < len(tc.COMMAND_REFUSALS) else "?"
                          for c in records["cmd_refusal"][refused].tolist()})
        out.append(f"refused a fleet command ({', '.join(reasons)}): agents {id_list(ids[refused])}")
    return out


def separation_alarm(ids: np.ndarray, pos_m: np.ndarray, d_min_m: float):
    """The closest pair among agents ``ids`` at ``pos_m`` (the fresh ones; non-finite rows ignored) and the
    alarm line when it is closer than ``d_min_m``:
    ``separation: agents 3 and 5 at 0.41 m < d_min 0.92 m`` (``(+n more pairs)`` when others are too).
    Returns ``(fisc_ground.fields.separation_stats.ClosestPair, line or None)``."""
    from fisc_ground.fields.separation_stats import closest_pair, pairs_closer_than

    pair = closest_pair(ids, pos_m)
    if not pair.distance_m < d_min_m:
        return pair, None
    more = int(pairs_closer_than(ids, pos_m, d_min_m).size) - 1
    return pair, (f"separation: agents {pair.id_a} and {pair.id_b} at {pair.distance_m:.2f} m < d_min {d_min_m:.2f} m"
                  + (f" (+{more} more pairs)" if more > 0 else ""))
