"""The agent bookkeeping of a swarm run (``sim.swarm.Swarm.counters``; re-exported by ``sim.swarm``)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class SwarmCounters:
    """Agent bookkeeping of a run (``injected == alive + exited + escaped``)."""

    injected: int = 0
    """Agents added (seeded or injected from the reservoir)."""
    exited: int = 0
    """Agents removed past the outlet (normal outflow)."""
    escaped: int = 0
    """Agents removed after leaving the CVs sideways/upstream for longer than the grace period."""
    returned: int = 0
    """Agent-steps spent under the return policy (outside every CV, flying back)."""
    steps: int = 0
    """Steps taken."""
    agent_steps: int = 0
    """Sum over steps of the agents alive during the step."""

    @property
    def removed(self) -> int:
        """exited + escaped."""
        return self.exited + self.escaped


__all__ = ["SwarmCounters"]
