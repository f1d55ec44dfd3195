"""fisc_agent.mavlink.fast_codec against pymavlink, from raw bytes: the same frames, the same decoded
objects, and pymavlink's own path (or its error) for everything the fast path does not take."""

from __future__ import annotations

import math
import struct

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from fisc_agent.mavlink.fast_codec import (can_pack_fast, decode_v2, fast_decoder, frame_length_v2, pack_v2,
                                           write_frame)

F32_MAX = struct.unpack("<f", struct.pack("<I", 0x7F7FFFFF))[0]
F32_TINY = struct.unpack("<f", struct.pack("<I", 0x00000001))[0]  # smallest subnormal
EDGE_FLOATS = (0.0, -0.0, 1.0, -1.5, F32_MAX, -F32_MAX, F32_TINY, math.inf, -math.inf, 1e-3, 123.456)


class _Sink:
    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, b) -> None:
        self.frames.append(bytes(b))


def _mav(sysid: int = 1, compid: int = 1, seq: int = 0) -> mavlink2.MAVLink:
    mav = mavlink2.MAVLink(_Sink(), srcSystem=sysid, srcComponent=compid)
    mav.seq = seq
    return mav


def _frames():
    """(description, frame bytes) of many messages, packed by pymavlink itself."""
    out = []
    for i, f in enumerate(EDGE_FLOATS):
        mav = _mav(sysid=1 + i * 23 % 255, compid=1 + i, seq=(250 + i) % 256)
        out.append((f"local {f}", mav.local_position_ned_encode(i * 0x1FFFFFFF & 0xFFFFFFFF, f, -f, 0.0, f, 0.0, f)
                    .pack(mav)))
        out.append((f"setpoint {f}", mav.set_position_target_local_ned_encode(
            0xFFFFFFFF, 255, 0, 1, 0xFFFF if i % 2 else 0, 0.0, 0.0, 0.0, f, f, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0).pack(mav)))
    for custom, base, armed in ((0, 0, 0), (0xFFFFFFFF, 255, 255), (393216, 157, 4)):
        mav = _mav(sysid=255, compid=191)
        out.append((f"heartbeat {custom}", mav.heartbeat_encode(2, 12, base, custom, armed, 3).pack(mav)))
    mav = _mav()
    out.append(("all zero local", mav.local_position_ned_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0).pack(mav)))
    out.append(("command_ack", mav.command_ack_encode(511, 0, 0, 0, 1, 1).pack(mav)))
    out.append(("command_long nan", mav.command_long_encode(1, 1, 511, 0, 33.0, -1.0, math.nan, 0, 0, 0, 0).pack(mav)))
    out.append(("global_position_int", mav.global_position_int_encode(7, -2**31, 2**31 - 1, -5, 5, -32768, 32767, 0,
                                                                       35999).pack(mav)))
    return out


def _same(a, b) -> None:
    assert type(a) is type(b)
    assert a.get_type() == b.get_type()
    for name in a.get_fieldnames():
        x, y = getattr(a, name), getattr(b, name)
        assert (x == y and math.copysign(1, x) == math.copysign(1, y)) if isinstance(x, float) and not math.isnan(x) \
            else (math.isnan(x) and math.isnan(y)) if isinstance(x, float) else x == y, name
    assert vars(a.get_header()) == vars(b.get_header())
    va, vb = dict(vars(a)), dict(vars(b))
    assert va.keys() == vb.keys()  # every attribute pymavlink sets, and no other
    for attr in ("_msgbuf", "_payload", "_crc", "_signed", "_link_id", "_fieldnames", "_instance_field",
                 "_instance_offset", "_instances", "_type"):
        assert va.get(attr) == vb.get(attr) and type(va.get(attr)) is type(vb.get(attr)), attr
    for name in a.get_fieldnames():
        assert type(va[name]) is type(vb[name]), name


@pytest.mark.parametrize("name,frame", _frames(), ids=[d for d, _ in _frames()])
def test_decode_is_pymavlinks_object(name, frame):
    fast = decode_v2(mavlink2.MAVLink(None), frame)
    assert fast is not None, name
    _same(fast, mavlink2.MAVLink(None).decode(bytearray(frame)))
    assert frame_length_v2(frame) == len(frame)


def test_decode_pads_a_stripped_payload_and_cuts_a_long_one():
    mav = _mav()
    short = mav.local_position_ned_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0).pack(mav)
    assert short[1] == 1  # payload of one byte: the rest were trailing zeros
    _same(decode_v2(mavlink2.MAVLink(None), short), mavlink2.MAVLink(None).decode(bytearray(short)))
    # a payload longer than the message (a newer dialect's extension): pymavlink cuts it, so do we
    body = bytearray(short[:10]) + struct.pack("<Iffffff", 9, 1, 2, 3, 4, 5, 6) + b"\x07\x08"
    body[1] = len(body) - 10
    crc = mavlink2.x25crc(bytes(body[1:]) + bytes((185,))).crc
    long_frame = bytes(body) + struct.pack("<H", crc)
    _same(decode_v2(mavlink2.MAVLink(None), long_frame), mavlink2.MAVLink(None).decode(bytearray(long_frame)))


def _falls_back(frame) -> None:
    """The fast path declines; pymavlink decodes it or raises, and the fast decoder does exactly that."""
    assert decode_v2(mavlink2.MAVLink(None), frame) is None
    try:
        want = mavlink2.MAVLink(None).decode(bytearray(frame))
    except mavlink2.MAVError as exc:
        with pytest.raises(mavlink2.MAVError, match=str(exc).split("(")[0][:20]):
            fast_decoder(mavlink2.MAVLink(None))(bytearray(frame))
        return
    _same(fast_decoder(mavlink2.MAVLink(None))(bytearray(frame)), want)


def test_declined_frames_go_to_pymavlink():
    mav = _mav()
    good = mav.local_position_ned_encode(5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0).pack(mav)
    bad_crc = good[:-1] + bytes(((good[-1] + 1) % 256,))
    _falls_back(bad_crc)  # CRC off by one: pymavlink raises
    _falls_back(good[:-1])  # one byte short
    _falls_back(good + b"\x00")  # one byte long
    _falls_back(good[:11])  # shorter than a header and CRC
    v1 = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    _falls_back(mav.local_position_ned_encode(5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0).pack(v1, force_mavlink1=True))
    _falls_back(mav.statustext_encode(4, b"hello").pack(mav))  # a string field
    _falls_back(mav.home_position_encode(1, 2, 3, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0, 0).pack(mav))  # an array
    flagged = bytearray(good)
    flagged[2] = 0x02  # an incompatibility flag other than signing
    _falls_back(bytes(flagged))
    unknown = bytearray(good)
    unknown[7:10] = (0xFF, 0xFF, 0x00)  # no message 65535 in the dialect
    _falls_back(bytes(unknown))


def test_signed_frames_and_a_signing_decoder_go_to_pymavlink():
    signer = _mav()
    signer.signing.secret_key = bytes(32)
    signer.signing.sign_outgoing = True
    signer.signing.link_id = 0
    signer.signing.timestamp = 1
    signed = signer.local_position_ned_encode(5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0).pack(signer)
    assert signed[2] & 0x01
    assert decode_v2(mavlink2.MAVLink(None), signed) is None
    mav = _mav()
    plain = mav.local_position_ned_encode(5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0).pack(mav)
    checker = mavlink2.MAVLink(None)
    checker.signing.secret_key = bytes(32)
    assert decode_v2(checker, plain) is None  # a link with a key checks signatures: pymavlink's job


@pytest.mark.parametrize("f", EDGE_FLOATS)
def test_pack_is_pymavlinks_frame(f):
    for seq in (0, 255):
        ref, fast = _mav(7, 1, seq), _mav(7, 1, seq)
        msg = ref.local_position_ned_encode(0xFFFFFFFF, f, 0.0, -f, 0.0, f, 0.0)
        payload = struct.pack("<Iffffff", 0xFFFFFFFF, f, 0.0, -f, 0.0, f, 0.0)
        assert can_pack_fast(fast)
        buf = pack_v2(fast, 32, bytes((185,)), payload)
        assert fast.seq == seq  # not changed by packing
        write_frame(fast, buf)
        ref.send(msg)
        assert fast.file.frames == ref.file.frames
        assert (fast.seq, fast.total_packets_sent, fast.total_bytes_sent) == \
            (ref.seq, ref.total_packets_sent, ref.total_bytes_sent)


def test_pack_all_zero_payload_keeps_one_byte():
    ref, fast = _mav(), _mav()
    ref.send(ref.local_position_ned_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    assert pack_v2(fast, 32, bytes((185,)), bytes(28)) == ref.file.frames[0]
    assert ref.file.frames[0][1] == 1


def test_signing_or_a_callback_disables_the_fast_pack():
    mav = _mav()
    mav.signing.sign_outgoing = True
    assert not can_pack_fast(mav)
    mav = _mav()
    mav.set_send_callback(lambda m: None)
    assert not can_pack_fast(mav)


def test_frame_length_v2_of_partial_and_foreign_input():
    assert frame_length_v2(b"") is None
    assert frame_length_v2(bytes((0xFD, 3, 0, 0, 0, 1, 1, 32, 0))) is None  # 9 bytes: no full header
    assert frame_length_v2(bytes((0xFD, 3, 0, 0, 0, 1, 1, 32, 0, 0))) == 15
    assert frame_length_v2(bytes((0xFE, 3, 0, 0, 0, 1, 1, 32, 0, 0))) is None  # MAVLink 1
    assert frame_length_v2(bytes((0xFD, 3, 1, 0, 0, 1, 1, 32, 0, 0))) is None  # signed
