"""Issue 12, agent side, pure cores: chunk reassembly, MAVLink framing and identity, position
gate, rate-limited log.  Property-based (hypothesis) where the input is raw bytes or numbers a
peer controls; each property is also what a process-level test in this directory relies on."""

from __future__ import annotations

import hashlib
import logging
import math
import os
import tracemalloc

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fisc_agent.map.chunks import (CHUNK_HEADER, CHUNK_MAGIC, CHUNK_VERSION, KIND_CHUNK,
                                   AssemblyLimits, DropReason, MapAssembler, announce_message, parse_chunk,
                                   split_map)
from fisc_agent.map.codec import MapError
from fisc_agent.mavlink.framing import (MAX_BAD_FRAMES_PER_DATAGRAM, AutopilotTracker, HeartbeatVerdict,
                                      parse_datagram)
from fisc_agent.flight.position_gate import GateVerdict, PositionGate, PositionGateConfig
from fisc_agent.common.ratelimit import OVERFLOW_KEY, RateLimitedLog

U64 = (1 << 64) - 1


def header(version: int, total: int, index: int = 0, count: int = 1, offset: int = 0, sha: bytes | None = None,
           kind: int = KIND_CHUNK) -> bytes:
    return CHUNK_HEADER.pack(CHUNK_MAGIC, CHUNK_VERSION, kind, 0, version, sha or os.urandom(32), total, index,
                             count, offset)


# ------------------------------------------------------------------------------------- chunks
def test_an_oversized_header_costs_only_the_bytes_it_carries():
    """Finding 1: the old assembler allocated the claimed 2^30 bytes at the first chunk."""
    asm = MapAssembler()
    tracemalloc.start()
    try:
        for k in range(20):
            asm.feed(header(U64 - 20 + k, 1 << 30, count=1 << 20) + os.urandom(11), now_s=k * 0.1)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20, f"peak {peak} bytes for 20 messages of 83 bytes"
    assert len(asm.pending) <= asm.limits.max_pending
    assert asm.buffered_bytes <= asm.limits.max_pending * (11 + 256)
    assert [d.reason for d in asm.drain_drops()] == [DropReason.EVICTED] * (20 - asm.limits.max_pending)


def test_unfinished_highest_version_streams_do_not_block_a_later_map():
    """Finding 2: streams claiming map_version 2^64-1 and 2^64-2 that never complete."""
    asm = MapAssembler()
    for v in (U64, U64 - 1):
        asm.feed(header(v, 4096, count=2) + bytes(2048), now_s=0.0)
    blob = os.urandom(5000)
    done = [asm.feed(c, now_s=1.0)[1] for c in split_map(blob, 7, 1000)]
    assert bytes(done[-1]) == blob
    asm.feed(announce_message(b"\0" * 32, 8, 10, 1), now_s=20.0)  # any message runs the timeout
    assert not asm.pending
    assert [d.reason for d in asm.drain_drops()] == [DropReason.TIMEOUT, DropReason.TIMEOUT]


def test_the_announced_map_keeps_its_slot_against_a_flood_of_new_streams():
    asm = MapAssembler(limits=AssemblyLimits(max_pending=2))
    blob = os.urandom(3000)
    chunks = split_map(blob, 5, 1000)
    sha = hashlib.sha256(blob).digest()
    asm.feed(announce_message(sha, 5, len(blob), 3), now_s=0.0)
    asm.feed(chunks[0], now_s=0.0)
    for k in range(50):  # newer streams, most recent chunk: they evict each other, not the announced map
        asm.feed(header(U64 - k, 1 << 20, count=4) + bytes(100), now_s=0.1 + k * 0.01)
    assert sha in asm.pending
    asm.feed(chunks[1], now_s=1.0)
    assert bytes(asm.feed(chunks[2], now_s=1.0)[1]) == blob


def test_the_byte_budget_drops_the_lowest_priority_map():
    asm = MapAssembler(limits=AssemblyLimits(budget_bytes=10_000, max_map_bytes=10_000))
    a, b = os.urandom(9000), os.urandom(9000)
    for c in split_map(a, 3, 3000)[:2]:
        asm.feed(c, now_s=0.0)
    for c in split_map(b, 4, 3000)[:2]:  # 4 x (3000 + overhead) > 10 000: the older map goes
        asm.feed(c, now_s=1.0)
    assert list(asm.pending) == [hashlib.sha256(b).digest()] and asm.buffered_bytes <= 10_000
    assert [d.reason for d in asm.drain_drops()] == [DropReason.BUDGET]
    with pytest.raises(MapError, match="limit"):
        asm.feed(header(5, 20_000, count=5) + bytes(10), now_s=2.0)


def test_old_and_replayed_maps_are_reported_once_and_the_map_in_use_is_ignored():
    asm = MapAssembler()
    current, older, oldest = os.urandom(300), os.urandom(300), os.urandom(300)
    for blob, v in ((oldest, 5), (current, 10)):
        assert asm.feed(split_map(blob, v)[0])[1] is not None
    asm.accept(10, hashlib.sha256(current).digest())
    for _ in range(3):
        for blob, v in ((current, 10), (older, 7), (oldest, 5)):
            assert asm.feed(split_map(blob, v)[0])[1] is None
    drops = asm.drain_drops()
    assert [(d.reason, d.head.map_version) for d in drops] == [(DropReason.OLD_VERSION, 7),
                                                               (DropReason.OLD_VERSION, 5)]



def test_a_map_of_the_installed_version_with_another_hash_is_refused_and_told_apart_from_the_installed_one():
    """Issue 38: the version rule at equality.  Same version, other content: refused as not newer (reported
    once, like an older map); the installed map itself sent again: ignored without a report; one version up:
    assembled."""
    asm = MapAssembler()
    installed, rival, newer = os.urandom(300), os.urandom(300), os.urandom(300)
    assert asm.feed(split_map(installed, 10)[0])[1] is not None
    asm.accept(10, hashlib.sha256(installed).digest())
    rival_head = asm.feed(split_map(rival, 10)[0])[0]
    assert not asm.wanted(rival_head)
    assert asm.feed(split_map(rival, 10)[0])[1] is None
    assert asm.feed(split_map(installed, 10)[0])[1] is None
    assert [(d.reason, d.head.sha256) for d in asm.drain_drops()] == [(DropReason.OLD_VERSION, rival_head.sha256)]
    assert asm.wanted(parse_chunk(split_map(newer, 11)[0])[0])
    assert asm.feed(split_map(newer, 11)[0])[1] == newer
    assert asm.drain_drops() == []

def test_the_hash_caches_are_bounded():
    """Finding 6: every bogus map's hash was kept forever."""
    asm = MapAssembler(limits=AssemblyLimits(max_remembered=16))
    asm.accept(1_000_000, None)
    for k in range(500):
        asm.feed(header(k, 100) + bytes(100))  # old versions: refused by header
        with pytest.raises(MapError, match="limit"):
            asm.feed(header(2_000_000 + k, U64 >> 1) + bytes(1))  # too large: refused once per map
    for k in range(500):
        blob = os.urandom(50)
        asm.feed(split_map(blob, 2_000_000 + k)[0])  # completed (e.g. then refused by signature)
    assert len(asm.refused) == 16 and len(asm.done) == 16


def test_overlapping_or_disagreeing_chunks_are_refused():
    asm = MapAssembler()
    asm.feed(header(3, 100, 0, 2, 0, sha=b"a" * 32) + bytes(60))
    with pytest.raises(MapError, match="overlaps"):
        asm.feed(header(3, 100, 1, 2, 50, sha=b"a" * 32) + bytes(50))
    asm.feed(header(3, 100, 0, 2, 0, sha=b"b" * 32) + bytes(50))
    with pytest.raises(MapError, match="disagrees"):
        asm.feed(header(4, 100, 1, 2, 50, sha=b"b" * 32) + bytes(50))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.binary(max_size=200), max_size=30))
def test_fuzz_any_bytes_only_ever_raise_map_error_and_stay_within_limits(messages):
    limits = AssemblyLimits(max_pending=3, budget_bytes=4096, max_map_bytes=4096, max_remembered=8)
    asm = MapAssembler(limits=limits)
    for k, raw in enumerate(messages):
        msg = CHUNK_MAGIC + bytes([CHUNK_VERSION]) + raw if k % 2 else raw  # half of them get past the magic
        try:
            asm.feed(msg, now_s=k * 0.5)
        except MapError:
            pass
        assert len(asm.pending) <= 3 and 0 <= asm.buffered_bytes <= 4096
        assert len(asm.done) <= 8 and len(asm.refused) <= 8


@settings(max_examples=150, deadline=None)
@given(st.binary(min_size=1, max_size=3000), st.integers(1, 700), st.randoms(use_true_random=False),
       st.lists(st.binary(max_size=120), max_size=10))
def test_fuzz_a_genuine_map_survives_any_order_duplicates_and_junk(blob, chunk_bytes, rnd, junk):
    chunks = split_map(blob, 9, chunk_bytes)
    stream = chunks + [rnd.choice(chunks) for _ in range(len(chunks) // 2)] + junk
    rnd.shuffle(stream)
    asm = MapAssembler()
    got = []
    for msg in stream:
        try:
            _, out = asm.feed(msg)
        except MapError:
            continue
        if out is not None:
            got.append(bytes(out))
    assert got == [blob]


# ------------------------------------------------------------------------------------- MAVLink
def _mav(system=1, component=1):
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    return mavlink.MAVLink(None, srcSystem=system, srcComponent=component)


DECODER = _mav(0, 0)


def _position_frame(x=1.0):
    enc = _mav()
    return enc.local_position_ned_encode(10, x, 2.0, -3.0, 0.1, 0.2, 0.3).pack(enc)


def test_a_partial_frame_is_forgotten_with_its_datagram():
    """Finding 6: with a stream parser, a cut frame swallowed the start of the next datagram."""
    full = _position_frame()
    cut = parse_datagram(full[:20], DECODER.decode)
    assert cut.messages == () and cut.bad_bytes == 20
    nxt = parse_datagram(full, DECODER.decode)
    assert [m.get_type() for m in nxt.messages] == ["LOCAL_POSITION_NED"] and nxt.bad_bytes == 0


def test_frames_around_garbage_in_one_datagram_are_decoded():
    a, b = _position_frame(1.0), _position_frame(2.0)
    scan = parse_datagram(b"\x00\x13" + a + b"junk" + b, DECODER.decode)
    assert [m.x for m in scan.messages] == [1.0, 2.0] and scan.bad_bytes == 6


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=600))
def test_fuzz_any_datagram_parses_without_raising_and_accounts_for_every_byte(data):
    scan = parse_datagram(data, DECODER.decode)
    framed = sum(len(m.get_msgbuf()) for m in scan.messages)
    assert framed + scan.bad_bytes == len(data)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300), st.floats(-1e6, 1e6))
def test_fuzz_garbage_datagrams_never_hide_the_next_fix(garbage, x):
    parse_datagram(garbage, DECODER.decode)  # stateless: nothing carries over
    scan = parse_datagram(_position_frame(x), DECODER.decode)
    assert len(scan.messages) == 1 and scan.messages[0].x == pytest.approx(x, rel=1e-6)


def test_work_per_datagram_is_bounded():
    bogus = bytes([0xFD, 10, 0, 0, 0, 1, 1, 0, 0, 0]) + bytes(12)  # header + payload + wrong CRC
    calls = []

    def decode(buf):
        calls.append(len(buf))
        return DECODER.decode(buf)
    scan = parse_datagram(bogus * 1000, decode)
    assert scan.dropped_rest and len(calls) == MAX_BAD_FRAMES_PER_DATAGRAM and scan.messages == ()


def test_only_the_autopilot_changes_state_and_a_stray_first_heartbeat_does_not_hold_forever():
    t = AutopilotTracker(relock_after_s=3.0)
    assert t.on_heartbeat(1, 1, "ap", 2, 12, armed=True, now_s=0.0) == HeartbeatVerdict.LOCKED
    # finding 4: same system, other component, generic autopilot, disarmed
    assert t.on_heartbeat(1, 100, "ap", 2, 0, armed=False, now_s=0.5) == HeartbeatVerdict.FOREIGN
    assert t.on_heartbeat(1, 1, "elsewhere", 2, 12, armed=False, now_s=0.6) == HeartbeatVerdict.FOREIGN
    assert t.on_heartbeat(6, 190, "gcs", 6, 8, armed=False, now_s=0.7) == HeartbeatVerdict.NOT_A_VEHICLE
    assert t.is_autopilot(1, 1, "ap") and not t.is_autopilot(1, 100, "ap") and t.target_armed
    # armed: never re-locks, even after a long silence
    assert t.on_heartbeat(42, 1, "x", 2, 12, armed=False, now_s=60.0) == HeartbeatVerdict.FOREIGN
    # finding 6: a stranger first, the autopilot later
    t = AutopilotTracker(relock_after_s=3.0)
    assert t.on_heartbeat(42, 1, "x", 2, 12, armed=False, now_s=0.0) == HeartbeatVerdict.LOCKED
    assert t.on_heartbeat(1, 1, "ap", 2, 12, armed=False, now_s=1.0) == HeartbeatVerdict.FOREIGN
    assert t.on_heartbeat(1, 1, "ap", 2, 12, armed=False, now_s=3.5) == HeartbeatVerdict.LOCKED
    assert t.target.system == 1 and t.relocks == 1
    # an unknown autopilot type gives way to PX4/ArduPilot at once (while disarmed)
    t = AutopilotTracker()
    t.on_heartbeat(1, 100, "ap", 2, 0, armed=False, now_s=0.0)
    assert t.on_heartbeat(1, 1, "ap", 2, 3, armed=False, now_s=0.1) == HeartbeatVerdict.LOCKED


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 255), st.integers(0, 255), st.sampled_from(["ap", "x"]),
                          st.integers(0, 40), st.integers(0, 20), st.booleans(), st.floats(0, 0.5)), max_size=40))
def test_fuzz_no_heartbeat_moves_the_lock_off_an_armed_autopilot(beats):
    t = AutopilotTracker()
    t.on_heartbeat(1, 1, "ap", 2, 12, armed=True, now_s=0.0)
    now = 0.0
    for system, comp, addr, mav_type, autopilot, armed, dt in beats:
        now += dt
        if (system, comp, addr) != (1, 1, "ap"):
            t.on_heartbeat(system, comp, addr, mav_type, autopilot, armed, now)
        assert (t.target.system, t.target.component, t.target.address) == (1, 1, "ap")



# Boundaries of the chunk codec and the assembler (issue 38).
OVER = 256  # CHUNK_OVERHEAD_BYTES charged per chunk held


def _chunk_error(msg) -> str:
    with pytest.raises(MapError) as err:
        parse_chunk(msg)
    return str(err.value)


def test_parse_chunk_refusals_at_their_limits():
    sha = bytes(32)
    assert _chunk_error(bytes(CHUNK_HEADER.size - 1)) == "chunks: message of 71 bytes is shorter than the chunk header"
    assert parse_chunk(announce_message(sha, 1, 10, 1))[0].kind == 2  # exactly a header: fine
    assert _chunk_error(b"XMCH" + header(1, 10)[4:]) == "chunks: bad magic (not a FISC map chunk)"
    for version in (0, 2):
        raw = CHUNK_HEADER.pack(CHUNK_MAGIC, version, KIND_CHUNK, 0, 1, sha, 10, 0, 1, 0)
        assert _chunk_error(raw) == f"chunks: chunk format {version} is not supported"
    for kind in (0, 3):
        assert _chunk_error(header(1, 10, kind=kind)) == f"chunks: unknown message kind {kind}"
    fits = [(dict(index=1, count=2, offset=5), 5), (dict(index=0, count=1, offset=0), 0)]  # last byte; an empty map
    for kw, n in fits:
        parse_chunk(header(1, 10 if n else 0, **kw) + bytes(n))
    misfits = [(dict(index=2, count=2, offset=0), 5, "chunk 2/2 at offset 0 does not fit a 10-byte map"),
               (dict(index=1, count=2, offset=6), 5, "chunk 1/2 at offset 6 does not fit a 10-byte map"),
               (dict(index=1, count=2, offset=5), 0, "chunk 1/2 at offset 5 does not fit a 10-byte map")]
    for kw, n, why in misfits:
        assert _chunk_error(header(1, 10, **kw) + bytes(n)) == "chunks: " + why
    assert parse_chunk(header(1, 10, kind=2, index=9, count=1, offset=99))[0].index == 9  # announcements: no fit


def test_split_map_and_announce_carry_every_header_field():
    blob = bytes(range(10))
    sha = hashlib.sha256(blob).digest()
    for chunk_bytes, count in ((1, 10), (4, 3), (5, 2), (10, 1), (11, 1)):
        parts = [parse_chunk(m) for m in split_map(blob, 7, chunk_bytes)]
        assert [(h.kind, h.map_version, h.sha256, h.total_bytes, h.index, h.count, h.offset) for h, _ in parts] == \
            [(KIND_CHUNK, 7, sha, 10, i, count, i * chunk_bytes) for i in range(count)]
        assert b"".join(bytes(d) for _, d in parts) == blob
    assert len(split_map(b"", 3)) == 1
    with pytest.raises(ValueError, match="^chunk_bytes must be > 0$"):
        split_map(blob, 7, 0)
    head = parse_chunk(announce_message(sha, 7, 10, 3))[0]
    assert (head.kind, head.map_version, head.sha256, head.total_bytes, head.index, head.count, head.offset) == \
        (2, 7, sha, 10, 0, 3, 0)


@pytest.mark.parametrize("name", ["max_map_bytes", "budget_bytes", "max_pending", "max_announced", "max_remembered"])
def test_assembly_count_limits_are_at_least_one(name):
    assert getattr(AssemblyLimits(**{name: 1}), name) == 1
    with pytest.raises(ValueError, match=f"^AssemblyLimits.{name} must be >= 1, got 0$"):
        AssemblyLimits(**{name: 0})


@pytest.mark.parametrize("name", ["stall_timeout_s", "announce_ttl_s"])
def test_assembly_time_limits_are_positive(name):
    assert getattr(AssemblyLimits(**{name: 0.5}), name) == 0.5
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match=f"^AssemblyLimits.{name} must be > 0, got {bad}$"):
            AssemblyLimits(**{name: bad})


def test_the_assembler_options_set_the_limits_and_a_fresh_one_takes_version_1():
    asm = MapAssembler(max_bytes=5000, max_pending=2)
    assert (asm.max_bytes, asm.limits.max_pending, asm.limits.budget_bytes) == (5000, 2, AssemblyLimits().budget_bytes)
    assert MapAssembler(max_bytes=1 << 31).limits.budget_bytes == 1 << 31  # the budget holds at least one map
    assert MapAssembler(max_pending=3).limits.max_map_bytes == AssemblyLimits().max_map_bytes
    fresh = MapAssembler()
    assert fresh.floor_version == 0 and fresh.buffered_bytes == 0
    assert fresh.feed(split_map(b"v1", 1)[0])[1] == b"v1"


def test_bytes_held_are_charged_and_given_back_exactly():
    asm = MapAssembler()
    blob = os.urandom(30)
    c = split_map(blob, 3, 10)
    asm.feed(c[0], now_s=0.0)
    assert asm.buffered_bytes == 10 + OVER
    asm.feed(c[0], now_s=0.0)  # a duplicate costs nothing
    assert asm.buffered_bytes == 10 + OVER
    asm.feed(c[2], now_s=0.0)  # ahead of the gap
    assert asm.buffered_bytes == 2 * (10 + OVER) and asm.pending[hashlib.sha256(blob).digest()].received == 20
    assert bytes(asm.feed(c[1], now_s=0.0)[1]) == blob
    assert asm.buffered_bytes == 0 and not asm.pending
    other = os.urandom(30)
    asm.feed(split_map(other, 4, 10)[1], now_s=1.0)
    asm.expire(1.0 + 10.0)  # exactly stall_timeout_s: kept
    assert asm.pending and asm.drain_drops() == []
    asm.expire(math.nextafter(11.0, 12.0))  # one step later: dropped, its bytes given back
    drops = asm.drain_drops()
    assert [(d.reason, d.head.index, d.received_bytes) for d in drops] == [(DropReason.TIMEOUT, 1, 10)]
    assert asm.buffered_bytes == 0 and not asm.pending


def test_announcements_and_progress_at_their_windows():
    asm = MapAssembler()
    sha = os.urandom(32)
    asm.feed(announce_message(sha, 5, 100, 2), now_s=10.0)
    assert asm.announced(sha, 15.0) and not asm.announced(sha, math.nextafter(15.0, 16.0))
    assert not asm.announced(os.urandom(32), 10.0)
    blob = os.urandom(20)
    key = hashlib.sha256(blob).digest()
    assert not asm.progressing(key, 10.0, 1.0)  # nothing received
    asm.feed(split_map(blob, 5, 10)[0], now_s=10.0)
    assert asm.progressing(key, 10.5, 1.0) and not asm.progressing(key, 11.0, 1.0)  # within_s: strict


def test_announcements_remembered_are_bounded_oldest_first():
    asm = MapAssembler(limits=AssemblyLimits(max_announced=2))
    a, b, c = (os.urandom(32) for _ in range(3))
    for k, sha in enumerate((a, b)):
        asm.feed(announce_message(sha, 5, 100, 2), now_s=float(k))
    assert asm.announced(a, 1.0) and asm.announced(b, 1.0)  # exactly max_announced: both kept
    asm.feed(announce_message(c, 5, 100, 2), now_s=2.0)
    assert not asm.announced(a, 2.0) and asm.announced(b, 2.0) and asm.announced(c, 2.0)


def test_wanted_is_newer_than_installed_and_neither_done_nor_refused():
    asm = MapAssembler()
    done_blob = os.urandom(10)
    asm.feed(split_map(done_blob, 8)[0])
    asm.accept(5, os.urandom(32))
    head = lambda v, sha=None: parse_chunk(announce_message(sha or os.urandom(32), v, 10, 1))[0]  # noqa: E731
    assert asm.wanted(head(6)) and not asm.wanted(head(5)) and not asm.wanted(head(4))
    assert not asm.wanted(head(8, hashlib.sha256(done_blob).digest()))  # completed already
    big = os.urandom(32)  # refused by its size
    with pytest.raises(MapError):
        asm.feed(header(9, 1 << 40, sha=big))
    assert not asm.wanted(head(9, big))


def test_verify_accepts_the_right_bytes_and_forgets_a_wrong_map():
    asm = MapAssembler()
    blob = os.urandom(50)
    head, got = asm.feed(split_map(blob, 3)[0])
    asm.verify(head, got)
    assert head.sha256 in asm.done
    with pytest.raises(MapError) as err:
        asm.verify(head, bytearray(os.urandom(50)))
    assert str(err.value) == "chunks: reassembled map does not match its sha256 (corrupted or forged chunks)"
    assert head.sha256 not in asm.done


def test_size_limits_at_equality_and_a_too_large_map_is_refused_once():
    asm = MapAssembler(limits=AssemblyLimits(max_map_bytes=100, budget_bytes=1000))
    asm.feed(header(1, 100, count=2) + bytes(50))  # exactly the limit: taken
    with pytest.raises(MapError) as err:
        asm.feed(header(1, 101, count=2, sha=b"L" * 32) + bytes(50))
    assert str(err.value) == "chunks: map of 101 bytes exceeds the 100-byte limit"
    assert asm.feed(header(1, 101, count=2, sha=b"L" * 32) + bytes(50))[1] is None  # then ignored
    tight = MapAssembler(limits=AssemblyLimits(max_map_bytes=1000, budget_bytes=100))
    tight.feed(header(1, 100, count=4) + bytes(1))  # the budget, exactly: taken
    with pytest.raises(MapError, match="^chunks: map of 101 bytes exceeds the 100-byte limit$"):
        tight.feed(header(1, 101, count=4) + bytes(1))


def test_a_newcomer_of_equal_priority_takes_the_slot_a_lower_one_gets_no_slot():
    asm = MapAssembler(limits=AssemblyLimits(max_pending=1))
    first = header(1, 100, count=2, sha=b"A" * 32) + bytes(50)
    second = header(1, 100, count=2, sha=b"B" * 32) + bytes(50)
    asm.feed(first, now_s=1.0)
    asm.feed(second, now_s=1.0)  # same time, neither announced: equal priority, the newcomer wins
    assert list(asm.pending) == [b"B" * 32]
    assert [(d.reason, d.head.sha256, d.received_bytes) for d in asm.drain_drops()] == [(DropReason.EVICTED, b"A" * 32, 50)]
    asm.feed(announce_message(b"B" * 32, 1, 100, 2), now_s=2.0)
    asm.feed(first, now_s=3.0)  # the announced map keeps its slot
    assert list(asm.pending) == [b"B" * 32]
    drops = asm.drain_drops()
    assert [(d.reason, d.head.sha256, d.received_bytes) for d in drops] == [(DropReason.NO_SLOT, b"A" * 32, 0)]
    assert asm.buffered_bytes == 50 + OVER


def test_the_budget_at_equality_and_a_map_that_survives_the_eviction_still_completes():
    budget = 10 + OVER
    asm = MapAssembler(limits=AssemblyLimits(budget_bytes=budget, max_map_bytes=budget))
    asm.feed(header(1, 20, count=2, sha=b"A" * 32) + bytes(10), now_s=0.0)  # exactly the budget: kept
    assert list(asm.pending) == [b"A" * 32] and asm.drain_drops() == []
    roomy = MapAssembler(limits=AssemblyLimits(budget_bytes=3 * (10 + OVER) - 1, max_map_bytes=100))
    roomy.feed(header(1, 20, count=2, sha=b"A" * 32) + bytes(10), now_s=0.0)
    blob = os.urandom(20)
    b = split_map(blob, 2, 10)
    roomy.feed(b[0], now_s=1.0)
    assert bytes(roomy.feed(b[1], now_s=2.0)[1]) == blob  # over budget: the older map A goes, B completes
    assert [(d.reason, d.head.sha256) for d in roomy.drain_drops()] == [(DropReason.BUDGET, b"A" * 32)]
    assert roomy.buffered_bytes == 0


def test_chunks_that_complete_the_count_but_not_the_size_are_refused():
    blob = os.urandom(30)
    sha = hashlib.sha256(blob).digest()
    asm = MapAssembler()
    asm.feed(header(1, 30, index=0, count=2, offset=0, sha=sha) + blob[:10])
    with pytest.raises(MapError) as err:
        asm.feed(header(1, 30, index=1, count=2, offset=10, sha=sha) + blob[10:20])  # no gap, 10 bytes short
    assert str(err.value) == "chunks: chunk sizes do not add up to the map size (corrupted or forged chunks)"
    assert sha not in asm.done


def test_two_chunks_claiming_one_offset_are_refused():
    asm = MapAssembler()
    asm.feed(header(1, 30, index=1, count=3, offset=10, sha=b"C" * 32) + bytes(10))
    with pytest.raises(MapError) as err:
        asm.feed(header(1, 30, index=2, count=3, offset=10, sha=b"C" * 32) + bytes(10))
    assert str(err.value) == "chunks: two chunks claim offset 10 (corrupted or forged chunks)"

# ------------------------------------------------------------------------------------- positions
def test_non_finite_fixes_are_rejected_and_leave_the_reference():
    g = PositionGate()
    assert g.check(0.0, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0)) == GateVerdict.ACCEPTED
    for bad in (math.nan, math.inf, -math.inf):
        assert g.check(0.1, (bad, 2.0, 3.0), (0.0, 0.0, 0.0)) == GateVerdict.NON_FINITE
        assert g.check(0.1, (1.0, 2.0, 3.0), (0.0, bad, 0.0)) == GateVerdict.NON_FINITE
    assert g.ref == (0.0, (1.0, 2.0, 3.0))


def test_a_one_km_burst_is_rejected_and_the_genuine_stream_continues():
    g = PositionGate(PositionGateConfig.for_speed_clamp(5.0))
    t, x = 0.0, 0.0
    for k in range(100):
        t, x = k * 0.02, k * 0.02 * 4.0  # 4 m/s
        if k in (50, 51, 52):
            assert g.check(t, (x + 1000.0, 0.0, -4.0), (0.0, 0.0, 0.0)) == GateVerdict.IMPLAUSIBLE_JUMP
        else:
            assert g.check(t, (x, 0.0, -4.0), (4.0, 0.0, 0.0)) == GateVerdict.ACCEPTED


def test_a_consistent_new_track_is_taken_after_reanchor_after_s():
    g = PositionGate(PositionGateConfig(reanchor_after_s=3.0))
    g.check(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    verdicts = [g.check(0.1 + k * 0.1, (500.0, 0.0, 0.0), (0.0, 0.0, 0.0)) for k in range(35)]
    assert verdicts[:30] == [GateVerdict.IMPLAUSIBLE_JUMP] * 30 and GateVerdict.REANCHORED in verdicts[30:]



# Boundaries of the gate (issue 38: each rule at equal, one step inside, one step outside, per axis, sign).
ZERO = (0.0, 0.0, 0.0)


@pytest.mark.parametrize("dt_s, reach", [(1.0, 16.0), (0.5, 8.5), (0.0, 1.0), (-1.0, 1.0)])
def test_a_fix_exactly_at_the_reach_is_accepted_one_step_beyond_is_not(dt_s, reach):
    """reach = max_speed_m_s * max(0, dt) + jump_tolerance_m; a fix from before the reference gets the tolerance."""
    for axis in range(3):  # every axis counts in the distance
        for sign in (1.0, -1.0):
            at = [0.0, 0.0, 0.0]
            at[axis] = sign * reach
            beyond = list(at)
            beyond[axis] = sign * math.nextafter(reach, math.inf)
            g = PositionGate()
            assert g.check(10.0, ZERO, ZERO) == GateVerdict.ACCEPTED
            assert g.check(10.0 + dt_s, tuple(beyond), ZERO) == GateVerdict.IMPLAUSIBLE_JUMP, (axis, sign)
            assert g.check(10.0 + dt_s, tuple(at), ZERO) == GateVerdict.ACCEPTED, (axis, sign)


def test_the_reach_is_measured_from_the_reference_not_from_the_origin():
    g = PositionGate()
    assert g.check(0.0, (100.0, -100.0, 50.0), ZERO) == GateVerdict.ACCEPTED
    assert g.check(0.1, (100.5, -100.5, 50.5), ZERO) == GateVerdict.ACCEPTED  # 0.87 m from the reference
    assert g.check(0.2, (0.0, 0.0, 0.0), ZERO) == GateVerdict.IMPLAUSIBLE_JUMP


def test_a_component_exactly_at_max_abs_m_is_in_range_one_step_beyond_is_not():
    limit = PositionGateConfig().max_abs_m
    for vec_is_pos in (True, False):
        for value in (limit, -limit):
            comp = (value, 0.0, 0.0)
            fix = (comp, ZERO) if vec_is_pos else (ZERO, comp)
            assert PositionGate().check(0.0, *fix) == GateVerdict.ACCEPTED
            comp = (math.copysign(math.nextafter(limit, math.inf), value), 0.0, 0.0)
            fix = (comp, ZERO) if vec_is_pos else (ZERO, comp)
            assert PositionGate().check(0.0, *fix) == GateVerdict.OUT_OF_RANGE


def test_a_track_is_taken_at_exactly_reanchor_after_s_and_not_one_step_before():
    g = PositionGate(PositionGateConfig(reanchor_after_s=3.0))
    g.check(0.0, ZERO, ZERO)
    far = (500.0, 0.0, 0.0)
    assert g.check(1.0, far, ZERO) == GateVerdict.IMPLAUSIBLE_JUMP  # the track starts at 1 s
    assert g.check(math.nextafter(4.0, 0.0), far, ZERO) == GateVerdict.IMPLAUSIBLE_JUMP
    assert g.check(4.0, far, ZERO) == GateVerdict.REANCHORED
    assert g.ref == (4.0, far)
    # after the re-anchor, the gate judges from the new reference: a jump away from it is refused
    assert g.check(4.1, ZERO, ZERO) == GateVerdict.IMPLAUSIBLE_JUMP
    assert g.ref == (4.0, far)
    assert g.check(4.2, (501.0, 0.0, 0.0), ZERO) == GateVerdict.ACCEPTED


def test_a_track_is_broken_by_a_fix_unreachable_from_the_previous_one():
    g = PositionGate(PositionGateConfig(reanchor_after_s=3.0))
    g.check(100.0, ZERO, ZERO)  # late clock: a sum of times instead of a difference would join the tracks
    assert g.check(100.1, (1000.0, 0.0, 0.0), ZERO) == GateVerdict.IMPLAUSIBLE_JUMP
    assert g.check(100.2, (1000.0, 200.0, 0.0), ZERO) == GateVerdict.IMPLAUSIBLE_JUMP  # a new track at 100.2 s
    assert g.check(103.15, (1000.0, 200.0, 0.0), ZERO) == GateVerdict.IMPLAUSIBLE_JUMP  # 2.95 s of the new track
    assert g.check(103.2, (1000.0, 200.0, 0.0), ZERO) == GateVerdict.REANCHORED


def test_for_speed_clamp_is_three_times_the_clamp_and_at_least_15_m_s():
    assert PositionGateConfig.for_speed_clamp(1.0).max_speed_m_s == 15.0
    assert PositionGateConfig.for_speed_clamp(5.0).max_speed_m_s == 15.0  # the two rules meet
    assert PositionGateConfig.for_speed_clamp(6.0).max_speed_m_s == 18.0


@pytest.mark.parametrize("name", ["max_speed_m_s", "jump_tolerance_m", "reanchor_after_s", "max_abs_m"])
@pytest.mark.parametrize("value", [0.0, -1.0, math.inf, math.nan])
def test_a_gate_limit_must_be_finite_and_positive(name, value):
    with pytest.raises(ValueError, match=name):
        PositionGateConfig(**{name: value})
    PositionGateConfig(**{name: 1e-9})  # just above zero is fine

@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.floats(allow_nan=True, allow_infinity=True),
                          st.floats(allow_nan=True, allow_infinity=True), st.floats(0, 1)), max_size=60))
def test_fuzz_only_finite_reachable_fixes_are_accepted(fixes):
    g = PositionGate()
    t = 0.0
    for x, v, dt in fixes:
        t += dt
        ref = g.ref
        verdict = g.check(t, (x, 0.0, 0.0), (v, 0.0, 0.0))
        if verdict.accepted:
            assert math.isfinite(x) and math.isfinite(v)
            if verdict == GateVerdict.ACCEPTED and ref is not None:
                assert abs(x - ref[1][0]) <= g.cfg.max_speed_m_s * (t - ref[0]) + g.cfg.jump_tolerance_m


# ------------------------------------------------------------------------------------- rate-limited log
def test_rate_limited_log_counts_everything_and_logs_once_per_period(caplog):
    now = [0.0]
    rl = RateLimitedLog(logging.getLogger("test.rl"), period_s=5.0, max_keys=3, clock=lambda: now[0])
    with caplog.at_level(logging.WARNING, logger="test.rl"):
        for k in range(1000):
            now[0] = k * 0.01  # 10 s
            rl.event("map:signature", logging.WARNING, "refused %d", k)
    assert rl.count("map:signature") == 1000
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and lines[0] == "refused 0" and "499 more like this" in lines[1]
    for key in ("a", "b", "c", "d"):
        rl.event(key, logging.DEBUG, "x")
    assert rl.count(OVERFLOW_KEY) == 2 and len(rl.counts()) == 4 and rl.total() == 1004



# ------------------------------------------------------------------------------------- the whole input path
@pytest.fixture(scope="module")
def udp_link():
    """A real ``MavlinkLink`` listening on a free loopback UDP port, and a sender socket."""
    import socket

    from fisc_agent.mavlink.link import MavlinkLink

    link = MavlinkLink("udpin:127.0.0.1:0")
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.bind(("127.0.0.1", 0))
    yield link, tx
    tx.close()
    link.close()


def _deliver(link, tx, datagrams) -> None:
    import select

    for d in datagrams:
        tx.sendto(d, link.udp.local_address)
    while select.select([link.udp.sock], [], [], 0.02)[0]:  # loopback: queued by the time sendto returns
        link.poll()


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.binary(min_size=1, max_size=300), min_size=1, max_size=5), st.floats(-50, 50))
def test_fuzz_the_udp_input_path_never_raises_and_the_next_fix_gets_through(udp_link, garbage, x):
    """Raw datagrams into a real ``MavlinkLink`` (socket, per-datagram framing, identity, gate):
    ``poll`` never raises, the autopilot stays the autopilot, and its next fix is used."""
    link, tx = udp_link
    ap = _mav(1, 1)
    if link.target_system is None:
        _deliver(link, tx, [ap.heartbeat_encode(2, 12, 1, 0, 3).pack(ap)])
        assert link.target_system == 1 and link.udp.peer == tx.getsockname()
    _deliver(link, tx, garbage)
    # far jumps are gated; move the reference slowly so every fix here is plausible
    link.position_gate = PositionGate(link.position_gate.cfg)
    _deliver(link, tx, [ap.heartbeat_encode(2, 12, 1, 0, 3).pack(ap),
                        ap.local_position_ned_encode(1234, x, 1.0, -2.0, 0.0, 0.0, 0.0).pack(ap)])
    fix = link.latest_position()
    assert fix is not None and fix.pos_ned_m[0] == pytest.approx(x, abs=1e-4)
    assert fix.autopilot_t_s == pytest.approx(1.234)                  # the autopilot's own clock (time_boot_ms)
    assert link.target_system == 1 and link.target_component == 1


def test_installing_a_map_drops_the_maps_in_progress_it_makes_old_and_gives_their_bytes_back():
    asm = MapAssembler()
    asm.feed(header(5, 100, count=2, sha=b"E" * 32) + bytes(50))  # no clock given: time 0
    asm.feed(header(6, 100, count=2, sha=b"F" * 32) + bytes(30))  # another size: the bytes given back are E's
    assert asm.pending[b"E" * 32].last_chunk_s == 0.0
    assert asm.buffered_bytes == (50 + OVER) + (30 + OVER)
    asm.accept(5, b"G" * 32)  # the equal version goes, the newer one stays
    assert list(asm.pending) == [b"F" * 32] and asm.buffered_bytes == 30 + OVER
    asm.feed(split_map(os.urandom(10), 4)[0])
    assert [(d.reason, d.received_bytes) for d in asm.drain_drops()] == [(DropReason.OLD_VERSION, 0)]
    raw = split_map(b"abc", 9)[0]
    assert CHUNK_HEADER.unpack_from(raw)[3] == 0 and CHUNK_HEADER.unpack_from(announce_message(b"s" * 32, 9, 3, 1))[3] == 0


def test_an_announced_newcomer_takes_the_slot_of_an_older_announced_map():
    asm = MapAssembler(limits=AssemblyLimits(max_pending=1))
    for k, sha in enumerate((b"A" * 32, b"B" * 32)):
        asm.feed(announce_message(sha, 1, 100, 2), now_s=float(k))
    asm.feed(header(1, 100, count=2, sha=b"A" * 32) + bytes(50), now_s=1.0)
    asm.feed(header(1, 100, count=2, sha=b"B" * 32) + bytes(50), now_s=2.0)
    assert list(asm.pending) == [b"B" * 32]
    assert [d.reason for d in asm.drain_drops()] == [DropReason.EVICTED]


def test_the_budget_victim_is_chosen_with_announced_maps_in_progress():
    asm = MapAssembler(limits=AssemblyLimits(budget_bytes=3 * (10 + OVER) - 1, max_map_bytes=100))
    blob = os.urandom(20)
    b = split_map(blob, 2, 10)
    asm.feed(announce_message(hashlib.sha256(blob).digest(), 2, 20, 2), now_s=0.0)
    asm.feed(header(1, 20, count=2, sha=b"A" * 32) + bytes(10), now_s=0.0)
    asm.feed(b[0], now_s=1.0)
    assert bytes(asm.feed(b[1], now_s=2.0)[1]) == blob  # the unannounced map goes
    assert [(d.reason, d.head.sha256) for d in asm.drain_drops()] == [(DropReason.BUDGET, b"A" * 32)]


def test_a_forged_map_is_refused_and_the_genuine_one_still_gets_through():
    blob = os.urandom(40)
    sha = hashlib.sha256(blob).digest()
    asm = MapAssembler()
    with pytest.raises(MapError) as err:
        asm.feed(header(3, 40, sha=sha) + os.urandom(40))
    assert str(err.value) == "chunks: reassembled map does not match its sha256 (corrupted or forged chunks)"
    assert bytes(asm.feed(split_map(blob, 3)[0])[1]) == blob  # not remembered as done
    with pytest.raises(MapError) as err:
        asm.verify(parse_chunk(header(3, 40, sha=b"N" * 32))[0], bytearray(40))  # never completed: no KeyError
    assert "does not match its sha256" in str(err.value)


def test_chunk_errors_name_the_problem_exactly():
    asm = MapAssembler()
    asm.feed(header(1, 30, index=0, count=3, offset=0, sha=b"D" * 32) + bytes(10))
    with pytest.raises(MapError) as err:
        asm.feed(header(1, 31, index=1, count=3, offset=10, sha=b"D" * 32) + bytes(10))
    assert str(err.value) == "chunks: chunk disagrees with earlier chunks of the same map"
    with pytest.raises(MapError) as err:
        asm.feed(header(1, 30, index=1, count=3, offset=5, sha=b"D" * 32) + bytes(10))
    assert str(err.value) == ("chunks: chunk 1 at offset 5 overlaps bytes already received (corrupted or forged "
                              "chunks)")


def test_remembered_refusals_forget_the_oldest_first():
    asm = MapAssembler(limits=AssemblyLimits(max_remembered=2))
    asm.accept(100, None)
    old = [split_map(os.urandom(10), v)[0] for v in (1, 2, 3)]
    for msg in old:
        asm.feed(msg)
    assert len(asm.drain_drops()) == 3
    asm.feed(old[2])
    asm.feed(old[1])  # the two most recent are remembered: not reported again
    assert asm.drain_drops() == []
    asm.feed(old[0])  # the oldest was forgotten: reported again
    assert [d.head.map_version for d in asm.drain_drops()] == [1]
