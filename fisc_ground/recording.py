"""Telemetry recordings (``fisc-ground monitor --record FILE``) and their replay.

File format (little-endian), version 1::

    b"FISCREC\\0"             magic
    u32  format version (1)
    u64  header length, header JSON {swarm, prefix, created_utc, telemetry_version,
                                     sample_period_s, stale_after_s}
    records, each:  u8 kind, f64 receive time [UNIX s], u32 agent id from the key
                    (0xFFFFFFFF: none), u32 length, payload
        kind 1: one telemetry message (``fisc_agent.telemetry_codec``), as received
        kind 2: the map the monitor switched to at that point (``.fiscmap`` bytes)

Records are appended in the order the monitor processed them, so a replay feeds the
aggregator exactly what the live monitor saw.  A file cut short by a crash is read up to its
last complete record (``Recording.truncated`` tells).

``replay`` turns a recording into the outputs of ``fisc-sim run``: fields.csv (same columns),
metrics.json (DESIGN.md section 4 fidelity metrics) and the figures.
"""

from __future__ import annotations

import json
import logging
import struct
import threading
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from fisc_agent import telemetry_codec as tc
from fisc_agent.mapfile import CommandMap, decode_map
from fisc_ground.field_run import FieldRun, FieldSource
from fisc_ground.monitor_aggregator import DEFAULT_MAX_AGENTS, AgentRoster, TelemetryAggregator

log = logging.getLogger(__name__)

MAGIC = b"FISCREC\x00"
VERSION = 1
KIND_TELEMETRY = 1
KIND_MAP = 2
_HEAD = struct.Struct("<8sIQ")
_REC = struct.Struct("<BdII")
#: Largest recording ``read_recording`` reads (it holds the file in memory; about 2 h of 1000
#: agents at 10 Hz).
MAX_RECORDING_BYTES = 8 << 30
_REC_DTYPE = np.dtype([("kind", "u1"), ("recv_s", "<f8"), ("agent_id", "<u4"), ("length", "<u4")])


class RecordingError(ValueError):
    """A recording cannot be read (message names the file and the problem)."""


class Recorder:
    """Append-only recording writer (thread-safe)."""

    def __init__(self, path: str | Path, meta: dict[str, Any], flush_every: int = 4096) -> None:
        self.path = Path(path)
        meta = dict(meta, created_utc=datetime.now(timezone.utc).isoformat(), telemetry_version=tc.VERSION)
        raw = json.dumps(meta, sort_keys=True).encode()
        self._fh = open(self.path, "wb")
        self._fh.write(_HEAD.pack(MAGIC, VERSION, len(raw)) + raw)
        self._lock = threading.Lock()
        self._since_flush = 0
        self._flush_every = int(flush_every)
        self.records = 0

    def write_telemetry(self, recv_s: np.ndarray, agent_ids: np.ndarray, payloads: list[bytes]) -> None:
        parts = []
        for t, aid, p in zip(np.asarray(recv_s, dtype=float).tolist(), np.asarray(agent_ids).tolist(), payloads):
            parts.append(_REC.pack(KIND_TELEMETRY, t, int(aid) & 0xFFFFFFFF, len(p)))
            parts.append(p)
        self._write(b"".join(parts), len(payloads))

    def write_map(self, recv_s: float, blob: bytes) -> None:
        self._write(_REC.pack(KIND_MAP, float(recv_s), 0xFFFFFFFF, len(blob)) + bytes(blob), 1)

    def _write(self, data: bytes, n: int) -> None:
        with self._lock:
            self._fh.write(data)
            self.records += n
            self._since_flush += n
            if self._since_flush >= self._flush_every:
                self._fh.flush()
                self._since_flush = 0

    def close(self) -> None:
        with self._lock:
            if not self._fh.closed:
                self._fh.flush()
                self._fh.close()


@dataclass
class Recording:
    """A recording read back."""

    meta: dict
    """The header JSON."""
    events: list = field(default_factory=list)
    """In order: ("telemetry", recv_s (n,), agent_ids (n,), payloads) runs and ("map", recv_s, blob)."""
    truncated: bool = False
    """True when the file ended inside a record (the partial record is ignored)."""

    @property
    def n_messages(self) -> int:
        return sum(len(e[3]) for e in self.events if e[0] == "telemetry")

    def maps(self) -> list[bytes]:
        return [e[2] for e in self.events if e[0] == "map"]


def read_recording(path: str | Path) -> Recording:
    """Read a recording (tolerates a truncated tail)."""
    from fisc_agent.safe_files import read_regular_file

    path = Path(path)
    data = read_regular_file(path, what="FISC telemetry recording", max_bytes=MAX_RECORDING_BYTES, magic=MAGIC,
                             error=RecordingError)
    if len(data) < _HEAD.size or data[:8] != MAGIC:
        raise RecordingError(f"{path}: not a FISC telemetry recording (bad magic)")
    _, version, n = _HEAD.unpack_from(data)
    if version != VERSION:
        raise RecordingError(f"{path}: recording format {version} is not supported (expected {VERSION})")
    try:
        meta = json.loads(data[_HEAD.size:_HEAD.size + n])
    except ValueError as exc:
        raise RecordingError(f"{path}: header is not valid JSON ({exc})") from exc
    rec = Recording(meta=meta)
    pos = _HEAD.size + n
    run_t: list[float] = []
    run_id: list[int] = []
    run_p: list[bytes] = []

    def flush() -> None:
        if run_p:
            rec.events.append(("telemetry", np.array(run_t), np.array(run_id, dtype=np.int64), list(run_p)))
            run_t.clear(), run_id.clear(), run_p.clear()

    view = memoryview(data)
    while pos < len(data):
        if pos + _REC.size > len(data):
            rec.truncated = True
            break
        kind, t, aid, length = _REC.unpack_from(data, pos)
        end = pos + _REC.size + length
        if end > len(data):
            rec.truncated = True
            break
        payload = bytes(view[pos + _REC.size:end])
        if kind == KIND_TELEMETRY:
            run_t.append(t), run_id.append(aid), run_p.append(payload)
        elif kind == KIND_MAP:
            flush()
            rec.events.append(("map", t, payload))
        else:
            raise RecordingError(f"{path}: unknown record kind {kind} at byte {pos}")
        pos = end
    flush()
    if rec.truncated:
        log.warning("%s: file ends inside a record at byte %d (recording cut short); using what precedes it",
                    path, pos)
    return rec


def aggregate(recording: Recording, cmap: CommandMap | None = None) -> TelemetryAggregator:
    """Feed a recording through a fresh aggregator with the recorded settings.

    ``cmap``: use this map for the whole recording instead of the map records in it."""
    meta = recording.meta
    roster = meta.get("roster")
    agg = TelemetryAggregator(cmap, sample_period_s=float(meta.get("sample_period_s", 0.5)),
                              stale_after_s=float(meta.get("stale_after_s", 3.0)),
                              roster=AgentRoster.parse(roster) if roster else None,
                              max_agents=int(meta.get("max_agents", DEFAULT_MAX_AGENTS)))
    for ev in recording.events:
        if ev[0] == "map":
            if cmap is None:
                agg.set_map(decode_map(ev[2], source="recorded map"))
        else:
            agg.ingest(ev[1], ev[2], ev[3])
    return agg


def replay(path: str | Path, out_dir: str | Path, cmap: CommandMap | None = None, min_samples: int = 10,
           figures: bool = True) -> dict[str, Path]:
    """Recording -> fields.csv, metrics.json (and figures) in ``out_dir``; returns name -> path."""
    rec = read_recording(path)
    agg = aggregate(rec, cmap)
    if agg.cmap is None:
        raise RecordingError(f"{path}: the recording holds no map; pass --map MAP")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    run = field_run_of(agg, min_samples)
    from fisc_ground.field_report import write_fields_csv, write_json

    paths = {"fields.csv": write_fields_csv(run, out / "fields.csv")}
    metrics = run.metrics()
    view = agg.view()
    metrics.update(recording=str(path), truncated=rec.truncated,
                   messages=view.messages, bad_messages=view.bad_messages, spoofed=view.spoofed,
                   agents=view.n_agents, sample_period_s=agg.sample_period_s, stale_after_s=agg.stale_after_s)
    paths["metrics.json"] = write_json(out / "metrics.json", metrics)
    if figures:
        from fisc_ground.field_figures import write_run_figures

        paths.update(write_run_figures(run, out))
    return paths


def field_run_of(agg: TelemetryAggregator, min_samples: int) -> FieldRun:
    """The aggregator's estimate so far as a ``FieldRun`` (it needs a map)."""
    return FieldRun(source=FieldSource.REPLAY, cmap=agg.cmap, fields=agg.fields(), scale=agg.cmap.scale,
                    min_samples=int(min_samples), scenario="telemetry", mode="replay")


def iter_messages(recording: Recording) -> Iterator[tuple[float, int, bytes]]:
    """Every telemetry message as (receive time, key agent id, payload)."""
    for ev in recording.events:
        if ev[0] == "telemetry":
            yield from zip(ev[1].tolist(), ev[2].tolist(), ev[3])


def run_replay(args: Any) -> int:
    """``fisc-ground replay FILE -o DIR [--map MAP]``."""
    from fisc_agent.mapfile import load_map

    cmap = load_map(args.map) if args.map else None
    paths = replay(args.file, args.output, cmap, min_samples=args.min_samples, figures=not args.no_figures)
    for name, p in paths.items():
        print(f"{name}: {p}")
    return 0
