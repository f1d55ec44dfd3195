"""Telemetry message of one agent from its ``AgentSnapshot`` and its Zenoh link's counters (pure).

Every field comes from a named field of the typed snapshot (``fisc_agent.runner.AgentSnapshot``);
the link adds what only it knows: the refused maps, the last accepted fleet command, the newest
refused one, whether its publisher is up and whether the map in use is unsigned.

Health.  ``AgentSnapshot.health_problems`` are typed (``fisc_agent.flight.readiness.HealthProblem``:
a kind and a phrase); telemetry carries their number, the first phrase (32 bytes) and one flag per
kind (``telemetry_codec.HEALTH_NAMES``, the ``HealthKind`` values).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from fisc_agent.zenoh import telemetry_codec as tc
from fisc_agent.flight.tick import AgentSnapshot

POSITION_FRESH_S = 1.0
"""A position fix younger than this sets the ``position_fresh`` flag [s]."""
_NO_VEC = (math.nan, math.nan, math.nan)


@dataclass(frozen=True)
class LinkStatus:
    """What the agent's Zenoh link adds to a telemetry message."""

    maps_rejected: int
    """Maps refused so far."""
    reject_reason: str
    """``REJECT_REASONS`` name of the last refusal (``none``: none)."""
    ack_command: str
    """Last fleet command accepted (``none``: none)."""
    ack_seq: int
    """Its sequence number."""
    zenoh_ok: bool
    """The link's telemetry publisher is declared."""
    map_unsigned: bool
    """The map in use is unsigned (``--allow-unsigned``)."""
    commands_refused: int = 0
    """Fleet commands refused so far."""
    refusal: str = "none"
    """``CommandCheck`` value of the newest refusal ("none")."""
    refused_command: str = "none"
    """Name of the command it refused ("none": it did not decode)."""


def _vec3(value: tuple[float, float, float] | None) -> tuple[float, float, float]:
    if value is None:
        return _NO_VEC
    x, y, z = (float(v) for v in value)
    return (x, y, z)


def telemetry_message(snap: AgentSnapshot | None, agent_id: int, seq: int, link: LinkStatus,
                      now_s: float) -> tc.Telemetry:
    """The telemetry of ``agent_id`` for ``snap`` (None before the runner's first tick: state
    ``WAIT_MAP``, no position, time ``now_s``)."""
    flags = {name for name, on in (("zenoh_ok", link.zenoh_ok), ("map_unsigned", link.map_unsigned)) if on}
    common = dict(agent_id=int(agent_id), seq=int(seq), maps_rejected=link.maps_rejected,
                  reject_reason=link.reject_reason, ack_command=link.ack_command, ack_seq=link.ack_seq,
                  commands_refused=link.commands_refused, command_refusal=link.refusal,
                  refused_command=link.refused_command)
    if snap is None:
        return tc.Telemetry(time_s=float(now_s), position_m=_NO_VEC, velocity_m_s=_NO_VEC, state="WAIT_MAP",
                            flags=frozenset(flags), **common)
    for name, on in (("armed", snap.armed), ("mavlink_ok", snap.link_ok), ("outside_map", snap.outside_map),
                     ("failsafe", snap.failsafe), ("position_fresh", snap.position_age_s < POSITION_FRESH_S)):
        if on:
            flags.add(name)
    state = snap.state
    if snap.map_sha256 is None and state == "WAIT_POSITION":
        state = "WAIT_MAP"  # on the ground, unarmed, until a valid map arrives
    return tc.Telemetry(
        time_s=float(snap.wall_time_s), position_m=_vec3(snap.position_map_m),
        velocity_m_s=_vec3(snap.velocity_map_m_s), cv_index=int(snap.cv_id), state=state,
        map_version=int(snap.map_version or 0), map_sha256=snap.map_sha256 or "", flags=frozenset(flags),
        position_age_s=float(snap.position_age_s), heartbeat_age_s=float(snap.heartbeat_age_s),
        authority=str(snap.authority), landed=str(snap.landed), battery_pct=snap.battery_pct,
        health=frozenset(p.kind.value for p in snap.health_problems), health_count=len(snap.health_problems),
        health_text=snap.health_problems[0].text if snap.health_problems else "", **common)
