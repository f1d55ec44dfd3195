"""What the agent believes from its MAVLink input (pure): frames per datagram, and who the autopilot is.

Two decisions a hostile or broken peer on the MAVLink side must not be able to bend:

1. **Framing.**  ``parse_datagram`` parses one UDP datagram on its own: complete MAVLink 1/2
   frames are decoded (CRC checked by pymavlink's ``decode``), anything else is counted as bad
   bytes and *forgotten with the datagram*.  A partial frame cannot swallow the start of the
   next datagram (a stream parser fed datagram after datagram does exactly that, and 50 partial
   frames per second then hide every position fix).  The work per datagram is bounded
   (``MAX_BAD_FRAMES_PER_DATAGRAM`` failed decodes, then the rest is dropped).

2. **Identity.**  ``AutopilotTracker`` decides which (system, component, sender address) is the
   autopilot.  Only its HEARTBEATs change armed state, mode and autopilot type, and only its
   other messages (positions, acks) are used.  With ``target_system`` given, only that system id
   can be the autopilot.  Otherwise the first vehicle HEARTBEAT locks on *provisionally*; a second
   HEARTBEAT from it (a PX4 or ArduPilot) *pins* its system id for the life of the tracker (the default
   ``--target-system``: the first autopilot heard).  A provisional lock may still move to another
   system while the locked one is disarmed and either silent for ``relock_after_s`` or of an
   unknown autopilot type while the other is PX4/ArduPilot (so a single stray or forged HEARTBEAT
   before the autopilot starts cannot hold the agent forever); a pinned one never does.  The same
   system may be re-locked from a new address or component (a reconnect, an autopilot reboot) under
   the same rule: disarmed, and silent or of an unknown type.  A stray HEARTBEAT from another
   component (a camera, a GCS, a forged one) changes nothing.

A MAVLink 1/2 link without message signing cannot tell a forger that copies the autopilot's
system, component and (UDP) address from the autopilot; see docs/deployment.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Callable, Hashable

from pymavlink.dialects.v20.common import (MAV_AUTOPILOT_INVALID, MAV_TYPE_ADSB, MAV_TYPE_CAMERA, MAV_TYPE_GCS,
                                           MAV_TYPE_GIMBAL, MAV_TYPE_ODID, MAV_TYPE_ONBOARD_CONTROLLER)

MAGIC_V1 = 0xFE
MAGIC_V2 = 0xFD
HEADER_V1 = 6
HEADER_V2 = 10
CRC_LEN = 2
SIGNATURE_LEN = 13
IFLAG_SIGNED = 0x01
MAX_BAD_FRAMES_PER_DATAGRAM = 4
"""Failed frame decodes after which the rest of a datagram is dropped (bounds the CPU a datagram costs)."""

NON_VEHICLE_TYPES = frozenset({MAV_TYPE_GCS, MAV_TYPE_ONBOARD_CONTROLLER, MAV_TYPE_GIMBAL, MAV_TYPE_ADSB,
                               MAV_TYPE_CAMERA, MAV_TYPE_ODID})
"""MAV_TYPE of GCS, onboard controller, gimbal, ADSB, camera, OpenDroneID: never an autopilot."""


@dataclass(frozen=True)
class DatagramScan:
    """The result of parsing one datagram."""

    messages: tuple
    """Decoded messages, in order."""
    bad_bytes: int
    """Bytes that were not part of a valid frame (garbage, partial or corrupted frames)."""
    dropped_rest: bool
    """True when parsing stopped early (too many bad frames); the rest counts as bad bytes."""


def frame_length(buf: bytes | bytearray | memoryview, i: int) -> int | None:
    """Length of the frame that starts with a magic byte at ``buf[i]``; None if ``buf[i]`` is no
    magic byte or the header is incomplete."""
    n = len(buf)
    b = buf[i]
    if b == MAGIC_V2:
        if n - i < HEADER_V2:
            return None
        sig = SIGNATURE_LEN if buf[i + 2] & IFLAG_SIGNED else 0
        return HEADER_V2 + buf[i + 1] + CRC_LEN + sig
    if b == MAGIC_V1:
        if n - i < HEADER_V1:
            return None
        return HEADER_V1 + buf[i + 1] + CRC_LEN
    return None


def parse_datagram(data: bytes | bytearray, decode: Callable[[bytearray], object]) -> DatagramScan:
    """Decode every complete frame of one datagram with ``decode`` (e.g. a pymavlink
    ``MAVLink.decode``; it raises on a bad CRC or length).  Never raises for any input bytes:
    a frame that fails to decode costs one byte of resynchronisation."""
    buf = bytes(data)
    n = len(buf)
    i = 0
    bad = 0
    failures = 0
    messages = []
    while i < n:
        flen = frame_length(buf, i)
        if flen is None or i + flen > n:
            bad += 1
            i += 1
            continue
        try:
            msg = decode(bytearray(buf[i:i + flen]))
        except Exception:  # any decode failure is bad input, never a crash
            msg = None
        if msg is None:
            failures += 1
            bad += 1
            i += 1
            if failures >= MAX_BAD_FRAMES_PER_DATAGRAM:
                return DatagramScan(tuple(messages), bad + (n - i), True)
            continue
        messages.append(msg)
        i += flen
    return DatagramScan(tuple(messages), bad, False)


# --------------------------------------------------------------------------------------------
# Who the autopilot is

@dataclass(frozen=True)
class AutopilotId:
    """The autopilot's MAVLink identity."""

    system: int
    """MAVLink system id."""
    component: int
    """MAVLink component id."""
    address: Hashable | None
    """Sender address of its datagrams (None on stream links: serial, TCP)."""


class HeartbeatVerdict(str, Enum):
    """What a HEARTBEAT did."""

    AUTOPILOT = "autopilot"
    """From the autopilot: its state applies."""
    LOCKED = "locked"
    """A new autopilot was chosen (first vehicle seen, or a re-lock): its state applies."""
    NOT_A_VEHICLE = "not_a_vehicle"
    """GCS, companion, gimbal... or MAV_AUTOPILOT_INVALID: ignored."""
    FOREIGN = "foreign"
    """Another vehicle or component: ignored."""


class AutopilotTracker:
    """Chooses the autopilot and attributes messages to it (pure; times come in)."""

    def __init__(self, relock_after_s: float = 3.0, known_autopilot: Callable[[int], bool] | None = None,
                 target_system: int | None = None, pin_after_heartbeats: int = 2) -> None:
        if not relock_after_s > 0:
            raise ValueError(f"relock_after_s must be > 0, got {relock_after_s}")
        if target_system is not None and not 1 <= int(target_system) <= 255:
            raise ValueError(f"target_system must be a MAVLink system id 1..255, got {target_system}")
        if pin_after_heartbeats < 1:
            raise ValueError(f"pin_after_heartbeats must be >= 1, got {pin_after_heartbeats}")
        self.relock_after_s = float(relock_after_s)
        self._known = known_autopilot or (lambda a: a in (3, 12))  # ArduPilot, PX4
        self.pinned_system: int | None = None if target_system is None else int(target_system)
        """The only system id that can be the autopilot (given, or pinned after ``pin_after_heartbeats``)."""
        self.pinned_by_user = target_system is not None
        """True when ``pinned_system`` was given (``--target-system``), not learnt."""
        self.pin_after_heartbeats = int(pin_after_heartbeats)
        self.target: AutopilotId | None = None
        self.target_autopilot: int | None = None
        self.target_armed = False
        self.last_heartbeat_s: float | None = None
        self.relocks = 0
        self._target_heartbeats = 0

    def is_autopilot(self, system: int, component: int, address: Hashable | None) -> bool:
        """True when a message comes from the locked autopilot (False before any lock)."""
        t = self.target
        return t is not None and t.system == system and t.component == component and t.address == address

    def on_heartbeat(self, system: int, component: int, address: Hashable | None, mav_type: int, autopilot: int,
                     armed: bool, now_s: float) -> HeartbeatVerdict:
        """Classify one HEARTBEAT (and lock on / re-lock when the rules say so)."""
        if int(mav_type) in NON_VEHICLE_TYPES or int(autopilot) == MAV_AUTOPILOT_INVALID:
            return HeartbeatVerdict.NOT_A_VEHICLE
        if self.is_autopilot(system, component, address):
            self.target_autopilot, self.target_armed, self.last_heartbeat_s = int(autopilot), bool(armed), now_s
            self._target_heartbeats += 1
            self._maybe_pin()
            return HeartbeatVerdict.AUTOPILOT
        if self.pinned_system is not None and int(system) != self.pinned_system:
            return HeartbeatVerdict.FOREIGN
        if self.target is not None and not self._may_relock(int(autopilot), now_s):
            return HeartbeatVerdict.FOREIGN
        if self.target is not None:
            self.relocks += 1
        self.target = AutopilotId(int(system), int(component), address)
        self.target_autopilot, self.target_armed, self.last_heartbeat_s = int(autopilot), bool(armed), now_s
        self._target_heartbeats = 1
        self._maybe_pin()
        return HeartbeatVerdict.LOCKED

    def _maybe_pin(self) -> None:
        # only a PX4/ArduPilot is pinned: an unknown autopilot type still gives way to one
        if self.pinned_system is None and self._target_heartbeats >= self.pin_after_heartbeats \
                and self._known(self.target_autopilot or 0):
            self.pinned_system = self.target.system

    def _may_relock(self, autopilot: int, now_s: float) -> bool:
        if self.target_armed:
            return False  # never switch away from a vehicle that may be flying
        silent = self.last_heartbeat_s is None or now_s - self.last_heartbeat_s > self.relock_after_s
        better = not self._known(self.target_autopilot or 0) and self._known(autopilot)
        return silent or better
