"""MAVLink autopilot emulator (PX4 / ArduPilot Copter personalities) on the paper's VelocityPlant.

* :mod:`~sim.autopilot.personalities` - mode encodings, autopilot types, parameter tables
* :mod:`~sim.autopilot.vehicle` - pure state machine + physics on an injected clock
* :mod:`~sim.autopilot.faults` - packet loss, latency, position dropouts
* :mod:`~sim.autopilot.server` - :class:`AutopilotEmulator`, the MAVLink I/O
* :mod:`~sim.autopilot.cli` - ``fisc-sim autopilot``
"""

from sim.autopilot.personalities import ARDUPILOT, PX4, FlightMode, Personality, get_personality
from sim.autopilot.server import AutopilotEmulator, parse_endpoint
from sim.autopilot.vehicle import Setpoint, Vehicle, VehicleConfig, VehicleState

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
    "parse_endpoint",
]
