"""Pure codecs from raw bytes: telemetry, fleet commands, map chunks, reassembly."""

from __future__ import annotations

import hashlib
import math
import struct

import numpy as np
import pytest
from nacl.signing import SigningKey

from fisc_agent.zenoh import telemetry_codec as tc
from fisc_agent.zenoh.command_gate import CommandGate
from fisc_agent.zenoh.fleet_commands import (CommandCheck, CommandError, FleetCommand, decode_command, encode_command,
                                             key_id_of)
from fisc_agent.map.codec import MapError, MapErrorKind
from fisc_agent.map.chunks import CHUNK_HEADER, MapAssembler, announce_message, parse_chunk, split_map
from fisc_agent.zenoh.maps import reject_code

SHA = "0123456789abcdef" * 4


def sample(**kw):
    base = dict(agent_id=42, seq=7, time_s=1_700_000_000.25, position_m=(1.5, -0.25, 0.75),
                velocity_m_s=(3.0, 0.5, -0.125), cv_index=311, state="FLOW", map_version=1234567890123,
                map_sha256=SHA, flags=frozenset({"armed", "mavlink_ok"}), maps_rejected=2,
                reject_reason="signature", position_age_s=0.05, heartbeat_age_s=0.5, ack_command="hold",
                ack_seq=1_700_000_000_123_456)
    base.update(kw)
    return tc.Telemetry(**base)


def test_telemetry_layout_is_the_documented_raw_bytes():
    raw = tc.encode(sample())
    assert len(raw) == tc.SIZE == 148
    assert raw[0] == 2  # version byte first
    assert raw[1] == tc.STATES.index("FLOW")
    assert raw[2] == tc.FLAG_ARMED | tc.FLAG_MAVLINK_OK
    assert raw[3] == tc.REJECT_REASONS.index("signature")
    assert struct.unpack_from("<II", raw, 4) == (42, 7)
    assert struct.unpack_from("<d", raw, 12)[0] == 1_700_000_000.25
    assert struct.unpack_from("<3f", raw, 20) == (1.5, -0.25, 0.75)
    assert struct.unpack_from("<i", raw, 44)[0] == 311
    assert struct.unpack_from("<Q", raw, 48)[0] == 1234567890123
    assert raw[56:88].hex() == SHA
    assert struct.unpack_from("<HHH", raw, 88) == (2, 50, 500)
    assert struct.unpack_from("<Q", raw, 96)[0] == 1_700_000_000_123_456


def test_telemetry_round_trip_and_batch_decode():
    t = sample()
    assert tc.decode(tc.encode(t)) == t
    empty = tc.Telemetry(agent_id=1, seq=0, time_s=0.0, position_m=(math.nan,) * 3, velocity_m_s=(0, 0, 0))
    back = tc.decode(tc.encode(empty))
    assert back.map_sha256 == "" and math.isinf(back.position_age_s) and back.state == "UNKNOWN"
    assert all(math.isnan(v) for v in back.position_m)
    recs, ok = tc.decode_many([tc.encode(t), b"\x03" + bytes(147), b"\x02short", tc.encode(empty)])
    assert ok.tolist() == [True, False, False, True]
    assert recs["agent_id"][0] == 42 and recs["cv_index"][0] == 311
    assert tc.sha_hex(recs[:1]) == [SHA] and tc.state_names(recs["state"][:1]) == ["FLOW"]


@pytest.mark.parametrize("raw, why", [(b"", "empty"), (b"\x09" + bytes(147), "version 9"),
                                      (b"\x01" + bytes(50), "104 bytes"), (b"\x02" + bytes(103), "148 bytes")])
def test_telemetry_refuses_unknown_versions_and_sizes(raw, why):
    with pytest.raises(tc.TelemetryError, match=why):
        tc.decode(raw)


def test_unknown_state_names_are_sent_as_unknown_and_ages_saturate():
    back = tc.decode(tc.encode(sample(state="SOMETHING_NEW", position_age_s=1e9)))
    assert back.state == "UNKNOWN" and back.position_age_s == 65.534


def cmd(name="hold", seq=10, issued=1000.0, **kw):
    return FleetCommand(name=name, swarm="alpha", seq=seq, issued_unix_s=issued, **kw)


def test_command_round_trip_signed_and_layout():
    key = SigningKey.generate()
    raw = encode_command(cmd("start-at", start_at_unix_s=2000.5, targets=(3,)), key.encode())
    assert raw[:4] == b"FCMD" and raw[4] == 2 and raw[5] == 4 and raw[6] == 1
    back = decode_command(raw, [key.verify_key.encode()])
    assert back == cmd("start-at", start_at_unix_s=2000.5, targets=(3,), signed=True,
                       key_id=key_id_of(key.verify_key.encode()))
    assert back.applies_to(3) and not back.applies_to(4)
    assert cmd().targets == () and cmd().applies_to(99)


def test_command_signature_checks():
    key, stranger = SigningKey.generate(), SigningKey.generate()
    trusted = [key.verify_key.encode()]
    raw = bytearray(encode_command(cmd(), key.encode()))
    raw[5] = 3  # hold -> land, signature no longer matches
    with pytest.raises(CommandError, match="signature"):
        decode_command(bytes(raw), trusted)
    with pytest.raises(CommandError, match="not signed by a trusted key"):
        decode_command(encode_command(cmd(), stranger.encode()), trusted)
    with pytest.raises(CommandError, match="unsigned"):
        decode_command(encode_command(cmd(), None), trusted)
    assert not decode_command(encode_command(cmd(), None), None, allow_unsigned=True).signed
    with pytest.raises(CommandError, match="truncated") as err:
        decode_command(b"FCMD", trusted)
    assert err.value.check is CommandCheck.TRUNCATED
    bad_magic = b"XCMD" + encode_command(cmd(), key.encode())[4:]
    with pytest.raises(CommandError) as err:
        decode_command(bad_magic, trusted)
    assert err.value.check is CommandCheck.MAGIC and str(err.value).startswith("magic: ")


def test_gate_refuses_replays_reorders_stale_future_and_foreign_commands():
    gate = CommandGate("alpha", agent_id=5, max_age_s=30, max_future_s=5)
    assert gate.check(cmd(seq=10, issued=1000.0), now_unix_s=1001.0).seq == 10
    for bad, why in [(cmd(seq=10, issued=1000.0), "replay"), (cmd(seq=9, issued=1000.5), "replay"),
                     (cmd(seq=11, issued=900.0), "stale"), (cmd(seq=12, issued=1100.0), "future"),
                     (FleetCommand("hold", "beta", 13, 1001.0), "swarm"), (cmd(seq=14, targets=(6,)), "target")]:
        with pytest.raises(CommandError, match=why) as err:
            gate.check(bad, now_unix_s=1001.0)
        assert err.value.check is CommandCheck(why)  # the typed check the agent's counters key on
    assert gate.check(cmd(seq=15, issued=1000.9), now_unix_s=1001.0).seq == 15


def test_chunks_round_trip_in_any_order_with_duplicates():
    blob = bytes(np.random.default_rng(0).integers(0, 256, 10_000, dtype=np.uint8))
    chunks = split_map(blob, 42, chunk_bytes=1000)
    assert len(chunks) == 10
    head, data = parse_chunk(chunks[3])
    assert (head.index, head.count, head.offset, head.total_bytes, head.map_version) == (3, 10, 3000, 10_000, 42)
    assert head.sha256 == hashlib.sha256(blob).digest() and bytes(data) == blob[3000:4000]
    asm = MapAssembler()
    order = [9, 0, 0, 5, 1, 2, 3, 4, 6, 7, 8, 8]
    out = [asm.feed(chunks[i])[1] for i in order]
    assert all(o is None for o in out[:-2]) and bytes(out[-2]) == blob and out[-1] is None


def test_assembler_refuses_forged_chunks_and_ignores_old_versions():
    blob = bytes(range(256)) * 20
    chunks = split_map(blob, 42, chunk_bytes=1000)
    forged = bytearray(chunks[1])
    forged[-1] ^= 1
    asm = MapAssembler()
    for c in [chunks[0], bytes(forged)] + chunks[2:]:
        try:
            asm.feed(c)
        except MapError as exc:
            assert "sha256" in str(exc) and reject_code(exc) == "chunks"
            break
    else:
        pytest.fail("forged chunk not detected")
    asm.accept(50)
    assert all(asm.feed(c)[1] is None for c in chunks) and not asm.pending
    with pytest.raises(MapError, match="limit"):
        MapAssembler(max_bytes=100).feed(split_map(bytes(1000), 60, 500)[0])
    with pytest.raises(MapError, match="magic"):
        parse_chunk(b"XXXX" + bytes(CHUNK_HEADER.size))
    head, data = parse_chunk(announce_message(b"\1" * 32, 7, 100, 1))
    assert head.kind == 2 and head.map_version == 7 and len(data) == 0


def test_reject_codes_name_the_failed_check():
    assert reject_code(MapError(MapErrorKind.SHA256, "content hash does not match", "fisc/a/map")) == "sha256"
    assert reject_code(MapError(MapErrorKind.SIGNATURE, "signed by a key that is not trusted")) == "signature"
    # the kind decides, never the text: a detail that mentions another check does not fool it
    assert reject_code(MapError(MapErrorKind.SCHEMA, "sha256: signature: looks like other checks")) == "schema"
    assert reject_code(MapError(MapErrorKind.N_STAR, "values must lie in 1..10")) == "other"  # no telemetry code
    assert reject_code(ValueError("signature: not a MapError")) == "other"


def test_start_at_times_are_utc_and_commands_are_stamped_increasing():
    from fisc_ground.zenoh.fleet import make_command, parse_utc

    assert parse_utc("2026-05-01T12:00:00Z") == parse_utc("2026-05-01T12:00:00") == 1777636800.0
    assert parse_utc("2026-05-01T14:00:00+02:00") == 1777636800.0
    with pytest.raises(ValueError, match="ISO-8601"):
        parse_utc("tomorrow")
    a, b = make_command("hold", "alpha", now_unix_s=100.0), make_command("resume", "alpha", now_unix_s=100.001)
    assert b.seq > a.seq and a.targets == ()
    start = make_command("start-at", "alpha", start_at_unix_s=1777636800.0)
    assert decode_command(encode_command(start, None), None, allow_unsigned=True).start_at_unix_s == 1777636800.0
