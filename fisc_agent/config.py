"""``AgentConfig``: everything the onboard agent needs to fly, validated on construction."""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

from fisc_agent.flight.drag import DragConfig
from fisc_agent.flight.failsafe import GeofencePolicy
from fisc_agent.flight.frames import DEFAULT_ORIGIN_NED_M, DeploymentTransform, GeodeticAnchor
from fisc_agent.map.lookup import COMMAND_MODES
from fisc_agent.flight.safety_net import SafetyNetConfig
from fisc_agent.flight.tracking import TrackingConfig



class ExitPolicy(StrEnum):
    """What an agent does once it has passed the outlet."""

    HOLD = "hold"
    """Stop ``exit_clearance_m`` beyond the outlet at the agent's own point (``exit_spacing_m``) and hold (latched)."""
    LAND = "land"
    """Land straight below the agent's own hold spot beyond the outlet (``exit_spacing_m`` apart horizontally)."""
    LOOP = "loop"
    """Fly back to the inlet outside the tunnel and go round again (``laps``)."""


AUTOPILOTS = ("auto", "px4", "ardupilot")
BACKENDS = ("pymavlink", "mavsdk")
EXIT_POLICIES = tuple(p.value for p in ExitPolicy)
GEOFENCE_POLICIES = tuple(p.value for p in GeofencePolicy)


@dataclass(frozen=True)
class AgentConfig:
    """Configuration of one ``fisc-agent`` (CLI flags map 1:1 to fields)."""

    mavlink_url: str
    """Autopilot endpoint (``udpin:0.0.0.0:14540``, ``udp://:14540``, ``/dev/ttyACM0:57600`` ...)."""
    agent_id: int
    """This agent's id N >= 0: selects its slot (slot mode) and its entry point in the inlet disc."""
    map_path: str | None = None
    """Command map file (.fiscmap); None when the map arrives over the network."""
    trusted_key: str | None = None
    """Ed25519 public key file (.pub); when set, maps must be signed by it."""
    autopilot: str = "auto"
    """``px4``, ``ardupilot`` or ``auto`` (from the autopilot's HEARTBEAT)."""
    backend: str = "pymavlink"
    """MAVLink backend: ``pymavlink`` (default) or ``mavsdk`` (optional dependency, PX4 only)."""
    mode: str | None = None
    """Command mode (``fisc_agent.map.lookup.COMMAND_MODES``, DESIGN.md section 3); None: the map's
    recommended mode (``mean`` for a schema-1 map).  Under streamline tracking ``kinetic`` flies the
    ``staggered`` field with its deviations, turned before the map's real wall; a map without the wall
    (``duct_wall_m``) or ``wall_margin_m`` None flies a recommended ``kinetic`` as ``staggered``, one given
    here with its deviations turning at the staircase (``point_command.tracked_mode``)."""
    lookahead_s: float | None = None
    """Command look-ahead t_lead [s] (``fisc_agent.map.lookup.lookahead_point``); None: the map's
    recommended value (0 for a schema-1 map).  A lag identified in flight is passed the same way."""
    wall_margin_m: float | None = 0.8
    """``kinetic`` mode under streamline tracking: the deviation's outward radial component is mirrored
    within a margin of the duct's real wall, where the map carries it (array ``duct_wall_m``,
    ``fisc_agent.map.wall``) [m]; None: the deviation reflects at the CV staircase only, as the simulator's
    agents do (the staircase's outer cubes lie partly outside a real duct).  Onboard the margin is fixed:
    the duct-adapted margin (``fisc_agent.map.wall.effective_margin_m``: half the local radius, never below
    d_min / 2, so the deviations fill the throat instead of folding onto its axis) took a real PX4 0.43 m
    beyond the wall by SIH's ground truth, and waits for issue 37's real-swarm flights.  The margin must cover the vehicle's overshoot and the error of
    its position estimate: on PX4 SITL (SIH) the altitude estimate strayed up to 0.9 m from the ground
    truth, and with a fixed 0.8 m six passes went at most 0.17 m beyond the wall by that truth
    (docs/deployment.md).  With motion-capture positions a smaller margin keeps more of the deviation."""
    tracking: TrackingConfig = TrackingConfig()
    """Streamline tracking: cross-stream feedback on the agent's own streamline (``fisc_agent.flight.tracking``);
    ``gain_1_s = 0`` flies the simulator's command function open loop."""
    drag: DragConfig = DragConfig()
    """The vehicle's drag identified in flight from its attitude and fed forward with each velocity setpoint
    (``fisc_agent.flight.drag``; PX4 only)."""
    safety_net: SafetyNetConfig | None = SafetyNetConfig()
    """The separation safety net (``fisc_agent.flight.safety_net``): with a Zenoh link the agent hears
    its neighbours' telemetry; closing on one faster than reaches the map's d_min (more for a stale
    report) within the net's horizon, it slows, and inside d_min it pushes apart; elsewhere the paper's
    law is flown unchanged.  None (``--safety-net off``): the paper's law alone."""
    lookahead_auto: bool = True
    """Identify the vehicle's velocity response in flight (take-off and join) and set the look-ahead and
    feed-forward gain from it (``--lookahead auto``); False: ``lookahead_s`` as given (or the map's)."""
    rate_hz: float = 20.0
    """Setpoint rate [Hz]; PX4 needs > 2 Hz, ArduPilot's GUID_TIMEOUT needs > 1/3 Hz."""
    origin_ned_m: tuple[float, float, float] = DEFAULT_ORIGIN_NED_M
    """Local NED position of the map origin [m] (deployment transform)."""
    yaw_deg: float = 0.0
    """Map x-axis direction, clockwise from North [deg] (deployment transform)."""
    geodetic_anchor: GeodeticAnchor | None = None
    """Map origin as (lat, lon, alt AMSL, heading); then positions come from GLOBAL_POSITION_INT."""
    max_speed_m_s: float = 5.0
    """Speed clamp on every setpoint [m/s]."""
    max_accel_m_s2: float = 3.0
    """Acceleration clamp on every setpoint, |dv|/dt [m/s^2]."""
    join_speed_m_s: float = 2.0
    """Speed while flying to the inlet (JOIN, loop return) [m/s]."""
    return_speed_m_s: float = 1.0
    """Speed when flying straight back to the nearest CV (geofence ``return``) from farther than
    ``fisc_agent.map.lookup.RETURN_RADIUS_CELLS`` cells; nearer, the vehicle rejoins the flow of that CV
    (``fisc_agent.map.lookup.return_command``, the simulator's rule) [m/s]."""
    climb_speed_m_s: float = 1.0
    """Climb rate of a setpoint takeoff (PX4 offboard, or finishing an interrupted ArduPilot takeoff) [m/s]."""
    takeoff_alt_m: float = 2.5
    """Takeoff height above the start position [m]."""
    exit_policy: ExitPolicy = ExitPolicy.HOLD
    """After the outlet (``ExitPolicy``; its value as a string is accepted and converted)."""
    laps: int = 0
    """With ``loop``: number of passes before applying ``hold`` (0 = loop until told otherwise)."""
    geofence: GeofencePolicy = GeofencePolicy.HOLD
    """Leaving the map's CVs (not through the outlet) while flowing (``fisc_agent.flight.failsafe.GeofencePolicy``;
    its value as a string is accepted and converted)."""
    stale_timeout_s: float = 0.5
    """Position older than this is stale -> zero-velocity hold setpoints [s]."""
    hold_grace_s: float = 2.0
    """Stale this much longer -> request the autopilot's hold/loiter mode [s]."""
    link_timeout_s: float = 3.0
    """No autopilot HEARTBEAT for this long -> link lost (reported, mission holds) [s]."""
    command_retry_s: float = 1.0
    """Resend an unacknowledged or unsatisfied mode/arm/takeoff command after this [s]."""
    command_timeout_s: float = 30.0
    """Give up arming / entering offboard after this long (mission ends, reason logged) [s]."""
    staging_m: float = 1.5
    """Staging point distance upstream of the inlet plane [m]."""
    keepout_margin_m: float = 1.0
    """Margin around the tunnel's bounding box kept clear while joining [m]."""
    waypoint_radius_m: float = 0.3
    """Acceptance radius of join waypoints [m]."""
    entry_radius_fraction: float = 0.6
    """Entry points are spread over this fraction of the inlet radius (``control.entry_point``): 0.6
    keeps a real duct's wall clear; 1 spreads them over every inlet CV (``fisc-sim emulate``'s default).
    Ids 0..63 have 64 distinct points (``fisc_agent.flight.spacing.ENTRY_POINTS``), at least 0.193 x this
    fraction x the inlet radius apart when all lie in inlet CVs (0.6: 0.12 m on a 1 m inlet)."""
    entry_stagger_s: float | None = None
    """Staggered entry: agents cross the inlet in windows of this length on the shared clock (on real
    vehicles GNSS time, ``VehicleStatus.wall_time_s``), agent i in window ``i mod entry_slots``
    (``spacing.entry_slot_open``); 0 = enter as soon as staged; None (``--entry-stagger auto``): the map's
    admission period (``separation.admission_period_s``, ``fisc_agent.flight.spacing.entry_schedule``), no
    stagger on a map without one [s]."""
    entry_slots: int | None = None
    """Number of entry windows in a stagger cycle (agents with equal ``id mod entry_slots`` share one).
    Two ids share both their window and their entry point only if they are equal modulo
    lcm(64, ``entry_slots``): never among ids 0..63.  None: with the map's admission period the map's
    ``separation.max_in_tunnel`` (a fleet within the budget has a window per vehicle), else
    ``spacing.DEFAULT_ENTRY_SLOTS`` (8)."""
    exit_clearance_m: float = 5.0
    """With exit ``hold``/``land``: the first row of hold spots lies this far downstream of the outlet
    plane; the exit climbs over the spots until ``exit_clearance_m - exit_spacing_m`` beyond the outlet
    (``routes.exit_waypoints``), so a vehicle keeps moving downstream as it leaves the stream
    (with 0.5 m of room, a leader slowed there and its follower came within 0.47 m on real PX4) [m]."""
    exit_spacing_m: float = 3.0
    """With exit ``hold``/``land``: least horizontal distance between two agents' hold spots, and so
    between their landing spots (``control.hold_point``: a square lattice of this pitch in the horizontal
    plane from ``exit_clearance_m`` beyond the outlet, agent i on the i-th site nearest the axis; any two
    ids, not only 0..49, are at least this far apart).  Spots are at the axis height, at least
    ``spacing.HOLD_FLOOR_MARGIN_M`` above the tunnel's floor.  The default leaves d_min between two
    neighbours that each wander 1.1 m in the autopilot's hold (PX4 SIH's Hold, ground truth: with a
    1.5 m pitch two held vehicles came within 0.82 m) [m]."""
    go: bool = False
    """Permission to arm and fly one flight given on the command line (``--go``: a bench or SITL
    flight); without it the agent waits disarmed for a fleet ``go`` / ``start-at``."""
    min_battery_pct: float | None = 20.0
    """Below this remaining battery [%] the agent finishes its pass, then ``low_battery_action``; it never
    starts a pass or arms below it; None: no battery rule (the autopilot's own failsafes still apply)."""
    low_battery_action: ExitPolicy = ExitPolicy.LAND
    """What follows the last pass on a low battery: ``land`` or ``hold`` at the exit point."""
    takeoff_timeout_s: float = 30.0
    """A take-off that has not reached its height (and left the ground) after this long lands [s]."""
    max_start_distance_m: float = 200.0
    """Do not arm when the start point is farther than this from the map's bounding box [m] (a wrong
    anchor or origin would fly the vehicle far away)."""
    target_system: int | None = None
    """MAVLink system id of the one autopilot this agent flies; None: the first one heard, then pinned."""
    state_file: str | None = "auto"
    """The agent's state file (``fisc_agent.flight.state_file``): a path; ``auto``: the per-user default
    ``$XDG_STATE_HOME/fisc/agent-<swarm>-<id>.json`` (``state_file.default_state_path``); None: no file
    (a restart forgets: the emulator's in-process agents)."""
    source_system: int | None = None
    """MAVLink system id of the agent; None = the vehicle's own id (companion convention)."""
    source_component: int = 191
    """MAVLink component id of the agent (191 = MAV_COMP_ID_ONBOARD_COMPUTER)."""

    def __post_init__(self) -> None:
        def need(cond: bool, msg: str) -> None:
            if not cond:
                raise ValueError(f"config: {msg}")

        need(isinstance(self.agent_id, int) and self.agent_id >= 0, f"agent id must be >= 0, is {self.agent_id!r}")
        need(self.autopilot in AUTOPILOTS, f"autopilot must be one of {AUTOPILOTS}, is {self.autopilot!r}")
        need(self.backend in BACKENDS, f"backend must be one of {BACKENDS}, is {self.backend!r}")
        need(self.mode is None or self.mode in COMMAND_MODES, f"mode must be one of {COMMAND_MODES}, is {self.mode!r}")
        need(self.lookahead_s is None or (isinstance(self.lookahead_s, (int, float)) and math.isfinite(self.lookahead_s)
                                          and self.lookahead_s >= 0),
             f"lookahead_s must be a finite number >= 0 seconds, is {self.lookahead_s!r}")
        need(self.wall_margin_m is None or (isinstance(self.wall_margin_m, (int, float))
                                            and math.isfinite(self.wall_margin_m) and self.wall_margin_m >= 0),
             f"wall_margin_m must be a finite number >= 0 metres or None, is {self.wall_margin_m!r}")
        for name, kind in (("exit_policy", ExitPolicy), ("geofence", GeofencePolicy), ("low_battery_action", ExitPolicy)):
            value = getattr(self, name)
            need(value in tuple(kind), f"{name} must be one of {', '.join(kind)}, is {value!r}")
            object.__setattr__(self, name, kind(value))  # typed from here on
        need(2.0 < self.rate_hz <= 500.0, f"rate must be in (2, 500] Hz (PX4 needs > 2 Hz), is {self.rate_hz}")
        for name in ("max_speed_m_s", "max_accel_m_s2", "join_speed_m_s", "return_speed_m_s", "climb_speed_m_s",
                     "takeoff_alt_m", "stale_timeout_s", "link_timeout_s", "command_retry_s",
                     "command_timeout_s", "waypoint_radius_m", "exit_spacing_m", "takeoff_timeout_s",
                     "max_start_distance_m"):
            v = getattr(self, name)
            need(isinstance(v, (int, float)) and math.isfinite(v) and v > 0, f"{name} must be > 0, is {v!r}")
        for name in ("hold_grace_s", "staging_m", "keepout_margin_m", "exit_clearance_m"):
            v = getattr(self, name)
            need(math.isfinite(v) and v >= 0, f"{name} must be >= 0, is {v!r}")
        need(0.0 < self.entry_radius_fraction <= 1.0, "entry_radius_fraction must be in (0, 1]")
        need(self.laps >= 0, "laps must be >= 0")
        need(self.entry_stagger_s is None or (isinstance(self.entry_stagger_s, (int, float))
                                              and math.isfinite(self.entry_stagger_s) and self.entry_stagger_s >= 0),
             f"entry_stagger_s must be a finite number >= 0 seconds or None (auto), is {self.entry_stagger_s!r}")
        need(self.entry_slots is None or (isinstance(self.entry_slots, int) and self.entry_slots >= 1),
             f"entry_slots must be an integer >= 1 or None (auto), is {self.entry_slots!r}")
        need(self.source_system is None or 1 <= self.source_system <= 255, "source_system must be 1..255")
        need(self.target_system is None or 1 <= self.target_system <= 255, "target_system must be 1..255")
        need(self.min_battery_pct is None or 0.0 <= self.min_battery_pct < 100.0,
             f"min_battery_pct must be in [0, 100) or None, is {self.min_battery_pct!r}")
        need(self.low_battery_action in (ExitPolicy.LAND, ExitPolicy.HOLD), "low_battery_action must be land or hold")
        need(0 <= self.source_component <= 255, "source_component must be 0..255")
        DeploymentTransform(self.origin_ned_m, self.yaw_deg)  # validates
        need(self.geodetic_anchor is None or (tuple(self.origin_ned_m) == DEFAULT_ORIGIN_NED_M and self.yaw_deg == 0.0),
             "give either --origin/--yaw (shared EKF origin) or --geodetic-anchor (its heading is the yaw), not both")

    @property
    def transform(self) -> DeploymentTransform:
        """The deployment transform in use (anchor-NED when a geodetic anchor is set)."""
        if self.geodetic_anchor is not None:
            return self.geodetic_anchor.transform()
        return DeploymentTransform(self.origin_ned_m, self.yaw_deg)

    @property
    def period_s(self) -> float:
        """Control period 1 / rate_hz [s]."""
        return 1.0 / self.rate_hz
