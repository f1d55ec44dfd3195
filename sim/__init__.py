"""FISC simulation: VelocityPlant, swarm simulator, MAVLink autopilot emulator, reports."""
