"""The vehicle link: MAVLink endpoints and framing, the pymavlink link, the PX4 / ArduPilot
adapters that turn intents (arm, set_mode, takeoff, hold, land, send_velocity) into MAVLink, and the
optional MAVSDK backend.

Interface: ``link.VehicleLink`` (the Protocol of intents), ``link.open_link``, ``adapters.ModeClass``.
"""
