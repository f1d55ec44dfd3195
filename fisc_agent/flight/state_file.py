"""The agent's small state file (``fisc-agent --state-file``): what a restarted agent must not forget.

A restart (a crash, a watchdog, a companion reboot) must not hand a held fleet its take-off back,
lose the laps flown, forget that a pilot took the vehicle, or accept a fleet command it had
already seen.  The file is JSON, written atomically (temporary file, fsync, rename) whenever one
of these changes; a missing file is a first start; an unreadable one is kept aside as
``<file>.corrupt`` and the agent starts from the cautious defaults, saying so.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

log = logging.getLogger(__name__)

VERSION = 1


@dataclass(frozen=True)
class AgentState:
    """What survives a restart of the agent process."""

    hands_off: bool = False
    """Someone else took the vehicle during the last flight (only an addressed command gives it back)."""
    fleet_hold: bool = False
    """A fleet hold was in force (a restarted agent stays on the ground until a resume)."""
    laps: int = 0
    """Passes completed in the current flight."""
    command_floors: dict[str, int] = field(default_factory=dict)
    """Newest accepted fleet-command sequence per ground key id (replay protection across restarts)."""

    def to_json(self) -> str:
        """The file's text."""
        return json.dumps({"version": VERSION, **asdict(self)}, sort_keys=True, indent=1)

    @classmethod
    def from_json(cls, text: str, source: str = "state file") -> AgentState:
        """Parse the file's text; ``ValueError`` naming the field that is wrong."""
        try:
            raw = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{source}: not JSON ({exc})") from None
        if not isinstance(raw, dict) or raw.get("version") != VERSION:
            raise ValueError(f"{source}: field 'version' must be {VERSION}")

        def need(name: str, kind: type, ok=lambda v: True):
            v = raw.get(name, getattr(cls, name, None) if name != "command_floors" else {})
            if not isinstance(v, kind) or isinstance(v, bool) != (kind is bool) or not ok(v):
                raise ValueError(f"{source}: field {name!r} is invalid ({v!r})")
            return v

        floors = need("command_floors", dict)
        if not all(isinstance(k, str) and isinstance(v, int) and not isinstance(v, bool) and v >= 0
                   for k, v in floors.items()):
            raise ValueError(f"{source}: field 'command_floors' must map key ids to sequence numbers >= 0")
        return cls(hands_off=need("hands_off", bool), fleet_hold=need("fleet_hold", bool),
                   laps=need("laps", int, lambda v: v >= 0), command_floors=dict(floors))


def load_state(path: str | Path) -> AgentState:
    """The saved state; defaults on a first start (no file).  An unreadable or invalid file is
    renamed ``<path>.corrupt`` (kept for a person to read) and the defaults are returned, logged."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        log.info("state file %s does not exist yet: first start", p)
        return AgentState()
    except (OSError, UnicodeDecodeError) as exc:
        log.error("state file %s unreadable (%s): starting from the defaults", p, exc)
        return AgentState()
    try:
        return AgentState.from_json(text, str(p))
    except ValueError as exc:
        aside = p.with_name(p.name + ".corrupt")
        try:
            os.replace(p, aside)
        except OSError:
            aside = p
        log.error("%s; kept as %s, starting from the defaults", exc, aside)
        return AgentState()


def save_state(path: str | Path, state: AgentState) -> None:
    """Write ``state`` atomically (a reader sees the old file or the new one, never a half)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=p.name + ".", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(state.to_json())
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def default_state_path(agent_id: int, swarm: str | None) -> Path:
    """``$XDG_STATE_HOME/fisc/agent-<swarm>-<id>.json`` (``~/.local/state`` without XDG_STATE_HOME)."""
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(base) / "fisc" / f"agent-{swarm or 'local'}-{agent_id}.json"
