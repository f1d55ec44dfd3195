"""Flight-log recordings (MCAP, ``fisc_ground.monitor.flight_log``) read back, and ``fisc-ground replay``.

A recording is any MCAP written by a ``FlightLog``: ``fisc-ground monitor --record FILE``,
``fisc-sim run --mcap FILE`` or ``fisc-sim emulate --mcap FILE``.  Replay reads its raw channels
(``/fisc/settings``, ``/fisc/map``, ``/fisc/telemetry``) in the order they were logged and feeds
them through a fresh ``TelemetryAggregator`` with the recorded settings: the result equals the
live estimate, because the aggregator is deterministic in the message sequence.  A file cut short
by a crash (no MCAP summary) is read up to its last complete chunk (``Recording.truncated``).

``replay`` turns a recording into the outputs of ``fisc-sim run``: fields.csv (same columns),
metrics.json (``FieldRun.metrics``) and the figures.
"""

from __future__ import annotations

import base64
import json
import logging
from dataclasses import dataclass, field, fields as dc_fields
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from fisc_agent.map.codec import CommandMap, decode_map
from fisc_ground.monitor import foxglove_scene as fs
from fisc_ground.monitor.flight_log import LogSettings
from fisc_ground.monitor.aggregator import TelemetryAggregator

log = logging.getLogger(__name__)

MCAP_MAGIC = b"\x89MCAP0\r\n"
#: Largest recording ``read_recording`` reads (about 2 h of 1000 agents at 10 Hz).
MAX_RECORDING_BYTES = 8 << 30


class RecordingError(ValueError):
    """A recording cannot be read (message names the file and the problem)."""


@dataclass
class Recording:
    """A flight log read back."""

    settings: LogSettings
    """The aggregator settings recorded (``/fisc/settings``)."""
    events: list = field(default_factory=list)
    """In log order: ("telemetry", recv_s (n,), agent_ids (n,), payloads) and ("map", recv_s, blob)."""
    truncated: bool = False
    """True when the file ended early (a crash): what precedes the break is used."""

    @property
    def n_messages(self) -> int:
        """Telemetry messages in the recording."""
        return sum(len(e[3]) for e in self.events if e[0] == "telemetry")

    def maps(self) -> list[bytes]:
        """The ``.fiscmap`` blobs recorded, in order."""
        return [e[2] for e in self.events if e[0] == "map"]


def _settings(path: Path, raw: dict) -> LogSettings:
    known = {f.name for f in dc_fields(LogSettings)}
    try:
        return LogSettings(**{k: v for k, v in raw.items() if k in known})
    except TypeError as exc:
        raise RecordingError(f"{path}: {fs.TOPIC_SETTINGS}: {exc}") from exc


def read_recording(path: str | Path) -> Recording:
    """Read the raw channels of an MCAP flight log (tolerates a truncated tail)."""
    from mcap.exceptions import McapError
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    from fisc_agent.common.safe_files import check_regular_file

    path = Path(path)
    check_regular_file(path, what="FISC flight log (MCAP)", max_bytes=MAX_RECORDING_BYTES, magic=MCAP_MAGIC,
                       error=RecordingError)
    topics: dict[int, str] = {}
    raw: list[tuple[int, str, dict]] = []
    settings_raw: dict | None = None
    truncated = False
    with open(path, "rb") as fh:
        try:
            for rec in StreamReader(fh, skip_magic=False).records:
                if isinstance(rec, Channel):
                    topics[rec.id] = rec.topic
                elif isinstance(rec, Message):
                    topic = topics.get(rec.channel_id)
                    if topic not in (fs.TOPIC_SETTINGS, fs.TOPIC_MAP, fs.TOPIC_TELEMETRY):
                        continue
                    try:
                        msg = json.loads(rec.data)
                    except ValueError as exc:
                        raise RecordingError(f"{path}: {topic}: message is not JSON ({exc})") from exc
                    if topic == fs.TOPIC_SETTINGS:
                        settings_raw = msg
                    else:
                        raw.append((int(msg["seq"]), topic, msg))
        except (McapError, EOFError, ValueError) as exc:
            if isinstance(exc, RecordingError):
                raise
            truncated = True
            log.warning("%s: the MCAP file ends early (%s: %s; recording cut short?): using what precedes it",
                        path, type(exc).__name__, exc)
    if settings_raw is None:
        raise RecordingError(f"{path}: no {fs.TOPIC_SETTINGS} message: not a FISC flight log")
    rec = Recording(settings=_settings(path, settings_raw), truncated=truncated)
    for _, topic, msg in sorted(raw, key=lambda r: r[0]):
        try:
            if topic == fs.TOPIC_MAP:
                rec.events.append(("map", float(msg["recv_s"]), base64.b64decode(msg["map_b64"])))
            else:
                rec.events.append(("telemetry", np.asarray(msg["recv_s"], dtype=float),
                                   np.asarray(msg["key_agent_id"], dtype=np.int64),
                                   [base64.b64decode(p) for p in msg["payload_b64"]]))
        except (KeyError, TypeError, ValueError) as exc:
            raise RecordingError(f"{path}: {topic} record {msg.get('seq')}: {type(exc).__name__}: {exc}") from exc
    return rec


def aggregate(recording: Recording, cmap: CommandMap | None = None) -> TelemetryAggregator:
    """Feed a recording through a fresh aggregator with the recorded settings.

    ``cmap``: use this map for the whole recording instead of the map records in it."""
    agg = recording.settings.aggregator(cmap)
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
    from fisc_ground.fields.field_report import write_fields_csv, write_json

    rec = read_recording(path)
    agg = aggregate(rec, cmap)
    if agg.cmap is None:
        raise RecordingError(f"{path}: the recording holds no map; pass --map MAP")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    run = agg.field_run(min_samples, with_statistics=True)
    paths = {"fields.csv": write_fields_csv(run, out / "fields.csv")}
    metrics = run.metrics()
    metrics.update(agg.approach.result().as_dict())  # closest approach of the live agents at every fleet sample
    view = agg.view()
    metrics.update(recording=str(path), recorded_by=rec.settings.source, truncated=rec.truncated,
                   messages=view.messages, bad_messages=view.bad_messages, spoofed=view.spoofed,
                   agents=view.n_agents, sample_period_s=agg.sample_period_s, stale_after_s=agg.stale_after_s)
    paths["metrics.json"] = write_json(out / "metrics.json", metrics)
    if figures:
        from fisc_ground.figures.field_figures import write_run_figures

        paths.update(write_run_figures(run, out))
    return paths


def iter_messages(recording: Recording) -> Iterator[tuple[float, int, bytes]]:
    """Every telemetry message as (receive time, key agent id, payload)."""
    for ev in recording.events:
        if ev[0] == "telemetry":
            yield from zip(ev[1].tolist(), ev[2].tolist(), ev[3])


def run_replay(args: Any) -> int:
    """``fisc-ground replay FILE -o DIR [--map MAP]``."""
    from fisc_agent.map.codec import load_map

    cmap = load_map(args.map) if args.map else None
    paths = replay(args.file, args.output, cmap, min_samples=args.min_samples, figures=not args.no_figures)
    for name, p in paths.items():
        print(f"{name}: {p}")
    return 0
