"""Zenoh onboard: the swarm's key expressions, sessions, map subscription, fleet commands and
telemetry, with their pure binary codecs.

Interface: ``runner.connect_runner`` wires a ``fisc_agent.runner.Runner`` to a session;
``telemetry_codec`` and ``fleet_commands`` are the wire formats the ground shares.
"""
