"""Zenoh key expressions of one swarm (pure; no zenoh import).

::

    <prefix>/<swarm>/map                      map chunks and announcements (queryable for late joiners)
    <prefix>/<swarm>/cmd                      signed fleet commands
    <prefix>/<swarm>/cmd/latest               the ground's latest commands, re-published (queryable too)
    <prefix>/<swarm>/agents/<id>/telemetry    telemetry (``fisc_agent.zenoh.telemetry_codec``)
"""

from __future__ import annotations

from dataclasses import dataclass

from fisc_agent.common.names import check_prefix, check_swarm_name

DEFAULT_PREFIX = "fisc"
"""Root of every key expression unless ``--prefix`` says otherwise."""


@dataclass(frozen=True)
class Keys:
    """The key expressions of one swarm."""

    prefix: str
    """Configurable root (default ``fisc``)."""
    swarm: str
    """Swarm name (one key segment)."""

    def __post_init__(self) -> None:  # the one name rule of every command (fisc_agent.common.names)
        check_prefix(self.prefix)
        check_swarm_name(self.swarm)

    @property
    def map(self) -> str:
        """Map chunks and announcements."""
        return f"{self.prefix}/{self.swarm}/map"

    @property
    def cmd(self) -> str:
        """Signed fleet commands."""
        return f"{self.prefix}/{self.swarm}/cmd"

    @property
    def cmd_latest(self) -> str:
        """The latest go / hold / land commands, re-published as one bundle (``fisc_agent.zenoh.state_bundle``)."""
        return f"{self.prefix}/{self.swarm}/cmd/latest"

    def telemetry(self, agent_id: int | str) -> str:
        """Telemetry of one agent."""
        return f"{self.prefix}/{self.swarm}/agents/{agent_id}/telemetry"

    @property
    def all_telemetry(self) -> str:
        """Telemetry of every agent of the swarm (a wildcard)."""
        return f"{self.prefix}/{self.swarm}/agents/*/telemetry"

    def agent_of(self, key: str) -> int | None:
        """Agent id from a telemetry key (None if the key is not one)."""
        parts = str(key).split("/")
        try:
            return int(parts[-2]) if parts[-1] == "telemetry" and parts[-3] == "agents" else None
        except (ValueError, IndexError):
            return None
