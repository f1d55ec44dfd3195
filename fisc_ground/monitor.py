"""Ground-station monitor: telemetry -> live per-CV swarm fields, fleet state, alarms.

Data path (nothing in it waits on the screen)::

    Zenoh callback --(bounded queue, drop counter)--> consumer thread --> recorder (--record)
                                                                      \\-> TelemetryAggregator
    renderer (rich Live, its own pace) <-- aggregator.view() under a lock

``TelemetryAggregator`` is deterministic in the message sequence: fed the same
``(receive time, key agent id, payload)`` stream in any batching, it produces the same fields.
That is what makes ``fisc-ground replay`` of a recording equal to the live estimate.  The fleet
is sampled every ``sample_period_s`` of receive time: at each sample, every agent heard within
``stale_after_s`` contributes its newest position (CV via ``CommandField.cv_of``) and velocity
to a ``FieldAccumulator`` (the paper's quartet, time-averaged; the dispersion pressure uses
the CV target command ``S v_target`` as reference, as ``fisc-sim run`` does).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from fisc_agent import telemetry_codec as tc
from fisc_agent.lookup import CommandField
from fisc_agent.mapfile import CommandMap
from fisc_agent.zenoh_keys import Keys
from fisc_ground.swarm_fields import FieldAccumulator, SwarmFields

log = logging.getLogger(__name__)

FLYING_STATES = frozenset({"TAKEOFF", "JOIN", "FLOW", "RETURN", "EXIT"})
NO_AGENT = 0xFFFFFFFF
"""Key agent id of a message whose key names no valid agent (telemetry ids are u32)."""
DEFAULT_MAX_AGENTS = 10_000
"""Agent ids the monitor tracks at most; messages from further new ids are counted, not shown."""


class AgentRoster:
    """The agent ids a monitor accepts telemetry from: inclusive ranges, e.g. ``"1-100,205"``.

    Stored as ranges (not a set), so ``0-4294967294`` costs two numbers."""

    def __init__(self, ranges: list[tuple[int, int]]) -> None:
        merged: list[list[int]] = []
        for lo, hi in sorted(ranges):
            if not 0 <= lo <= hi < NO_AGENT:
                raise ValueError(f"agent id range {lo}-{hi} outside 0..{NO_AGENT - 1}")
            if merged and lo <= merged[-1][1] + 1:
                merged[-1][1] = max(merged[-1][1], hi)
            else:
                merged.append([lo, hi])
        if not merged:
            raise ValueError("an agent roster needs at least one id")
        self.lo = np.array([m[0] for m in merged], dtype=np.int64)
        self.hi = np.array([m[1] for m in merged], dtype=np.int64)

    @classmethod
    def parse(cls, text: str) -> "AgentRoster":
        """``"1-100,205"`` -> roster (ids are decimal integers; ranges inclusive)."""
        ranges = []
        for part in str(text).split(","):
            part = part.strip()
            lo, sep, hi = part.partition("-")
            try:
                ranges.append((int(lo), int(hi) if sep else int(lo)))
            except ValueError:
                raise ValueError(f"roster: {part!r} is not an agent id or an id range like 1-100") from None
        return cls(ranges)

    def spec(self) -> str:
        """The canonical text form (``parse(spec())`` gives the same roster)."""
        return ",".join(f"{a}-{b}" if a != b else str(a) for a, b in zip(self.lo.tolist(), self.hi.tolist()))

    def contains(self, ids: np.ndarray) -> np.ndarray:
        """Boolean mask: which ``ids`` are on the roster."""
        ids = np.asarray(ids, dtype=np.int64)
        k = np.searchsorted(self.lo, ids, side="right") - 1
        inside = k >= 0
        inside[inside] = ids[inside] <= self.hi[k[inside]]
        return inside


@dataclass(frozen=True)
class FleetView:
    """What the dashboard shows at one instant."""

    now_s: float
    """Time of the view (receive-time clock) [UNIX s]."""
    n_agents: int
    """Agents ever heard."""
    by_state: dict[str, int]
    """Live (not stale) agents per state."""
    stale: tuple[int, ...]
    """Agents not heard for ``stale_after_s``."""
    map_versions: dict[int, int]
    """map_version -> live agents flying it."""
    alarms: tuple[str, ...]
    """Human-readable alarms (outside the tunnel, failsafes, refused maps, foreign maps, spoofing)."""
    messages: int
    """Messages ingested."""
    bad_messages: int
    """Undecodable messages (wrong version or size)."""
    spoofed: int
    """Messages whose payload agent id differs from their key's."""
    time_samples: int
    """Fleet samples in the field average."""
    off_roster: int = 0
    """Messages from agent ids not on the roster (``--roster``), not shown."""
    over_cap: int = 0
    """Messages from new agent ids refused because ``max_agents`` ids are already tracked."""


class TelemetryAggregator:
    """Newest telemetry per agent plus time-averaged swarm fields over the map's CVs."""

    def __init__(self, cmap: CommandMap | None = None, sample_period_s: float = 0.5, stale_after_s: float = 3.0,
                 roster: AgentRoster | None = None, max_agents: int = DEFAULT_MAX_AGENTS) -> None:
        if not sample_period_s > 0 or not stale_after_s > 0:
            raise ValueError("sample_period_s and stale_after_s must be > 0")
        if int(max_agents) < 1:
            raise ValueError(f"max_agents must be >= 1, got {max_agents}")
        self.sample_period_s = float(sample_period_s)
        self.stale_after_s = float(stale_after_s)
        self.roster = roster
        """Agent ids accepted (None: any id, up to ``max_agents``)."""
        self.max_agents = int(max_agents)
        """Most agent ids tracked; later new ids are refused and counted in ``over_cap``."""
        self.slots: dict[int, int] = {}
        self.latest = np.zeros(64, dtype=tc.DTYPE)
        self.seen_s = np.full(64, -math.inf)
        self.messages = self.bad_messages = self.spoofed = self.off_roster = self.over_cap = 0
        self.next_sample_s: float | None = None
        self._tmax = -math.inf
        self.cmap: CommandMap | None = None
        self.field: CommandField | None = None
        self.acc: FieldAccumulator | None = None
        if cmap is not None:
            self.set_map(cmap)

    # -- map -----------------------------------------------------------------------------------
    def set_map(self, cmap: CommandMap) -> None:
        """Use this map's CVs (restarts the field average)."""
        self.cmap = cmap
        self.field = CommandField.from_map(cmap)
        self.acc = FieldAccumulator(cmap.n_cv, cmap.cell_size_m ** 3)
        self._mass_kg = float(cmap.body.get("agent_mass_kg", 1.0))
        self._target_cmd = cmap.scale * np.asarray(cmap["target_velocity_m_s"], dtype=float)

    # -- ingest --------------------------------------------------------------------------------
    def ingest(self, recv_s: np.ndarray, key_ids: np.ndarray, payloads: list[bytes]) -> None:
        """Feed messages in arrival order: receive times [UNIX s], agent id from each key
        (``NO_AGENT`` if none), raw payloads."""
        n = len(payloads)
        if n == 0:
            return
        recv_s = np.asarray(recv_s, dtype=float)
        key_ids = np.asarray(key_ids, dtype=np.int64)
        records, ok = tc.decode_many(payloads)
        self.messages += n
        self.bad_messages += int((~ok).sum())
        spoof = ok & (records["agent_id"].astype(np.int64) != key_ids)
        self.spoofed += int(spoof.sum())
        ok &= ~spoof
        if self.roster is not None:
            off = ok & ~self.roster.contains(key_ids)
            self.off_roster += int(off.sum())
            ok &= ~off
        tmax = np.maximum.accumulate(np.r_[self._tmax, recv_s])[1:]
        self._tmax = float(tmax[-1])
        if self.next_sample_s is None:
            self.next_sample_s = (math.floor(recv_s[0] / self.sample_period_s) + 1) * self.sample_period_s
        i = 0
        while i < n:
            j = i + int(np.searchsorted(tmax[i:], self.next_sample_s, side="left"))
            self._update(records[i:j][ok[i:j]], recv_s[i:j][ok[i:j]])
            if j < n:
                self._sample(self.next_sample_s)
                self.next_sample_s = (math.floor(tmax[j] / self.sample_period_s) + 1) * self.sample_period_s
            i = j

    def _slot_of(self, agent_ids: np.ndarray) -> np.ndarray:
        """Slot of each id (new ids get one while fewer than ``max_agents`` are tracked, else -1)."""
        slots = np.empty(len(agent_ids), dtype=np.int64)
        for k, aid in enumerate(agent_ids.tolist()):
            s = self.slots.get(aid)
            if s is None:
                if len(self.slots) >= self.max_agents:
                    s = -1
                else:
                    s = self.slots[aid] = len(self.slots)
            slots[k] = s
        if len(self.slots) > len(self.latest):
            grow = max(len(self.slots), 2 * len(self.latest))
            self.latest = np.concatenate([self.latest, np.zeros(grow - len(self.latest), dtype=tc.DTYPE)])
            self.seen_s = np.concatenate([self.seen_s, np.full(grow - len(self.seen_s), -math.inf)])
        return slots

    def _update(self, records: np.ndarray, recv_s: np.ndarray) -> None:
        if len(records) == 0:
            return
        slots = self._slot_of(records["agent_id"])
        refused = slots < 0
        if refused.any():
            self.over_cap += int(refused.sum())
            slots, records, recv_s = slots[~refused], records[~refused], recv_s[~refused]
            if len(slots) == 0:
                return
        # last message per slot wins (as if applied one by one)
        rev_unique, rev_first = np.unique(slots[::-1], return_index=True)
        last = len(slots) - 1 - rev_first
        self.latest[rev_unique] = records[last]
        self.seen_s[rev_unique] = recv_s[last]

    def _live(self, t: float) -> np.ndarray:
        n = len(self.slots)
        return self.seen_s[:n] > t - self.stale_after_s

    def _sample(self, t: float) -> None:
        if self.acc is None:
            return
        live = self._live(t)
        rec = self.latest[: len(self.slots)][live]
        pos = rec["position_m"].astype(float)
        vel = rec["velocity_m_s"].astype(float)
        good = np.isfinite(pos).all(axis=1) & np.isfinite(vel).all(axis=1)
        cv = self.field.cv_of(pos[good]) if good.any() else np.zeros(0, dtype=np.int64)
        self.acc.add(cv, vel[good], self._mass_kg, self._target_cmd)

    # -- results -------------------------------------------------------------------------------
    @property
    def last_receive_s(self) -> float:
        """Newest receive time ingested (-inf before any message)."""
        return self._tmax

    def fields(self) -> SwarmFields | None:
        """Time-averaged swarm fields so far (None without a map)."""
        return None if self.acc is None else self.acc.result()

    def agents(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(agent ids, newest records, receive times) of every agent heard."""
        n = len(self.slots)
        ids = np.fromiter(self.slots.keys(), dtype=np.int64, count=n)
        return ids, self.latest[:n].copy(), self.seen_s[:n].copy()

    def view(self, now_s: float | None = None) -> FleetView:
        """Fleet state for display; ``now_s`` defaults to the newest receive time."""
        now = self._tmax if now_s is None else float(now_s)
        ids, rec, seen = self.agents()
        live = seen > now - self.stale_after_s
        states = np.array(tc.state_names(rec["state"]), dtype=object)
        by_state: dict[str, int] = {}
        for s in states[live]:
            by_state[s] = by_state.get(s, 0) + 1
        versions: dict[int, int] = {}
        for v in rec["map_version"][live].tolist():
            versions[int(v)] = versions.get(int(v), 0) + 1
        alarms: list[str] = []
        flags = rec["flags"]
        flying = np.isin(states, list(FLYING_STATES))
        if self.field is not None:  # the monitor's own CV assignment from the reported position
            pos = rec["position_m"].astype(float)
            ok = np.isfinite(pos).all(axis=1)
            cv = np.full(len(ids), -1, dtype=np.int64)
            if ok.any():
                cv[ok] = self.field.cv_of(pos[ok])
        else:  # no map: trust the agent's own CV index
            cv = rec["cv_index"].astype(np.int64)
        outside = live & (((flags & tc.FLAG_OUTSIDE_MAP) != 0) | (flying & (cv < 0)))
        for label, mask in (("outside the tunnel", outside),
                            ("failsafe", live & ((flags & tc.FLAG_FAILSAFE) != 0)),
                            ("refused a map", live & (rec["maps_rejected"] > 0))):
            if mask.any():
                alarms.append(f"{label}: agents {_id_list(ids[mask])}")
        if self.cmap is not None:
            want = bytes.fromhex(self.cmap.sha256)
            other = live & np.array([bytes(s) != want for s in rec["map_sha256"]], dtype=bool) & (rec["map_version"] > 0)
            if other.any():
                alarms.append(f"flying another map than {self.cmap.sha256[:12]}: agents {_id_list(ids[other])}")
        if self.spoofed:
            alarms.append(f"{self.spoofed} messages claimed another agent's id (spoofing?)")
        if self.off_roster:
            alarms.append(f"{self.off_roster} messages from agent ids not on the roster (ignored)")
        if self.over_cap:
            alarms.append(f"{self.over_cap} messages from new agent ids refused: {self.max_agents} agents "
                          "already tracked (forged telemetry? raise --max-agents or give --roster)")
        stale = tuple(int(i) for i in ids[~live])
        return FleetView(now_s=now, n_agents=len(ids), by_state=by_state, stale=stale, map_versions=versions,
                         alarms=tuple(alarms), messages=self.messages, bad_messages=self.bad_messages,
                         spoofed=self.spoofed, time_samples=0 if self.acc is None else self.acc.n_time_samples,
                         off_roster=self.off_roster, over_cap=self.over_cap)


def _id_list(ids: np.ndarray, limit: int = 12) -> str:
    ids = sorted(int(i) for i in ids)
    text = ", ".join(str(i) for i in ids[:limit])
    return text + (f" ... (+{len(ids) - limit})" if len(ids) > limit else "")


# --------------------------------------------------------------------------------------------
# Zenoh -> queue -> consumer

class TelemetryPipe:
    """Zenoh subscriber feeding an aggregator (and optionally a recorder) through a bounded queue.

    The Zenoh callback never blocks: when the queue is full the message is counted in
    ``dropped``.  The consumer thread writes each batch to the recorder first, then ingests it,
    so a slow *renderer* (which only reads ``view()``) can never cause a loss.
    """

    def __init__(self, keys: Keys, aggregator: TelemetryAggregator, recorder: Any = None,
                 maxsize: int = 200_000, batch: int = 8192) -> None:
        self.keys = keys
        self.aggregator = aggregator
        self.recorder = recorder
        self.lock = threading.Lock()
        self.dropped = 0
        self.received = 0
        self.worker_errors = 0
        """Batches the consumer failed to process (each logged; the consumer keeps running)."""
        self.lost_to_errors = 0
        """Messages in those batches (not ingested; recorded if the failure came after recording)."""
        self.last_error = ""
        """``Type: message`` of the newest worker error (shown on the dashboard)."""
        self._error_types: set[str] = set()
        self._q: queue.Queue = queue.Queue(maxsize)
        self._batch = int(batch)
        self._stop = threading.Event()
        self._sub = None
        self._thread = threading.Thread(target=self._consume, name="fisc-monitor-consumer", daemon=True)
        self._thread.start()

    def attach(self, session: Any) -> "TelemetryPipe":
        """Subscribe to every agent's telemetry of the swarm on ``session``."""
        self._sub = session.declare_subscriber(self.keys.all_telemetry, self.on_sample)
        return self

    def on_sample(self, sample: Any) -> None:
        self.offer(time.time(), str(sample.key_expr), sample.payload.to_bytes())

    def offer(self, recv_s: float, key: str, payload: bytes) -> None:
        """Enqueue one message (never blocks; counts a drop when full)."""
        self.received += 1
        try:
            self._q.put_nowait((recv_s, key, payload))
        except queue.Full:
            self.dropped += 1

    def set_map(self, cmap: CommandMap, blob: bytes | None = None) -> None:
        """Switch the aggregator (and the recording) to a map, in stream order."""
        self._q.put(("map", cmap, blob))

    def _consume(self) -> None:
        while not self._stop.is_set() or not self._q.empty():
            try:
                items = [self._q.get(timeout=0.05)]
            except queue.Empty:
                continue
            while len(items) < self._batch:
                try:
                    items.append(self._q.get_nowait())
                except queue.Empty:
                    break
            try:
                self._process(items)
            except Exception as exc:  # noqa: BLE001 - no message may kill the consumer: count, log, show
                self._worker_error(exc, items)
            finally:
                for _ in items:
                    self._q.task_done()

    def _worker_error(self, exc: Exception, items: list) -> None:
        name = type(exc).__name__
        self.worker_errors += 1
        self.lost_to_errors += sum(1 for it in items if it[0] != "map")
        self.last_error = f"{name}: {exc}"
        if name not in self._error_types:  # full traceback once per exception type, then a count
            self._error_types.add(name)
            log.error("monitor worker: a batch of %d items failed (%s); the worker keeps running",
                      len(items), self.last_error, exc_info=exc)
        else:
            log.debug("monitor worker: batch failed again (%s), %d failures so far", self.last_error,
                      self.worker_errors)

    def _process(self, items: list) -> None:
        run: list = []
        for it in items:
            if it[0] == "map":
                self._flush_run(run)
                run = []
                _, cmap, blob = it
                if self.recorder is not None and blob is not None:
                    last = self.aggregator.last_receive_s
                    self.recorder.write_map(last if math.isfinite(last) else time.time(), blob)
                with self.lock:
                    self.aggregator.set_map(cmap)
            else:
                run.append(it)
        self._flush_run(run)

    def _flush_run(self, run: list) -> None:
        if not run:
            return
        recv = np.fromiter((r[0] for r in run), dtype=float, count=len(run))
        ids = np.fromiter((_key_id(self.keys, r[1]) for r in run), dtype=np.int64, count=len(run))
        payloads = [r[2] for r in run]
        if self.recorder is not None:
            self.recorder.write_telemetry(recv, ids, payloads)
        with self.lock:
            self.aggregator.ingest(recv, ids, payloads)

    def drain(self, timeout_s: float = 10.0) -> bool:
        """Wait until everything queued so far is processed."""
        end = time.monotonic() + timeout_s
        while self._q.unfinished_tasks and time.monotonic() < end:
            time.sleep(0.01)
        return not self._q.unfinished_tasks

    def view(self) -> FleetView:
        with self.lock:
            return self.aggregator.view(time.time())

    def close(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None
        self._stop.set()
        self._thread.join(timeout=10.0)


def _key_id(keys: Keys, key: str) -> int:
    """Agent id from a telemetry key; ``NO_AGENT`` unless it is a u32 below ``NO_AGENT``
    (``.../agents/99999999999999999999/telemetry`` names no agent)."""
    aid = keys.agent_of(key)
    return aid if aid is not None and 0 <= aid < NO_AGENT else NO_AGENT


# --------------------------------------------------------------------------------------------
# Rendering (rich)

_PALETTE = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], dtype=float)


def _colour(v: float) -> str:
    x = min(max(v, 0.0), 1.0) * (len(_PALETTE) - 1)
    i = min(int(x), len(_PALETTE) - 2)
    r, g, b = _PALETTE[i] + (x - i) * (_PALETTE[i + 1] - _PALETTE[i])
    return f"on rgb({int(r)},{int(g)},{int(b)})"


def heatmap_text(cmap: CommandMap, values: np.ndarray, max_cols: int = 60) -> Any:
    """A rich Text heat map of per-CV values on the XZ plane (layers nearest y = 0, z up)."""
    from rich.text import Text

    from fisc_ground.plots import xz_slice

    _, _, grid = xz_slice(np.asarray(cmap["cv_center_m"]), np.asarray(values, dtype=float), cmap.cell_size_m)
    step = max(1, -(-grid.shape[1] // max_cols))
    if step > 1:
        cols = -(-grid.shape[1] // step)
        pad = np.full((grid.shape[0], cols * step - grid.shape[1]), np.nan)
        grid = np.nanmean(np.concatenate([grid, pad], axis=1).reshape(grid.shape[0], cols, step), axis=2)
    finite = grid[np.isfinite(grid)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    text = Text()
    for row in grid[::-1]:
        for v in row:
            text.append("  ", style=_colour((v - lo) / (hi - lo) if hi > lo else 0.5) if np.isfinite(v) else "")
        text.append("\n")
    text.append(f"min {lo:.3g}  max {hi:.3g}" if finite.size else "no samples yet")
    return text


def render(view: FleetView, fields: SwarmFields | None, cmap: CommandMap | None, dropped: int, title: str,
           worker_errors: int = 0, last_error: str = "") -> Any:
    """The dashboard as one rich renderable."""
    from rich.console import Group
    from rich.panel import Panel
    from rich.table import Table

    table = Table(title="agents by state", expand=False)
    table.add_column("state")
    table.add_column("agents", justify="right")
    for state, n in sorted(view.by_state.items()):
        table.add_row(state, str(n))
    table.add_row("stale", str(len(view.stale)), style="red" if view.stale else "")
    info = Table.grid(padding=(0, 2))
    info.add_row("agents heard", str(view.n_agents))
    info.add_row("map", f"{cmap.sha256[:12]} v{cmap.map_version} ({cmap.n_cv} CVs)" if cmap else "none yet")
    info.add_row("map versions flown", ", ".join(f"v{k}: {v}" for k, v in sorted(view.map_versions.items())) or "-")
    info.add_row("messages", f"{view.messages}  (bad {view.bad_messages}, dropped {dropped}, "
                             f"off roster {view.off_roster}, over agent cap {view.over_cap})")
    if worker_errors:
        info.add_row("worker errors", f"{worker_errors} batches failed; last: {last_error}", style="bold red")
    info.add_row("field samples", str(view.time_samples))
    parts: list[Any] = [Panel(info, title=title), table]
    alarms = "\n".join(view.alarms) if view.alarms else "none"
    parts.append(Panel(alarms, title="alarms", style="bold red" if view.alarms else "green"))
    if cmap is not None and fields is not None and view.time_samples:
        parts.append(Panel(heatmap_text(cmap, np.where(fields.samples > 0, fields.rho_s_kg_m3, np.nan)),
                           title="swarm density rho_s [kg/m^3], XZ plane"))
        parts.append(Panel(heatmap_text(cmap, np.where(fields.samples > 0, fields.p_dispersion_pa, np.nan)),
                           title="swarm pressure [Pa], XZ plane"))
    return Group(*parts)


# --------------------------------------------------------------------------------------------
# Map discovery for the monitor

def verify_monitor_map(blob: bytes | bytearray, trusted_keys: list[bytes] | None, allow_unsigned: bool,
                       claimed_version: int | None = None, source: str = "<zenoh>") -> CommandMap:
    """The monitor's rule for a map: with trusted keys, signed by one of them; without, any valid
    signature; an unsigned map only with ``allow_unsigned`` (``MapError`` names the refusal)."""
    from fisc_agent.mapfile import MapError, MapErrorKind
    from fisc_agent.zenoh_maps import verify_map_bytes

    if trusted_keys:
        return verify_map_bytes(blob, trusted_keys, allow_unsigned=False, claimed_version=claimed_version,
                                source=source)
    cmap = verify_map_bytes(blob, None, allow_unsigned=True, claimed_version=claimed_version, source=source)
    if not cmap.signed and not allow_unsigned:
        raise MapError(MapErrorKind.SIGNATURE, "the map is unsigned (refused; --allow-unsigned accepts it in a lab)",
                       source=source)
    return cmap


def fetch_map(session: Any, keys: Keys, trusted_keys: list[bytes] | None, timeout_s: float = 5.0,
              allow_unsigned: bool = False) -> tuple[CommandMap, bytes] | None:
    """Query the swarm's current map, verified by ``verify_monitor_map``."""
    import zenoh

    from fisc_agent.mapfile import MapError
    from fisc_agent.map_chunks import MapAssembler

    asm = MapAssembler()
    for reply in session.get(keys.map, consolidation=zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE),
                             timeout=timeout_s):
        if reply.ok is None:
            continue
        try:
            head, blob = asm.feed(reply.ok.payload.to_bytes())
        except MapError as exc:
            log.warning("map chunk refused: %s", exc)
            continue
        if blob is not None:
            cmap = verify_monitor_map(blob, trusted_keys, allow_unsigned, claimed_version=head.map_version,
                                      source=keys.map)
            return cmap, bytes(blob)
    return None


class MapFollower:
    """Keeps the monitor on the swarm's current map: on an announcement of a newer map, fetch
    and verify it, then switch the pipe to it (in stream order, so replays switch there too)."""

    def __init__(self, session: Any, keys: Keys, pipe: TelemetryPipe, trusted_keys: list[bytes] | None,
                 current_version: int = 0, allow_unsigned: bool = False) -> None:
        self.session, self.keys, self.pipe, self.trusted = session, keys, pipe, trusted_keys
        self.allow_unsigned = bool(allow_unsigned)
        self.version = int(current_version)
        self.refused: set[int] = set()
        """map_versions announced, fetched and refused (not fetched again)."""
        self._busy = threading.Lock()
        self._sub = session.declare_subscriber(keys.map, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        from fisc_agent.mapfile import MapError
        from fisc_agent.map_chunks import KIND_ANNOUNCE, parse_chunk

        try:
            head, _ = parse_chunk(sample.payload.to_bytes()[:96])
        except MapError:
            return
        if head.kind == KIND_ANNOUNCE and head.map_version > self.version and head.map_version not in self.refused \
                and self._busy.acquire(blocking=False):
            threading.Thread(target=self._fetch, args=(head.map_version,), daemon=True, name="fisc-monitor-map").start()

    def _fetch(self, announced_version: int = 0) -> None:
        from fisc_agent.mapfile import MapError

        try:
            got = fetch_map(self.session, self.keys, self.trusted, allow_unsigned=self.allow_unsigned)
            if got is not None and got[0].map_version > self.version:
                self.version = got[0].map_version
                self.pipe.set_map(*got)
                log.info("monitor switched to map %s (map_version %d)", got[0].sha256[:12], self.version)
        except MapError as exc:
            self.refused.add(announced_version)
            log.warning("newer map announced but refused: %s", exc)
        finally:
            self._busy.release()

    def close(self) -> None:
        self._sub.undeclare()


def run_monitor(args: Any) -> int:
    """``fisc-ground monitor --swarm NAME [--map MAP] [--record FILE] [--duration S]``."""
    from rich.console import Console
    from rich.live import Live

    from fisc_agent.mapfile import MAGIC, MAX_MAP_FILE_BYTES, MapError, MapFileError, read_public_key
    from fisc_agent.safe_files import read_regular_file
    from fisc_ground.recording import Recorder
    from fisc_ground.zenoh_config import open_ground_session, silence_hint, zenoh_neighbours

    keys = Keys(args.prefix, args.swarm)
    trusted = [read_public_key(p) for p in (args.trusted_key or [])]
    roster = args.roster if args.roster is None or isinstance(args.roster, AgentRoster) else AgentRoster.parse(args.roster)
    if args.map:  # read before opening the session: a bad file fails fast
        map_file_blob = read_regular_file(args.map, what="FISC map", max_bytes=MAX_MAP_FILE_BYTES, magic=MAGIC,
                                          error=MapFileError)
        map_file = verify_monitor_map(map_file_blob, trusted, args.allow_unsigned, source=str(args.map))
    console = Console(stderr=False)
    session = open_ground_session(args.zenoh_config)
    recorder = None
    try:
        cmap, blob = None, None
        if args.map:
            cmap, blob = map_file, map_file_blob
        else:
            try:
                got = fetch_map(session, keys, trusted, timeout_s=args.map_timeout, allow_unsigned=args.allow_unsigned)
                if got is None:
                    log.warning("no map on %s yet: showing fleet state only", keys.map)
            except MapError as exc:  # e.g. a map signed by a stranger: the fleet is what to watch now
                log.error("the swarm's map was refused (%s): showing fleet state only", exc)
                got = None
            if got is not None:
                cmap, blob = got
        agg = TelemetryAggregator(None, sample_period_s=args.sample_period, stale_after_s=args.stale_after,
                                  roster=roster, max_agents=args.max_agents)
        if args.record:
            recorder = Recorder(args.record, {"swarm": args.swarm, "prefix": args.prefix,
                                              "sample_period_s": args.sample_period,
                                              "stale_after_s": args.stale_after,
                                              "roster": roster.spec() if roster else None,
                                              "max_agents": args.max_agents})
        pipe = TelemetryPipe(keys, agg, recorder)
        if cmap is not None:
            pipe.set_map(cmap, blob)
        pipe.attach(session)
        follower = None if args.map else MapFollower(session, keys, pipe, trusted,
                                                     cmap.map_version if cmap is not None else 0,
                                                     allow_unsigned=args.allow_unsigned)
        end = time.monotonic() + args.duration if args.duration else math.inf
        started, hinted = time.monotonic(), False
        title = f"FISC swarm {args.swarm}" + (f"  recording {args.record}" if args.record else "")
        try:
            with Live(console=console, refresh_per_second=4, screen=False) as live:
                while time.monotonic() < end:
                    with pipe.lock:
                        view = agg.view(time.time())
                        fields = agg.fields()
                        shown_map = agg.cmap
                    live.update(render(view, fields, shown_map, pipe.dropped, title, pipe.worker_errors,
                                       pipe.last_error))
                    hint = None if hinted or view.n_agents else silence_hint(
                        0, time.monotonic() - started, keys, args.zenoh_config, zenoh_neighbours(session))
                    if hint:  # once: why nobody is heard and what to start
                        log.warning("%s", hint)
                        hinted = True
                    time.sleep(0.5)
        except KeyboardInterrupt:
            pass
        if follower is not None:
            follower.close()
        pipe.close()
        console.print(f"{pipe.received} messages received, {pipe.dropped} dropped"
                      + (f", {pipe.worker_errors} worker errors ({pipe.lost_to_errors} messages lost; "
                         f"last: {pipe.last_error})" if pipe.worker_errors else "")
                      + (f", recorded to {args.record}" if args.record else ""))
    finally:
        if recorder is not None:
            recorder.close()
        session.close()
    return 0
