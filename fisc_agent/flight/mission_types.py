"""The mission's vocabulary: states, causes, reasons, fleet commands and the per-tick records
the state machine (``fisc_agent.flight.mission``) reads and writes.  Pure types, no behaviour."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum, StrEnum
from typing import NamedTuple

from fisc_agent.flight.control import Vec
from fisc_agent.flight.health import VehicleHealth
from fisc_agent.flight.integrity import IntegrityConfig
from fisc_agent.mavlink.adapters import ModeClass


class MissionCommand(StrEnum):
    """A fleet command the mission obeys (the value is its name on the wire)."""

    HOLD = "hold"
    RESUME = "resume"
    LAND = "land"
    GO = "go"
    """Permission to arm and fly one flight (``--go`` on the command line is the same)."""
    TAKEOVER = "takeover"
    """Take an armed vehicle that this process did not arm (only when addressed to this agent)."""

    @classmethod
    def parse(cls, name: str) -> MissionCommand:
        """The command called ``name``; ``ValueError`` naming the choices otherwise."""
        try:
            return cls(name)
        except ValueError:
            raise ValueError(f"unknown fleet command {name!r}; choose one of "
                             f"{', '.join(c.value for c in cls)}") from None


@dataclass(frozen=True)
class FleetOrder:
    """A fleet command as the mission receives it: what, and whether it named this agent."""

    command: MissionCommand
    """The command."""
    addressed: bool = False
    """True when the command named this agent (``fisc-ground cmd ... --agents N``); a swarm-wide
    command is False.  Only an addressed command gives a vehicle back after hands-off."""
    seq: int = 0
    """The command's sequence number (0: from this process, e.g. ``--go``)."""
    key_id: str = ""
    """Which ground key signed it (hex of the public key's first bytes; "" unsigned or local)."""


class Authority(StrEnum):
    """Who is in charge of the vehicle, as the agent sees it (telemetry ``authority``)."""

    WAITING = "waiting"
    """No go yet: the agent waits disarmed and sends nothing."""
    NOT_OURS = "not-ours"
    """The vehicle was armed by someone else: the agent watches and sends nothing."""
    COMMAND = "command"
    """The agent armed the vehicle in this process (or was handed it by an addressed takeover) and flies it."""
    HANDS_OFF = "hands-off"
    """Someone else changed the vehicle's mode: no mode request and no setpoint for the rest of
    the flight, unless a command addressed to this agent gives it back."""
    RELEASED = "released"
    """The flight is over (landed, or could not arm): the go is used up."""


class State(str, Enum):
    """The mission's states, in flight order (their values are the flight log's and telemetry's names)."""
    WAIT_POSITION = "WAIT_POSITION"
    STANDBY = "STANDBY"
    """Position, heartbeat and map are there but the agent is not in command: no go yet, or the
    vehicle is someone else's (``Authority``)."""
    ARM = "ARM"
    TAKEOFF = "TAKEOFF"
    JOIN = "JOIN"
    FLOW = "FLOW"
    RETURN = "RETURN"
    EXIT = "EXIT"
    HOLD = "HOLD"
    LAND = "LAND"
    DONE = "DONE"


class HoldCause(str, Enum):
    """Why the mission holds (``Mission.hold_cause``); the value is the hold's default reason text."""

    LINK_LOST = "link lost"
    POSITION_STALE = "position stale"
    GEOFENCE = "geofence: outside the map"
    EXIT = "exit: holding after the outlet"
    FLEET = "fleet hold"
    FLEET_ON_GROUND = "fleet hold (on the ground)"
    PILOT_OVERRIDE = "pilot override"
    POSITION_JUMP = "position jump"
    AGENT_FAULT = "agent fault"


AUTO_RESUMING = frozenset({HoldCause.POSITION_STALE, HoldCause.POSITION_JUMP})
"""Holds that end by themselves when the position is good again (unless latched)."""
JUMP_HOLD_GRACE_S = IntegrityConfig.consistent_s + 1.0
"""The first stage of a position-jump hold lasts at least this long [s]: an estimator reset ends once the track has
been consistent for ``IntegrityConfig.consistent_s`` (2 s) after the jump.  PX4 SIH's EKF2 resets its position near
2 m in every take-off; with the grace equal to that (``hold_grace_s`` 2 s), the hold escalated to the autopilot's hold
mode on the tick before it ended by itself, and the autopilot's answer a HEARTBEAT later read as a foreign mode
change: hands-off (PX4 SITL, 2026-12-06).  A long glitch (a real EKF3 GPS glitch: 15 s) still escalates."""
KEEPING_SPOT = frozenset({HoldCause.FLEET, HoldCause.GEOFENCE})
"""Holds whose first stage (the vehicle still in offboard/guided, ``hold_grace_s``) keeps the spot where
they began: back towards it at most ``HOLD_KEEP_SPEED_M_S``, corrected for the bias of the autopilot's
velocity estimate (``Navigator.goto``).  The others send zero velocity (a stale or jumped position is not
to be trusted).  Zero velocity alone is held on the autopilot's velocity *estimate* and lets the vehicle
drift with its bias: a stock PX4 (SIH) in a fleet hold drifted 0.6 m up and 0.6 m sideways in the 2 s
before its own hold mode (its EKF reporting 0 m/s while its position moved at 0.3-0.4 m/s), then out of
the duct (``tests/faults/test_px4_kills.py``, seed 7, 2026-12-05)."""
HOLD_KEEP_SPEED_M_S = 0.5
"""Fastest a held vehicle is brought back to the spot where its hold began (``KEEPING_SPOT``) [m/s]."""
HoldOutput = tuple[Vec | None, ModeClass | None, bool | None, float | None]
"""A hold's (velocity, mode wanted, armed wanted, take-off height) (``Mission._hold_output``)."""


class Cause(str, Enum):
    """Why the mission entered a state other than HOLD; the value is the default reason text."""

    START = "start"
    AUTOPILOT_FOUND = "position and autopilot heartbeat received"
    WAITING_GO = "ready: waiting for a go (--go, or fisc-ground cmd go)"
    NOT_OURS = "vehicle armed by someone else: not ours (only an addressed takeover hands it over)"
    NOT_READY = "not arming: the vehicle is not ready"
    GO = "go: arming"
    TAKEOFF_TIMEOUT = "take-off timed out: landing"
    LOW_BATTERY = "battery below the minimum"
    ARMED = "armed in offboard/guided"
    ARM_FAILED = "failed: not armed in offboard/guided"
    TAKING_OVER = "already flying: taking over"
    TAKEOFF_DONE = "takeoff height reached"
    ENTERED_MAP = "entered the map"
    BACK_IN_MAP = "back in the map"
    LAP_DONE = "lap done: back to the inlet"
    PASSED_OUTLET = "passed the outlet"
    GEOFENCE_RETURN = "geofence: outside the map, returning to the nearest CV"
    EXIT_LAND = "exit: landing"
    LANDED = "landed and disarmed"
    DISARMED_IN_FLIGHT = "disarmed in flight (landed or killed by the autopilot/pilot)"
    FLEET_LAND = "fleet land"
    FLEET_LAND_DISARMED = "fleet land while disarmed"
    FLEET_RESUME = "fleet resume"
    POSITION_BACK = "position fix back"


BACK_TO_STREAMLINE = frozenset({Cause.FLEET_RESUME, Cause.POSITION_BACK, Cause.BACK_IN_MAP})
"""Returns to FLOW that keep the pass's streamline (``ParcelTracker.resume``): the vehicle flies back onto it
instead of taking a new one where a hold or a geofence return left it.  A hold's drift is the autopilot's, not
the design's: on stock PX4 SIH a fleet hold in the throat drifted 0.3 m outwards (its own hold mode wanders
about 0.7 m), and a new parcel there would have carried that offset to the outlet, 0.23 m from the wall by
PX4's estimate and 0.24 m beyond it by SIH's ground truth (``tests/faults/test_px4_kills.py``, 2026-12-06).
A takeover (``Cause.TAKING_OVER``) and a new pass start a parcel at the vehicle; a position jump has cleared
the parcel (its hold's ``POSITION_BACK`` then starts one too)."""


class Reason(str):
    """Why the mission is in its state: the human text (a ``str``: logged, written to the flight
    log and the status as before) with its typed ``cause``, which is what code decides on."""

    cause: Cause | HoldCause
    """The typed cause."""

    def __new__(cls, cause: Cause | HoldCause, text: str | None = None) -> Reason:
        obj = super().__new__(cls, cause.value if text is None else text)
        obj.cause = cause
        return obj

    def __getnewargs__(self) -> tuple:  # pickling (emulator workers send reasons across processes)
        return (self.cause, str(self))


FLYING = frozenset({State.TAKEOFF, State.JOIN, State.FLOW, State.RETURN, State.EXIT})
"""States in which the agent commands the vehicle in offboard/guided."""


class VehicleStatus(NamedTuple):
    """What the mission sees each tick (map frame).  Immutable (a NamedTuple: built every tick)."""

    t_s: float
    """Monotonic time [s]."""
    pos_m: Vec | None
    """Newest position, map frame [m]; None if never received."""
    vel_m_s: Vec | None
    """Newest velocity, map frame [m/s]."""
    position_age_s: float
    """Age of the newest position [s]; inf if none."""
    heartbeat_age_s: float
    """Age of the newest autopilot HEARTBEAT [s]; inf if none."""
    autopilot: str | None
    """``px4``, ``ardupilot`` or None while unknown."""
    armed: bool
    """Armed flag from the HEARTBEAT."""
    mode: ModeClass
    """Autopilot mode class: ``offboard`` (PX4 OFFBOARD / ArduPilot GUIDED), ``hold``, ``land``,
    ``other`` or ``unknown``."""
    wall_time_s: float = 0.0
    """UNIX time [s] (the shared clock of the entry slots; GNSS/NTP-disciplined on real vehicles)."""
    fix_t_s: float | None = None
    """The autopilot's own time of the newest fix [s] (``PositionSample.autopilot_t_s``), None when the
    link gives none: the velocity-estimate bias is learnt on this clock, else on the fix's receive time."""
    health: VehicleHealth = VehicleHealth()
    """The autopilot's own view of its health (battery, landed state, estimator)."""
    integrity_ok: bool = True
    """The position track is consistent (no estimator reset or jump since a consistent track)."""
    integrity_reason: str = ""
    """Why it is not ("" when it is)."""
    gnss_vel_m_s: tuple[float, float] | None = None
    """The GNSS receiver's own horizontal velocity, map frame (x, y) [m/s], while fresh
    (``tracking.GNSS_FRESH_S``); None without one."""


class MissionOutput(NamedTuple):
    """What the mission wants this tick.  Immutable (a NamedTuple: built every tick)."""

    state: State
    """State after this step."""
    velocity_m_s: Vec | None
    """Map-frame velocity setpoint to stream (unclamped); None = stream nothing."""
    want_mode: ModeClass | None
    """``offboard``, ``hold``, ``land`` or None (leave the mode alone)."""
    want_armed: bool | None
    """True to arm; None = leave alone."""
    takeoff_alt_m: float | None
    """ArduPilot: takeoff height above home to command; None otherwise."""
    cv_id: int
    """CV of the vehicle, -1 outside the map (or no position/map)."""
    reason: Reason
    """Why the mission is in this state (last transition's reason)."""


@dataclass(frozen=True)
class Transition:
    """One logged state change."""

    t_s: float
    """Time of the change [s]."""
    src: State
    """State left."""
    dst: State
    """State entered."""
    reason: Reason
    """Why."""
