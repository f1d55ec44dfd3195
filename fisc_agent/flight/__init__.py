"""Flying one vehicle (pure cores, simulated clocks): the mission state machine and its vocabulary,
the control law, the routes around the tunnel, streamline tracking, in-flight identification, failsafes,
the position gate, frames between the map and the vehicle, and the per-tick flight log.

Interface: ``mission.Mission.step(status, now) -> MissionOutput``; ``control`` position -> setpoint.
"""
