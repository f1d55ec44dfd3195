"""Zenoh benchmarks on loopback: map delivery latency and monitor telemetry throughput.

    python benchmarks/bench_zenoh.py                 # everything (takes ~1-2 min)
    python benchmarks/bench_zenoh.py --skip-big      # without the 10^6-CV map

1. Reference-size map (~1000 CVs, a few hundred KB) to ``--agents`` subscribers (each an
   ``AgentZenohLink`` that verifies hash and signature), spread over ``--sessions`` Zenoh
   sessions: time from ``MapServer.serve`` to the last agent's ``on_map``.  Target < 1 s.
2. A 10^6-CV map (~370 MB, 1 MiB chunks) to ``--big-agents`` running subscribers (each
   reassembles, hashes and verifies the whole map), and to one agent that starts afterwards
   (queries the map).
3. Telemetry: a separate publisher process emits ``--tele-agents`` agents x ``--rate`` Hz
   for ``--seconds`` s; the monitor's pipeline (queue, recorder, aggregator) consumes it.
   Reports messages expected/received, queue drops and recording size.  Target: 1000 x 10 Hz
   with zero drops.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fisc_agent.zenoh import telemetry_codec as tc  # noqa: E402
from fisc_agent.zenoh.keys import Keys  # noqa: E402
from fisc_agent.zenoh.link import AgentZenohLink  # noqa: E402
from fisc_agent.zenoh.session import config_from_json, peer_config_json  # noqa: E402
from tests.ports import free_tcp_port as free_port  # noqa: E402


def configs(port: int):
    hub = config_from_json(peer_config_json([f"tcp/127.0.0.1:{port}"], []))
    member = config_from_json(peer_config_json(["tcp/127.0.0.1:0"], [f"tcp/127.0.0.1:{port}"]))
    for c in (hub, member):
        c.insert_json5("scouting/gossip/enabled", "false")  # star around the hub, no full mesh
    return hub, member


def make_map(n_cv_target: int, n_max: int, version: int, key: bytes) -> bytes:
    from fisc_agent.map.codec import encode_map

    nx = max(1, int(round((n_cv_target / 16) ** (1 / 3) * 4)))
    ny = nz = max(1, int(round(np.sqrt(n_cv_target / nx))))
    n = nx * ny * nz
    idx = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
    rng = np.random.default_rng(0)
    vel = rng.normal(size=(n, n_max, 3))
    meta = {"map_version": version, "n_cv": n, "grid": {"origin_m": [0.0, -ny / 4, -nz / 4], "cell_size_m": 0.5,
                                                        "shape": [nx, ny, nz]},
            "n_range": [2, n_max], "scale": 1.0, "kappa": 1e-3, "agent_mass_kg": 1.0}
    arrays = {"cv_center_m": idx * 0.5 + 0.25, "cv_index": idx, "grid_cv": np.arange(n, dtype=np.int32).reshape(nx, ny, nz),
              "n_star": np.full(n, n_max), "fit_velocity_m_s": vel, "fit_mean_velocity_m_s": vel.mean(1),
              "fit_pressure": np.ones(n), "fit_loss": np.zeros(n), "target_velocity_m_s": vel.mean(1),
              "target_pressure_gauge_pa": np.ones(n), "target_density_kg_m3": np.ones(n),
              "swarm_pressure_target": np.ones(n), "node_count": np.ones(n)}
    return encode_map(meta, arrays, key)


def bench_map(n_agents: int, n_sessions: int, blob: bytes, key_pub: bytes, label: str, timeout_s: float) -> dict:
    import zenoh

    from fisc_agent.map.codec import decode_map
    from fisc_ground.zenoh.publish import MapServer

    port = free_port()
    hub_cfg, member_cfg = configs(port)
    hub = zenoh.open(hub_cfg)
    t0 = time.perf_counter()
    sessions = [zenoh.open(member_cfg) for _ in range(n_sessions)]
    t_open = time.perf_counter() - t0
    done = threading.Event()
    arrivals: list[float] = []
    lock = threading.Lock()

    def on_map(_cmap):
        with lock:
            arrivals.append(time.perf_counter())
            if len(arrivals) == n_agents:
                done.set()

    links = [AgentZenohLink(None, "bench", i, [key_pub], False, on_map, lambda c: None,
                            session=sessions[i % n_sessions]).start() for i in range(n_agents)]
    time.sleep(1.0)  # let declarations propagate (agents running before the map is served)
    server = MapServer(hub, "bench", announce_period_s=1.0)
    t_serve = time.perf_counter()
    server.serve(blob)
    done.wait(timeout_s)
    lat = np.array(arrivals) - t_serve
    out = {"case": label, "map_bytes": len(blob), "n_cv": decode_map(blob).n_cv, "agents": n_agents,
           "sessions": n_sessions, "received": len(arrivals), "session_open_s": round(t_open, 2),
           "latency_first_s": round(float(lat.min()), 3) if lat.size else None,
           "latency_median_s": round(float(np.median(lat)), 3) if lat.size else None,
           "latency_last_s": round(float(lat.max()), 3) if lat.size else None}
    for link in links:
        link.close()
    server.close()
    for s in sessions:
        s.close()
    hub.close()
    return out


def bench_late_joiner(blob: bytes, key_pub: bytes, label: str) -> dict:
    """An agent that starts after the map is served: session open + query + reassembly + checks."""
    import zenoh

    from fisc_ground.zenoh.publish import MapServer

    port = free_port()
    hub_cfg, member_cfg = configs(port)
    hub = zenoh.open(hub_cfg)
    server = MapServer(hub, "bench")
    server.serve(blob)
    got = threading.Event()
    t0 = time.perf_counter()
    link = AgentZenohLink(member_cfg, "bench", 1, [key_pub], False, lambda m: got.set(), lambda c: None).start()
    got.wait(300)
    out = {"case": label, "map_bytes": len(blob), "received": got.is_set(),
           "seconds_from_agent_start": round(time.perf_counter() - t0, 2), "queries": link.stats.queries_sent}
    link.close()
    server.close()
    hub.close()
    return out


def _publisher(port: int, n_agents: int, rate_hz: float, seconds: float, ready, go) -> None:
    import zenoh

    _, member = configs(port)
    s = zenoh.open(member)
    pubs = [s.declare_publisher(f"fisc/bench/agents/{i}/telemetry", congestion_control=zenoh.CongestionControl.DROP)
            for i in range(n_agents)]
    msgs = [tc.encode(tc.Telemetry(agent_id=i, seq=0, time_s=0.0, position_m=(1.0, 0.0, 0.0),
                                   velocity_m_s=(3.0, 0.0, 0.0), state="FLOW")) for i in range(n_agents)]
    ready.set()
    go.wait()
    period = 1.0 / rate_hz
    t_next = time.perf_counter()
    sent = 0
    end = t_next + seconds
    while time.perf_counter() < end:
        for p, m in zip(pubs, msgs):
            p.put(m)
        sent += n_agents
        t_next += period
        time.sleep(max(0.0, t_next - time.perf_counter()))
    time.sleep(0.5)
    s.close()
    print(json.dumps({"sent": sent}), flush=True)


def bench_telemetry(n_agents: int, rate_hz: float, seconds: float) -> dict:
    import zenoh

    from fisc_ground.monitor.flight_log import FlightLog, LogSettings
    from fisc_ground.monitor.run import TelemetryAggregator, TelemetryPipe

    port = free_port()
    hub_cfg, _ = configs(port)
    hub = zenoh.open(hub_cfg)
    tmp = Path(tempfile.mkdtemp()) / "bench.mcap"
    rec = FlightLog(LogSettings(swarm="bench", sample_period_s=0.5, stale_after_s=3.0), mcap_path=tmp)
    agg = TelemetryAggregator(None)
    pipe = TelemetryPipe(Keys("fisc", "bench"), agg, rec).attach(hub)
    ctx = mp.get_context("spawn")
    ready, go = ctx.Event(), ctx.Event()
    proc = ctx.Process(target=_publisher, args=(port, n_agents, rate_hz, seconds, ready, go))
    proc.start()
    ready.wait(60)
    time.sleep(1.0)
    go.set()
    t0 = time.perf_counter()
    proc.join(seconds + 60)
    pipe.drain(30)
    wall = time.perf_counter() - t0
    pipe.close()
    rec.close()
    hub.close()
    expected = int(round(seconds * rate_hz)) * n_agents
    return {"case": "telemetry", "agents": n_agents, "rate_hz": rate_hz, "seconds": seconds,
            "expected": expected, "received": pipe.received, "queue_drops": pipe.dropped,
            "ingested": agg.messages, "agents_seen": len(agg.slots), "lost_in_transport": max(0, expected - pipe.received),
            "msgs_per_s": round(pipe.received / seconds), "recording_mb": round(os.path.getsize(tmp) / 1e6, 1),
            "wall_s": round(wall, 1)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--agents", type=int, default=100)
    ap.add_argument("--sessions", type=int, default=20, help="Zenoh sessions the map subscribers share")
    ap.add_argument("--big-agents", type=int, default=2)
    ap.add_argument("--big-cv", type=int, default=1_000_000)
    ap.add_argument("--skip-big", action="store_true")
    ap.add_argument("--tele-agents", type=int, default=1000)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--seconds", type=float, default=10.0)
    args = ap.parse_args()
    from nacl.signing import SigningKey

    key = SigningKey.generate()
    pub = key.verify_key.encode()
    ref = make_map(1000, 10, 1, key.encode())
    print(json.dumps(bench_map(args.agents, args.sessions, ref, pub, "reference map", 30)), flush=True)
    if not args.skip_big:
        t0 = time.perf_counter()
        big = make_map(args.big_cv, 10, 2, key.encode())
        print(json.dumps({"case": "build 10^6-CV map", "bytes": len(big), "seconds": round(time.perf_counter() - t0, 1)}),
              flush=True)
        print(json.dumps(bench_map(args.big_agents, args.big_agents, big, pub, "10^6-CV map", 300)), flush=True)
        print(json.dumps(bench_late_joiner(big, pub, "10^6-CV map, late joiner")), flush=True)
        del big
    print(json.dumps(bench_telemetry(args.tele_agents, args.rate, args.seconds)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
