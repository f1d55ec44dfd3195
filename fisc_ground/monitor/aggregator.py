"""The monitor's aggregator: telemetry messages in, fleet state and per-CV swarm fields out (pure).

``TelemetryAggregator`` is deterministic in the message sequence: fed the same
``(receive time, key agent id, payload)`` stream in any batching, it produces the same fields.
That is what makes ``fisc-ground replay`` of a recording equal to the live estimate.  The fleet
is sampled every ``sample_period_s`` of receive time: at each sample, every agent heard within
``stale_after_s`` contributes its newest position (CV via ``CommandField.cv_of``) and velocity
to a ``FieldAccumulator`` (the paper's quartet, time-averaged; the dispersion pressure uses
the CV target command ``S v_target`` as reference, as ``fisc-sim run`` does).

No threads, no I/O, no clock: arrays in, arrays out (``fisc_ground.monitor.run`` adds the Zenoh
subscriber and the threads, ``fisc_ground.monitor.view`` the terminal dashboard).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fisc_agent.zenoh import telemetry_codec as tc
from fisc_agent.map.lookup import CommandField
from fisc_agent.map.codec import CommandMap
from fisc_agent.map.separation import DEFAULT_D_MIN_M, map_separation
from fisc_ground.monitor.alarms import LOW_BATTERY_PCT, fleet_alarms, id_list as _id_list, separation_alarm
from fisc_ground.fields.field_run import FieldRun, FieldSource
from fisc_ground.fields.intervals import HonestStatistics, honest_statistics, stats_inputs
from fisc_ground.fields.separation_stats import ApproachTracker
from fisc_ground.fields.swarm_fields import FieldAccumulator, SwarmFields, cv_moments
from fisc_ground.fields.time_blocks import DEFAULT_BLOCK_S, BlockAccumulator

FLYING_STATES = frozenset({"TAKEOFF", "JOIN", "FLOW", "RETURN", "EXIT"})
NO_AGENT = 0xFFFFFFFF
"""Key agent id of a message whose key names no valid agent (telemetry ids are u32)."""
DEFAULT_MAX_AGENTS = 10_000
"""Agent ids the monitor tracks at most; messages from further new ids are counted, not shown."""
STATS_EVERY_SAMPLES = 20
"""The view's bootstrap intervals are recomputed after this many new fleet samples (a bootstrap costs
~0.1 s; the samples, not a clock, decide, so a replay shows what the live view showed)."""
STATS_REPLICATES = 100
"""Bootstrap replicates of the live view (the reports use ``bootstrap.DEFAULT_REPLICATES``)."""
TARGET_WIDTH = 0.1
"""Interval width the view's time-to-width estimate aims at."""


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
    """Human-readable alarms (every agent / some agents stale, low battery, unhealthy, hands-off,
    refused commands, outside the tunnel, failsafes, refused maps, foreign maps, spoofing)."""
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
    by_authority: dict[str, int] | None = None
    """Live agents per authority (``telemetry_codec.AUTHORITIES``; ``unknown`` from version-1 agents)."""
    closest_m: float | None = None
    """Distance of the closest two live agents now [m] (None: fewer than two with a position)."""
    closest_ids: tuple[int, int] | None = None
    """Their ids."""
    d_min_m: float = DEFAULT_D_MIN_M
    """The spacing the separation alarm holds them to (the map's d_min) [m]."""
    approach: dict | None = None
    """Closest approach and near-misses over the fleet samples so far (``ClosestApproach.as_dict``)."""
    statistics: tuple[str, ...] = ()
    """How far the figures can be trusted: lines like ``profile density r 0.62 [0.41, 0.78]; interval < 0.1
    wide in ~4 min at the current rate`` (empty until there are two time blocks)."""


SAMPLE_PERIOD_S = 0.2
"""Default fleet sampling period [s]: the agents' telemetry period (``fisc-agent --telemetry-rate`` 5 Hz).  A
longer one drops positions: at 0.5 s a vehicle crossing a 0.5 m slice of the throat in 0.3 s was sampled
once or not at all, and eight stock PX4 looping 300 s scored profile density r 0.81 / 0.87 where the same
recordings give 0.87 / 0.94 at 0.2 s (and the same at 0.1 s; 2026-12-07)."""


class TelemetryAggregator:
    """Newest telemetry per agent plus time-averaged swarm fields over the map's CVs."""

    def __init__(self, cmap: CommandMap | None = None, sample_period_s: float = SAMPLE_PERIOD_S,
                 stale_after_s: float = 3.0, roster: AgentRoster | None = None, max_agents: int = DEFAULT_MAX_AGENTS,
                 low_battery_pct: float = LOW_BATTERY_PCT) -> None:
        if not sample_period_s > 0 or not stale_after_s > 0:
            raise ValueError("sample_period_s and stale_after_s must be > 0")
        if int(max_agents) < 1:
            raise ValueError(f"max_agents must be >= 1, got {max_agents}")
        self.sample_period_s = float(sample_period_s)
        self.stale_after_s = float(stale_after_s)
        self.low_battery_pct = float(low_battery_pct)
        """Battery level below which ``low battery`` is raised [%]."""
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
        self.blocks: BlockAccumulator | None = None
        self.d_min_m = DEFAULT_D_MIN_M
        """The spacing of the separation alarm and the near-misses (the map's d_min) [m]."""
        self.approach = ApproachTracker(self.d_min_m)
        """Closest approach and near-misses of the live agents at every fleet sample."""
        self._stats: tuple[int, int, HonestStatistics] | None = None
        if cmap is not None:
            self.set_map(cmap)

    # -- map -----------------------------------------------------------------------------------
    def set_map(self, cmap: CommandMap) -> None:
        """Use this map's CVs (restarts the field average)."""
        self.cmap = cmap
        self.field = CommandField.from_map(cmap)
        self.acc = FieldAccumulator(cmap.n_cv, cmap.cell_size_m ** 3)
        self.blocks = BlockAccumulator(cmap.n_cv, DEFAULT_BLOCK_S)
        self._stats = None
        d_min = map_separation(cmap.body).d_min_m
        if d_min != self.d_min_m:
            self.d_min_m, self.approach = d_min, ApproachTracker(d_min)
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
            self.next_sample_s = self._grid_after(float(recv_s[0]))
        i = 0
        while i < n:
            j = i + int(np.searchsorted(tmax[i:], self.next_sample_s, side="left"))
            self._update(records[i:j][ok[i:j]], recv_s[i:j][ok[i:j]])
            if j < n:
                self._sample(self.next_sample_s)
                self.next_sample_s = self._grid_after(float(tmax[j]))
            i = j

    def _grid_after(self, t: float) -> float:
        """The first sample time k * sample_period_s strictly after ``t``.  (``floor(t / p) + 1``
        alone is not enough in floating point: t = 4.3, p = 0.1 gives 43 * 0.1 == 4.3, and ingest
        would sample the same instant forever.)"""
        k = math.floor(t / self.sample_period_s) + 1
        while k * self.sample_period_s <= t:
            k += 1
        return k * self.sample_period_s

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
        live = self._live(t)
        rec = self.latest[: len(self.slots)][live]
        pos = rec["position_m"].astype(float)
        self.approach.add(t, rec["agent_id"].astype(np.int64), pos)
        if self.acc is None:
            return
        vel = rec["velocity_m_s"].astype(float)
        good = np.isfinite(pos).all(axis=1) & np.isfinite(vel).all(axis=1)
        cv = self.field.cv_of(pos[good]) if good.any() else np.zeros(0, dtype=np.int64)
        mom = cv_moments(cv, vel[good], self._mass_kg, self.acc.n_cv, self._target_cmd)
        self.acc.add_moments(mom)
        self.blocks.add_moments(t, mom)

    # -- results -------------------------------------------------------------------------------
    @property
    def last_receive_s(self) -> float:
        """Newest receive time ingested (-inf before any message)."""
        return self._tmax

    def fields(self) -> SwarmFields | None:
        """Time-averaged swarm fields so far (None without a map)."""
        return None if self.acc is None else self.acc.result()

    def field_run(self, min_samples: int, with_statistics: bool = False) -> FieldRun:
        """The estimate so far as a ``FieldRun`` (source: replay of telemetry; needs a map); with its
        bootstrap intervals, axial profile and samples per CV when ``with_statistics``."""
        if self.cmap is None:
            raise ValueError("the aggregator has no map yet: no swarm fields to report")
        return FieldRun(source=FieldSource.REPLAY, cmap=self.cmap, fields=self.acc.result(), scale=self.cmap.scale,
                        min_samples=int(min_samples), scenario="telemetry", mode="replay",
                        statistics=self.statistics(min_samples) if with_statistics else None)

    def statistics(self, min_samples: int, n_boot: int | None = None) -> HonestStatistics | None:
        """Bootstrap intervals, axial profile and samples per CV of the fields so far (None without a map)."""
        if self.blocks is None:
            return None
        kw = {} if n_boot is None else {"n_boot": int(n_boot)}
        return honest_statistics(self.blocks.sums(), stats_inputs(self.cmap, min_samples),
                                 self.blocks.last_t_s - self.blocks.first_t_s + self.sample_period_s, **kw)

    def _view_statistics(self, min_samples: int) -> tuple[str, ...]:
        """The view's statistics lines, recomputed every ``STATS_EVERY_SAMPLES`` fleet samples."""
        if self.blocks is None or self.blocks.n_blocks < 2:
            return ()
        n = self.acc.n_time_samples
        if self._stats is None or self._stats[1] != min_samples or n >= self._stats[0] + STATS_EVERY_SAMPLES:
            self._stats = (n, min_samples, self.statistics(min_samples, STATS_REPLICATES))
        st = self._stats[2]
        s = st.samples
        return (st.progress_line("profile_pearson_density", TARGET_WIDTH),
                st.progress_line("profile_pearson_pressure", TARGET_WIDTH),
                f"samples per CV: min {s['min']}, median {s['median']:.0f}, max {s['max']}; "
                f"{100 * s['fraction_below_min_samples']:.0f} % of CVs below {s['min_samples']}")

    def agents(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(agent ids, newest records, receive times) of every agent heard."""
        n = len(self.slots)
        ids = np.fromiter(self.slots.keys(), dtype=np.int64, count=n)
        return ids, self.latest[:n].copy(), self.seen_s[:n].copy()

    def view(self, now_s: float | None = None, min_samples: int = 10) -> FleetView:
        """Fleet state for display; ``now_s`` defaults to the newest receive time; ``min_samples``: the
        CVs and slices the statistics lines compare."""
        now = self._tmax if now_s is None else float(now_s)
        ids, rec, seen = self.agents()
        live = seen > now - self.stale_after_s
        states = np.array(tc.state_names(rec["state"]), dtype=object)
        by_state: dict[str, int] = {}
        for s in states[live]:
            by_state[s] = by_state.get(s, 0) + 1
        by_authority: dict[str, int] = {}
        for code in rec["authority"][live].tolist():
            name = tc.AUTHORITIES[code] if code < len(tc.AUTHORITIES) else "unknown"
            by_authority[name] = by_authority.get(name, 0) + 1
        versions: dict[int, int] = {}
        for v in rec["map_version"][live].tolist():
            versions[int(v)] = versions.get(int(v), 0) + 1
        alarms = fleet_alarms(ids, rec, live, self.stale_after_s, self.low_battery_pct)
        pair, sep_line = separation_alarm(ids[live], rec["position_m"][live].astype(float), self.d_min_m)
        if sep_line is not None:
            alarms.append(sep_line)
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
                         off_roster=self.off_roster, over_cap=self.over_cap, by_authority=by_authority,
                         closest_m=pair.distance_m if pair.id_a >= 0 else None,
                         closest_ids=(pair.id_a, pair.id_b) if pair.id_a >= 0 else None, d_min_m=self.d_min_m,
                         approach=self.approach.result().as_dict(), statistics=self._view_statistics(min_samples))
