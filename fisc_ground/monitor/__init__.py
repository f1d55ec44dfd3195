"""The ground-station monitor: telemetry in, fleet view and per-CV fields out (aggregator),
the terminal view, the Foxglove scene, MCAP flight logs and their replay.

Interface: ``run.run_monitor``; ``aggregator.TelemetryAggregator`` (pure); ``recording.replay``.
"""
