"""Flight logs: the FISC channels (``fisc_ground.monitor.foxglove_scene``) to an MCAP file and/or a live
Foxglove WebSocket server, through ``foxglove-sdk``.

One ``FlightLog`` serves ``fisc-ground monitor --record FILE --foxglove [PORT]`` (telemetry as
received, plus the live scene), ``fisc-sim run --mcap`` and ``fisc-sim emulate --mcap``
(``SimulatedTelemetry``: the simulated agents' states encoded as telemetry), so a simulated and
a flown run carry the same channels and open side by side in Foxglove.  The raw channels
(``/fisc/settings``, ``/fisc/map``, ``/fisc/telemetry``) are what ``fisc-ground replay`` reads
back (``fisc_ground.monitor.recording``); the scene and time-series channels are derived from a
``TelemetryAggregator`` every ``publish_period_s`` of receive time.
"""

from __future__ import annotations

import base64
import json
import threading
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from fisc_agent.zenoh import telemetry_codec as tc
from fisc_agent.map.codec import CommandMap
from fisc_ground.monitor import foxglove_scene as fs
from fisc_ground.fields.field_report import json_safe
from fisc_ground.monitor.aggregator import DEFAULT_MAX_AGENTS, SAMPLE_PERIOD_S, FleetView, TelemetryAggregator
from fisc_ground.monitor.alarms import LOW_BATTERY_PCT

#: Uncompressed size of an MCAP chunk [bytes]: a log cut short by a crash loses at most its last chunk.
CHUNK_BYTES = 256 * 1024


class FlightLogError(ValueError):
    """A flight-log sink cannot be opened (the message names the file or the port)."""


@dataclass(frozen=True)
class LogSettings:
    """Aggregator settings written at the start of a flight log (``/fisc/settings``); replay uses them."""

    sample_period_s: float = SAMPLE_PERIOD_S
    """Fleet sampling period of the field average [s of receive time]."""
    stale_after_s: float = 3.0
    """Agents not heard for this long leave the fleet sample [s]."""
    source: str = "fisc-ground monitor"
    """What wrote the log (``fisc-ground monitor``, ``fisc-sim run``, ``fisc-sim emulate``)."""
    swarm: str | None = None
    """Zenoh swarm name (monitor), None for simulations."""
    prefix: str = "fisc"
    """Zenoh key prefix (monitor)."""
    roster: str | None = None
    """Accepted agent ids (``AgentRoster.spec``), None: any."""
    max_agents: int = DEFAULT_MAX_AGENTS
    """Most agent ids tracked."""
    low_battery_pct: float = LOW_BATTERY_PCT
    """Battery level below which the ``low battery`` alarm is raised [%]."""

    def aggregator(self, cmap: CommandMap | None = None) -> TelemetryAggregator:
        """A fresh aggregator with these settings."""
        from fisc_ground.monitor.aggregator import AgentRoster

        return TelemetryAggregator(cmap, sample_period_s=self.sample_period_s, stale_after_s=self.stale_after_s,
                                   roster=AgentRoster.parse(self.roster) if self.roster else None,
                                   max_agents=self.max_agents, low_battery_pct=self.low_battery_pct)


def map_bytes(cmap: CommandMap) -> bytes:
    """The ``.fiscmap`` bytes of a decoded map (re-encoded unsigned: same content, same sha256)."""
    from fisc_ground.maps.write import encode_map

    return encode_map({k: v for k, v in cmap.body.items() if k != "arrays"}, dict(cmap.arrays))


def _ns(t_s: float) -> int:
    return max(0, int(round(float(t_s) * 1e9)))


class FlightLog:
    """The FISC channels on their own ``foxglove.Context``, logged to an MCAP file (``mcap_path``)
    and/or served on a Foxglove WebSocket (``ws_port``; 0 picks a free port, see ``port``).

    ``write_map``/``write_telemetry`` log the raw stream (thread-safe, in call order);
    ``publish(aggregator)`` logs the derived scene when ``publish_period_s`` of receive time has
    passed since the last one (call it after each ingest, holding the aggregator's lock).
    """

    def __init__(self, settings: LogSettings, mcap_path: str | Path | None = None, ws_port: int | None = None,
                 ws_host: str = "127.0.0.1", publish_period_s: float = 0.5, min_samples: int = 1) -> None:
        try:
            import foxglove
            from foxglove.channels import PointCloudChannel, SceneUpdateChannel
        except ImportError as exc:
            raise RuntimeError(f"flight logs (--record, --foxglove, --mcap) need the foxglove-sdk package: {exc}") from exc
        if mcap_path is None and ws_port is None:
            raise ValueError("a flight log needs an MCAP file or a WebSocket port")
        if not publish_period_s > 0:
            raise ValueError(f"publish_period_s must be > 0, got {publish_period_s!r}")
        self.settings = settings
        self.publish_period_s = float(publish_period_s)
        self.min_samples = int(min_samples)
        self._ctx = foxglove.Context()
        self._lock = threading.Lock()
        self._seq = 0
        self._next_publish_s: float | None = None
        self._wall: tuple[str, list] | None = None
        self.records = 0
        """Raw records (telemetry messages and maps) logged."""
        self.mcap_path = None if mcap_path is None else Path(mcap_path)
        self._mcap = None
        self._server = None
        if self.mcap_path is not None:
            from foxglove.mcap import MCAPWriteOptions

            try:
                self._mcap = foxglove.open_mcap(self.mcap_path, allow_overwrite=True, context=self._ctx,
                                                writer_options=MCAPWriteOptions(chunk_size=CHUNK_BYTES))
            except (OSError, RuntimeError) as exc:
                raise FlightLogError(f"{self.mcap_path}: cannot write the MCAP flight log: {exc}") from exc
        if ws_port is not None:
            try:
                self._server = foxglove.start_server(name=f"FISC {settings.swarm or settings.source}",
                                                     host=ws_host, port=int(ws_port), context=self._ctx)
            except (OSError, RuntimeError) as exc:
                self.close()
                raise FlightLogError(f"Foxglove WebSocket on {ws_host}:{ws_port}: {exc}") from exc
        def ch(topic: str, schema: dict) -> Any:  # a JSON channel named after its schema's title
            return foxglove.Channel(topic, schema=foxglove.Schema(name=schema["title"], encoding="jsonschema",
                                                                  data=json.dumps(schema).encode()),
                                    message_encoding="json", context=self._ctx)

        self._settings_ch = ch(fs.TOPIC_SETTINGS, fs.SETTINGS_SCHEMA)
        self._map_ch = ch(fs.TOPIC_MAP, fs.MAP_SCHEMA)
        self._telemetry_ch = ch(fs.TOPIC_TELEMETRY, fs.TELEMETRY_SCHEMA)
        self._fidelity_ch = ch(fs.TOPIC_FIDELITY, fs.FIDELITY_SCHEMA)
        self._states_ch = ch(fs.TOPIC_STATES, fs.STATES_SCHEMA)
        self._alarms_ch = ch(fs.TOPIC_ALARMS, fs.ALARMS_SCHEMA)
        self._alarms: tuple[str, ...] | None = None
        self._agents_ch = PointCloudChannel(fs.TOPIC_AGENTS, context=self._ctx)
        self._cvs_ch = PointCloudChannel(fs.TOPIC_CVS, context=self._ctx)
        self._scene_ch = SceneUpdateChannel(fs.TOPIC_SCENE, context=self._ctx)
        self._settings_ch.log(json_safe(dict(asdict(settings), telemetry_version=tc.VERSION,
                                             created_utc=datetime.now(timezone.utc).isoformat())), log_time=0)

    @property
    def port(self) -> int | None:
        """Port of the WebSocket server (None without one)."""
        return None if self._server is None else int(self._server.port)

    # -- raw stream ----------------------------------------------------------------------------
    def write_map(self, recv_s: float, blob: bytes, cmap: CommandMap | None = None) -> None:
        """The map the log switches to at receive time ``recv_s``."""
        with self._lock:
            msg = {"seq": self._seq, "recv_s": float(recv_s), "map_b64": base64.b64encode(bytes(blob)).decode()}
            if cmap is not None:
                msg.update(sha256=cmap.sha256, map_version=int(cmap.map_version))
            self._map_ch.log(msg, log_time=_ns(recv_s))
            self._seq += 1
            self.records += 1

    def write_telemetry(self, recv_s: np.ndarray, agent_ids: np.ndarray, payloads: list[bytes]) -> None:
        """Telemetry messages as received: receive times [UNIX s], key agent ids, raw payloads."""
        if len(payloads) == 0:
            return
        recv = np.asarray(recv_s, dtype=float)
        with self._lock:
            self._telemetry_ch.log({
                "seq": self._seq, "recv_s": recv.tolist(),
                "key_agent_id": (np.asarray(agent_ids, dtype=np.int64) & 0xFFFFFFFF).tolist(),
                "payload_b64": [base64.b64encode(bytes(p)).decode() for p in payloads]},
                log_time=_ns(recv[-1]))
            self._seq += 1
            self.records += len(payloads)

    def log_alarms(self, view: FleetView) -> bool:
        """Log ``view``'s alarms on ``/fisc/alarms`` at ``view.now_s`` if they changed since the last
        ones logged (the monitor calls it on its clock too, so that silence, "every agent stale",
        is logged although no message arrives); returns whether it logged."""
        with self._lock:
            if view.alarms == self._alarms:
                return False
            self._alarms = view.alarms
            self._alarms_ch.log({"t_s": float(view.now_s), "agents_heard": view.n_agents, "stale": len(view.stale),
                                 "alarms": list(view.alarms), "closest_approach_m": view.closest_m,
                                 "d_min_m": float(view.d_min_m)}, log_time=_ns(view.now_s))
        return True

    # -- derived scene -------------------------------------------------------------------------
    def publish(self, agg: TelemetryAggregator, force: bool = False) -> bool:
        """Log the scene, the fidelity and the state counts of ``agg`` at its newest receive time
        when due (or ``force``); returns whether it did."""
        t = agg.last_receive_s
        if not np.isfinite(t):
            return False
        if not force and self._next_publish_s is not None and t < self._next_publish_s:
            return False
        self._next_publish_s = t + self.publish_period_s
        lt = _ns(t)
        ids, rec, seen = agg.agents()
        live = seen > t - agg.stale_after_s
        points = fs.agent_points(ids[live], rec[live])
        self._agents_ch.log(fs.agents_cloud(t, points), log_time=lt)
        view = agg.view(t)
        self._states_ch.log({"t_s": t, "agents_heard": view.n_agents, "stale": len(view.stale),
                             **{s: int(view.by_state.get(s, 0)) for s in tc.STATES}}, log_time=lt)
        self.log_alarms(view)
        cmap = agg.cmap
        wall = []
        if cmap is not None:
            f = agg.fields()
            self._cvs_ch.log(fs.cvs_cloud(t, fs.cv_points(cmap["cv_center_m"], f.rho_s_kg_m3, f.p_dispersion_pa,
                                                          f.samples)), log_time=lt)
            wall = self._wall_of(cmap)
            fid = agg.field_run(self.min_samples).fidelity()
            self._fidelity_ch.log(json_safe({
                "t_s": t, "time_samples": int(f.n_time_samples), "n_cv_compared": int(fid["n_cv_compared"]),
                **{f"{k}_{q}": fid[f"{k}_{q}"] for k in ("nrmse", "pearson") for q in ("velocity", "pressure", "density")},
                "closest_approach_m": view.closest_m, "d_min_m": float(view.d_min_m),
            }), log_time=lt)
        self._scene_ch.log(fs.scene_update(t, wall, points, d_min_m=agg.d_min_m), log_time=lt)
        return True

    def _wall_of(self, cmap: CommandMap) -> list:
        if self._wall is None or self._wall[0] != cmap.sha256:
            from fisc_ground.figures.plots import design_tunnel_wall

            self._wall = (cmap.sha256, fs.wall_lines(np.asarray(cmap["cv_center_m"]), cmap.cell_size_m,
                                                     design_tunnel_wall(cmap)))
        return self._wall[1]

    def close(self) -> None:
        """Finish the MCAP file (summary, indexes) and stop the server."""
        if self._mcap is not None:
            self._mcap.close()
            self._mcap = None
        if self._server is not None:
            self._server.stop()
            self._server = None


class SimulatedTelemetry:
    """Simulated or emulated agents -> telemetry messages -> a ``FlightLog`` (and its aggregator),
    so ``fisc-sim run``/``emulate`` write what a monitor would have recorded of the same swarm.

    ``sample(t_s, ids, pos, vel, states)`` encodes one fleet sample (map frame) with receive time
    ``t_s`` (the run's clock), logs it and publishes the scene when due."""

    def __init__(self, log: FlightLog, cmap: CommandMap, blob: bytes | None = None) -> None:
        self.log = log
        self.cmap = cmap
        self.aggregator = log.settings.aggregator(cmap)
        self._sha = np.frombuffer(bytes.fromhex(cmap.sha256), dtype="V32")[0]
        self._field = None
        self._seq = 0
        if blob is not None:
            log.write_map(0.0, blob, cmap)

    def sample(self, t_s: float, ids: np.ndarray, pos_m: np.ndarray, vel_m_s: np.ndarray,
               states: np.ndarray | str = "FLOW", cv: np.ndarray | None = None) -> None:
        """One fleet sample: ids (n,), positions and velocities (n, 3) in the map frame, state names
        (n,) or one name for all, CV index (n,) (-1 outside; None: looked up on the map)."""
        n = len(ids)
        if n == 0:
            return
        rec = np.zeros(n, dtype=tc.DTYPE)
        rec["version"] = tc.VERSION
        rec["battery_pct"] = tc.NO_BATTERY
        rec["authority"] = tc.AUTHORITIES.index("command")
        names = np.full(n, states, dtype=object) if isinstance(states, str) else np.asarray(states, dtype=object)
        rec["state"] = [tc.STATES.index(s) if s in tc.STATES else 0 for s in names.tolist()]
        rec["agent_id"] = np.asarray(ids, dtype=np.int64) & 0xFFFFFFFF
        rec["seq"] = self._seq
        rec["time_s"] = float(t_s)
        rec["position_m"] = pos_m
        rec["velocity_m_s"] = vel_m_s
        if cv is None:
            if self._field is None:
                from fisc_agent.map.lookup import CommandField

                self._field = CommandField.from_map(self.cmap)
            ok = np.isfinite(np.asarray(pos_m, dtype=float)).all(axis=1)
            cv = np.full(n, -1, dtype=np.int64)
            cv[ok] = self._field.cv_of(np.asarray(pos_m, dtype=float)[ok])
        rec["cv_index"] = cv
        rec["flags"] = np.where(np.asarray(cv) < 0, tc.FLAG_OUTSIDE_MAP, 0) | tc.FLAG_MAVLINK_OK | tc.FLAG_ARMED
        rec["map_version"] = self.cmap.map_version
        rec["map_sha256"] = self._sha
        rec["position_age_ms"] = rec["heartbeat_age_ms"] = 0
        self._seq += 1
        payloads = [r.tobytes() for r in rec]
        recv = np.full(n, float(t_s))
        key = np.asarray(ids, dtype=np.int64)
        self.log.write_telemetry(recv, key, payloads)
        self.aggregator.ingest(recv, key, payloads)
        self.log.publish(self.aggregator)

    def close(self) -> Any:
        """Publish the final scene and finish the log; returns the aggregator."""
        self.log.publish(self.aggregator, force=True)
        self.log.close()
        return self.aggregator
