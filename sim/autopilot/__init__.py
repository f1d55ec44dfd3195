"""MAVLink autopilot emulator (PX4 / ArduPilot Copter personalities) on the paper's VelocityPlant.

* :mod:`~sim.autopilot.personalities` - mode encodings, autopilot types, parameter tables
* :mod:`~sim.autopilot.vehicle_types` - outcomes, setpoints, settings and snapshots (frozen data)
* :mod:`~sim.autopilot.vehicle` - pure state machine + physics on an injected clock
* :mod:`~sim.autopilot.faults` - packet loss, latency, position dropouts
* :mod:`~sim.autopilot.setpoints` - SET_POSITION_TARGET_* and takeoff altitudes to local NED
* :mod:`~sim.autopilot.telemetry` - streamed messages from a vehicle snapshot (WGS-84 via fisc_agent.flight.frames)
* :mod:`~sim.autopilot.streams` - per-message stream intervals
* :mod:`~sim.autopilot.framing` - MAVLink 2 encoder and per-peer parsers (pymavlink public API)
* :mod:`~sim.autopilot.transport` - UDP/TCP sockets; endpoints parsed by fisc_agent.mavlink.endpoints
* :mod:`~sim.autopilot.server` - :class:`AutopilotEmulator`: the loop and the command handling
* :mod:`~sim.autopilot.cli` - ``fisc-sim autopilot``
"""

from sim.autopilot.personalities import ARDUPILOT, PX4, FlightMode, Personality, get_personality
from sim.autopilot.server import AutopilotEmulator
from sim.autopilot.transport import parse_emulator_endpoint
from sim.autopilot.vehicle import Vehicle
from sim.autopilot.vehicle_types import Setpoint, VehicleConfig, VehicleState

__all__ = [
    "ARDUPILOT",
    "PX4",
    "AutopilotEmulator",
    "FlightMode",
    "Personality",
    "Setpoint",
    "Vehicle",
    "VehicleConfig",
    "VehicleState",
    "get_personality",
    "parse_emulator_endpoint",
]
