"""Telemetry version 2 from raw bytes: authority, battery, landed state, health, command refusals;
version 1 still decodes; the snapshot -> message mapping of health phrases."""

from __future__ import annotations

import math
import struct

import numpy as np

from fisc_agent.zenoh import telemetry_codec as tc
from fisc_agent.zenoh.fleet_commands import CommandCheck, CommandName
from fisc_agent.flight.readiness import HealthKind, HealthProblem
from fisc_agent.zenoh.telemetry import LinkStatus, telemetry_message

from .conftest import snap


def v2(**kw):
    base = dict(agent_id=7, seq=1, time_s=10.0, position_m=(0.0, 0.0, 0.0), velocity_m_s=(0.0, 0.0, 0.0),
                authority="hands-off", landed="in-air", battery_pct=42.4, health=frozenset({"estimator", "other"}),
                health_count=2, health_text="estimator: pos_horiz_abs bad", commands_refused=3,
                command_refusal="future", refused_command="go", ack_command="takeover", ack_seq=99)
    base.update(kw)
    return tc.Telemetry(**base)


def test_version_2_fields_are_the_documented_bytes():
    raw = tc.encode(v2())
    assert len(raw) == 148 and raw[0] == 2
    assert raw[94] == tc.ACK_COMMANDS.index("takeover") == 6
    assert raw[104:108] == bytes([tc.AUTHORITIES.index("hands-off"), tc.LANDED.index("in-air"), 42, 2])
    assert struct.unpack_from("<H", raw, 108)[0] == tc.HEALTH_ESTIMATOR | tc.HEALTH_OTHER
    assert raw[110] == tc.COMMAND_REFUSALS.index("future") and raw[111] == tc.ACK_COMMANDS.index("go")
    assert struct.unpack_from("<HH", raw, 112) == (3, 0)
    assert raw[116:148].rstrip(b"\0") == b"estimator: pos_horiz_abs bad"
    back = tc.decode(raw)
    assert back == v2(battery_pct=42.0)


def test_battery_and_text_edges():
    assert tc.decode(tc.encode(v2(battery_pct=None))).battery_pct is None
    assert tc.encode(v2(battery_pct=math.nan))[106] == tc.NO_BATTERY
    assert tc.encode(v2(battery_pct=100.4))[106] == 100 and tc.encode(v2(battery_pct=-3))[106] == 0
    assert tc.encode(v2(battery_pct=0.0))[106] == 0 and tc.decode(tc.encode(v2(battery_pct=0.0))).battery_pct == 0.0
    long = "é" * 40  # 80 bytes: cut at a character boundary within 32
    assert tc.decode(tc.encode(v2(health_text=long))).health_text == "é" * 16
    recs, ok = tc.decode_many([tc.encode(v2(battery_pct=None)), tc.encode(v2(battery_pct=55))])
    assert ok.all() and np.isnan(tc.battery_pct(recs)[0]) and tc.battery_pct(recs)[1] == 55


def test_version_1_messages_still_decode_with_unknown_new_fields():
    v1 = bytearray(tc.encode(v2(state="FLOW"))[:104])
    v1[0] = 1
    back = tc.decode(bytes(v1))
    assert back.state == "FLOW" and back.agent_id == 7 and back.ack_seq == 99
    assert (back.authority, back.landed, back.battery_pct, back.health, back.commands_refused) == \
        ("unknown", "unknown", None, frozenset(), 0)
    recs, ok = tc.decode_many([bytes(v1), tc.encode(v2()), bytes(v1) + b"\0"])
    assert ok.tolist() == [True, True, False]
    assert recs["version"].tolist()[:2] == [1, 2] and recs["battery_pct"][0] == tc.NO_BATTERY
    assert recs["authority"][1] == tc.AUTHORITIES.index("hands-off")


def test_wire_tables_match_the_typed_enums():
    from fisc_agent.flight.health import LandedState
    from fisc_agent.flight.mission_types import Authority

    assert tc.COMMAND_REFUSALS[1:] == tuple(c.value for c in CommandCheck)
    assert tc.ACK_COMMANDS[1:5] == ("hold", "resume", "land", "start-at")  # version-1 codes kept
    assert set(tc.ACK_COMMANDS[1:]) == {c.value for c in CommandName}
    assert set(tc.AUTHORITIES[1:]) == {a.value for a in Authority}
    assert set(tc.LANDED) == {s.value for s in LandedState}


def test_snapshot_health_problems_become_kinds_count_and_first_text():
    assert set(tc.HEALTH_NAMES) == {k.value for k in HealthKind}  # one wire flag per typed kind
    link = LinkStatus(maps_rejected=0, reject_reason="none", ack_command="go", ack_seq=5, zenoh_ok=True,
                      map_unsigned=False, commands_refused=2, refusal="stale", refused_command="hold")
    msg = telemetry_message(snap(authority="command", battery_pct=18.0, landed="in-air",
                                 health_problems=(HealthProblem(HealthKind.BATTERY, "battery 18 % < 25 %"),
                                                  HealthProblem(HealthKind.ESTIMATOR, "estimator: no GPS"))),
                            3, 1, link, 0.0)
    assert (msg.authority, msg.battery_pct, msg.landed, msg.health_count) == ("command", 18.0, "in-air", 2)
    assert msg.health == {"battery", "estimator"} and msg.health_text == "battery 18 % < 25 %"
    assert (msg.commands_refused, msg.command_refusal, msg.refused_command) == (2, "stale", "hold")
    healthy = telemetry_message(snap(), 3, 1, link, 0.0)
    assert healthy.health == frozenset() and healthy.health_count == 0 and healthy.battery_pct is None
    assert tc.decode(tc.encode(msg)).health == {"battery", "estimator"}
