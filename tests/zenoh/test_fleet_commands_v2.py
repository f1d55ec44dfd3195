"""Fleet commands v2 from raw bytes: agent lists, version 1 still read, the per-key gate at its
boundaries (clock skew, replay across keys), the latest-state bundle and the ground's store of it."""

from __future__ import annotations

import struct

import pytest
from nacl.signing import SigningKey

from fisc_agent.zenoh.command_gate import CommandGate, Source
from fisc_agent.zenoh.command_rx import CommandReceiver
from fisc_agent.zenoh.state_bundle import decode_bundle, encode_bundle
from fisc_agent.zenoh.fleet_commands import (CommandCheck, CommandError, FleetCommand, decode_command, encode_command,
                                             key_id_of)
from fisc_ground.zenoh.command_relay import LatestCommands

KEY, OTHER = SigningKey.generate(), SigningKey.generate()
PUB, OTHER_PUB = KEY.verify_key.encode(), OTHER.verify_key.encode()


def cmd(name="hold", seq=10, issued=1000.0, key_id="", **kw):
    return FleetCommand(name=name, swarm="alpha", seq=seq, issued_unix_s=issued, key_id=key_id, **kw)


def test_version_2_layout_names_a_list_of_agents():
    raw = encode_command(cmd("go", seq=7, issued=1000.25, targets=(1, 3, 5)), KEY.encode())
    assert raw[:4] == b"FCMD" and raw[4] == 2 and raw[5] == 5 and raw[6] == 1 and raw[7] == 5
    assert struct.unpack_from("<HHQQQ", raw, 8) == (3, 0, 7, 1_000_250, 0)
    assert raw[36:41] == b"alpha" and struct.unpack_from("<3I", raw, 41) == (1, 3, 5)
    assert len(raw) == 41 + 12 + 64
    back = decode_command(raw, [OTHER_PUB, PUB])
    assert back.targets == (1, 3, 5) and back.addressed and back.key_id == key_id_of(PUB) == PUB[:8].hex()
    assert back.applies_to(3) and not back.applies_to(2)
    whole = decode_command(encode_command(cmd("go"), KEY.encode()), [PUB])
    assert whole.targets == () and not whole.addressed and whole.applies_to(12345)


def v1_bytes(code: int, target: int, seq: int, issued_ms: int, start_ms: int = 0) -> bytes:
    head = struct.pack("<4sBBBBIQQQ", b"FCMD", 1, code, 1, 5, target, seq, issued_ms, start_ms) + b"alpha"
    return head + KEY.sign(head).signature


def test_version_1_commands_still_decode():
    every = decode_command(v1_bytes(1, 0xFFFFFFFF, 9, 1_000_000), [PUB])
    assert (every.name, every.targets, every.seq, every.issued_unix_s) == ("hold", (), 9, 1000.0)
    one = decode_command(v1_bytes(4, 3, 10, 1_000_000, 2_000_500), [PUB])
    assert one.name == "start-at" and one.targets == (3,) and one.start_at_unix_s == 2000.5 and one.signed


def test_takeover_must_name_agents_and_agent_lists_must_be_clean():
    with pytest.raises(CommandError) as err:
        encode_command(cmd("takeover"), KEY.encode())
    assert err.value.check is CommandCheck.ADDRESS
    # forged on the wire: a signed swarm-wide takeover, a list out of order
    head = struct.pack("<4sBBBBHHQQQ", b"FCMD", 2, 6, 1, 5, 0, 0, 1, 1_000_000, 0) + b"alpha"
    with pytest.raises(CommandError, match="address: takeover"):
        decode_command(head + KEY.sign(head).signature, [PUB])
    head = struct.pack("<4sBBBBHHQQQ", b"FCMD", 2, 5, 1, 5, 2, 0, 1, 1_000_000, 0) + b"alpha" + struct.pack("<2I", 5, 5)
    with pytest.raises(CommandError, match="ascending"):
        decode_command(head + KEY.sign(head).signature, [PUB])
    with pytest.raises(CommandError) as err:
        decode_command(head + KEY.sign(head).signature + b"x", [PUB])
    assert err.value.check is CommandCheck.SIZE


@pytest.mark.parametrize("now, ok", [
    (1030.0, True), (1030.001, False),   # 30 s old: just inside / just outside the live window
    (980.0, True), (979.999, False),     # 20 s in the future: just inside / just outside
    (1010.0, True), (990.0, True),       # the agent's clock 10 s ahead of / behind the ground's
])
def test_live_freshness_window_boundaries(now, ok):
    gate = CommandGate("alpha", 1)
    if ok:
        assert gate.check(cmd(issued=1000.0), now).seq == 10 and gate.floors == {"": 10}
    else:
        with pytest.raises(CommandError) as err:
            gate.check(cmd(issued=1000.0), now)
        assert err.value.check in (CommandCheck.STALE, CommandCheck.FUTURE) and gate.floors == {}


def test_sequence_floors_are_per_key_and_survive_a_restart():
    gate = CommandGate("alpha", 1, floors={"aa": 100})
    with pytest.raises(CommandError, match="replay") as err:
        gate.check(cmd(seq=100, key_id="aa"), 1000.0)  # equal: replay
    assert err.value.check is CommandCheck.REPLAY
    assert gate.check(cmd(seq=101, key_id="aa"), 1000.0).seq == 101  # just above
    assert gate.check(cmd(seq=50, key_id="bb"), 1000.0).seq == 50  # another key has its own floor
    with pytest.raises(CommandError, match="replay"):
        gate.check(cmd(seq=50, key_id="bb"), 1000.0)
    restarted = CommandGate("alpha", 1, floors=gate.floors)
    assert restarted.floors == {"aa": 101, "bb": 50}
    with pytest.raises(CommandError, match="replay"):
        restarted.check(cmd(seq=101, key_id="aa"), 1000.0)


@pytest.mark.parametrize("name, issued, start, now, ok", [
    ("hold", 1000.0, None, 1000.0 + 86400, True),        # the standing hold: any age
    ("land", 1000.0, None, 1000.0 + 86400, True),
    ("go", 1000.0, None, 1120.0, True),                   # a re-published go: 120 s, just inside
    ("go", 1000.0, None, 1120.001, False),                # just outside
    ("start-at", 1000.0, 5000.0, 4000.0, True),           # issued long ago, its start still ahead
    ("start-at", 1000.0, 5000.0, 5120.001, False),
    ("takeover", 1000.0, None, 1030.001, False),          # never standing: the live window
    ("hold", 1000.0, None, 979.999, False),               # from the future: refused whatever the source
])
def test_republished_state_freshness(name, issued, start, now, ok):
    gate = CommandGate("alpha", 1)
    c = cmd(name, issued=issued, start_at_unix_s=start, targets=(1,) if name == "takeover" else ())
    if ok:
        assert gate.check(c, now, Source.STATE) is c
    else:
        with pytest.raises(CommandError):
            gate.check(c, now, Source.STATE)


def test_bundle_raw_bytes_and_malformed_bundles():
    a, b = encode_command(cmd("go"), KEY.encode()), encode_command(cmd("hold", seq=11), KEY.encode())
    raw = encode_bundle([a, b])
    assert raw[:8] == b"FCST\x01\x00\x02\x00" and struct.unpack_from("<H", raw, 8)[0] == len(a)
    assert decode_bundle(raw) == [a, b] and decode_bundle(encode_bundle([])) == []
    for bad, check in [(raw[:5], CommandCheck.TRUNCATED), (b"XCST" + raw[4:], CommandCheck.MAGIC),
                       (raw[:4] + b"\x02" + raw[5:], CommandCheck.VERSION), (raw[:-1], CommandCheck.TRUNCATED),
                       (raw + b"\0", CommandCheck.SIZE), (raw[:6] + b"\xff\xff" + raw[8:], CommandCheck.SIZE)]:
        with pytest.raises(CommandError) as err:
            decode_bundle(bad)
        assert err.value.check is check


def test_the_ground_keeps_the_latest_go_and_hold_per_scope():
    store = LatestCommands("alpha", [PUB])
    enc = lambda c, k=KEY: encode_command(c, k.encode())  # noqa: E731
    assert store.offer(enc(cmd("go", seq=1, issued=100.0))) is not None
    assert store.offer(enc(cmd("hold", seq=2, issued=101.0, targets=(3,)))) is not None
    assert store.offer(enc(cmd("takeover", seq=3, issued=102.0, targets=(3,)))) is None  # never kept
    assert store.offer(enc(cmd("go", seq=1, issued=99.0))) is None  # older: not kept
    with pytest.raises(CommandError, match="signature"):
        store.offer(enc(cmd("land", seq=9, issued=200.0), OTHER))
    names = [decode_command(r, [PUB]).name for r in store.commands()]
    assert names == ["go", "hold"]
    assert store.offer(enc(cmd("resume", seq=4, issued=103.0))) is not None  # swarm-wide: supersedes agent 3's hold
    assert [decode_command(r, [PUB]).name for r in store.commands()] == ["go", "resume"]
    assert decode_bundle(store.bundle()) == store.commands()


def test_receiver_counts_refusals_once_and_ignores_state_it_already_has():
    now = [1000.0]
    rx = CommandReceiver("alpha", 1, [PUB], False, clock=lambda: now[0])
    go = encode_command(cmd("go", seq=5, issued=1000.0), KEY.encode())
    assert rx.live(go).name == "go"
    assert rx.state(encode_bundle([go])) == [] and rx.stats.refused == 0  # already had it: no refusal
    assert rx.live(go) is None and rx.stats.refused == 1 and rx.stats.last_refusal == "replay"
    old = encode_command(cmd("go", seq=6, issued=500.0), KEY.encode())
    for _ in range(3):  # re-published every few seconds: judged and counted once
        assert rx.state(encode_bundle([old])) == []
    assert rx.stats.refused == 2 and (rx.stats.last_refusal, rx.stats.last_refused_command) == ("stale", "go")
    assert rx.live(b"garbage") is None and rx.stats.last_refused_command == "none"
    assert rx.floors == {key_id_of(PUB): 5} and rx.stats.accepted == 1


def test_cmd_agents_option_parses_lists_and_ranges_and_refuses_the_rest(capsys):
    from fisc_ground.zenoh.fleet import parse_agents

    from .test_names_and_json import ground_parser

    assert parse_agents("5,1,3") == (1, 3, 5) and parse_agents("1-4,9,2") == (1, 2, 3, 4, 9)
    assert parse_agents("0") == (0,) and parse_agents("4294967294") == (4294967294,)
    for bad in ("", "x", "3-1", "4294967295", "-1", "0-5000"):
        with pytest.raises(ValueError, match="--agents"):
            parse_agents(bad)
    args = ground_parser().parse_args(["cmd", "go", "--swarm", "alpha", "--agents", "1,3,5"])
    assert args.agents == (1, 3, 5) and args.fleet_command == "go"
    with pytest.raises(SystemExit) as exit_:
        ground_parser().parse_args(["cmd", "takeover", "--swarm", "alpha", "--agents", "1,x"])
    assert exit_.value.code == 2 and "'x' is not an agent id" in capsys.readouterr().err
