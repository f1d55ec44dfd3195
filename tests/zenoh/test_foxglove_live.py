"""``fisc-ground monitor --foxglove PORT``: a Foxglove WebSocket client (subprotocol
``foxglove.sdk.v1`` of foxglove-sdk 0.30) connected to a real monitor process receives the agents'
positions and the per-CV density within 5 s of the first telemetry; the shipped layout matches
the channels."""

from __future__ import annotations

import asyncio
import base64
import json
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fisc_agent.map.codec import decode_map
from fisc_agent.zenoh.link import AgentZenohLink
from fisc_ground.monitor import foxglove_scene as fs

from .conftest import free_port, snap, wait_for
from ..optional import require_module

websockets = require_module("websockets", extra="test")

SUBPROTOCOL = "foxglove.sdk.v1"


def protobuf_decoder(schema_name: str, schema_b64: str):
    """Decoder of a protobuf channel from its advertised FileDescriptorSet (mcap-protobuf-support)."""
    from mcap.records import Schema
    from mcap_protobuf.decoder import DecoderFactory

    schema = Schema(id=1, name=schema_name, encoding="protobuf", data=base64.b64decode(schema_b64))
    return DecoderFactory().decoder_for("protobuf", schema)


def cloud_points(msg, dtype: np.dtype) -> np.ndarray:
    """A decoded foxglove.PointCloud's points, checked against the expected packing."""
    assert msg.point_stride == dtype.itemsize and [f.name for f in msg.fields] == list(dtype.names)
    return np.frombuffer(msg.data, dtype=dtype)


async def collect(url: str, until, timeout_s: float) -> dict:
    """Connect, subscribe to every channel, decode messages into {topic: [(t_recv, msg)]} until
    ``until(got)`` holds or ``timeout_s`` passes."""
    got: dict[str, list] = {}
    async with websockets.connect(url, subprotocols=[SUBPROTOCOL], open_timeout=10) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        channels: dict[int, dict] = {}
        subs: dict[int, tuple[str, object]] = {}
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and not until(got):
            try:
                raw = await asyncio.wait_for(ws.recv(), timeout=max(0.05, end - time.monotonic()))
            except asyncio.TimeoutError:
                break
            if isinstance(raw, str):
                msg = json.loads(raw)
                if msg["op"] == "advertise":
                    new = []
                    for ch in msg["channels"]:
                        channels[ch["id"]] = ch
                        sid = len(subs) + 1
                        dec = (protobuf_decoder(ch["schemaName"], ch["schema"]) if ch["encoding"] == "protobuf"
                               else json.loads)
                        subs[sid] = (ch["topic"], dec)
                        new.append({"id": sid, "channelId": ch["id"]})
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                    got.setdefault("_advertised", []).extend((c["topic"], c["schemaName"], c["encoding"])
                                                             for c in msg["channels"])
                continue
            assert raw[0] == 0x01  # message data: opcode, u32 subscription id, u64 log time, payload
            sid, _ = struct.unpack_from("<IQ", raw, 1)
            topic, dec = subs[sid]
            got.setdefault(topic, []).append((time.monotonic(), dec(raw[13:])))
    return got


@pytest.mark.slow
def test_a_foxglove_client_sees_agents_and_cv_density_within_5_s_of_the_first_telemetry(
        net, sessions, make_map, ground_key, tmp_path):
    hub, member = net
    blob = make_map(7, nx=12)
    cmap = decode_map(blob)
    map_path = tmp_path / "m.fiscmap"
    map_path.write_bytes(blob)
    port = free_port()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    monitor = subprocess.Popen(
        [sys.executable, "-m", "fisc_ground.cli", "monitor", "--swarm", "alpha", "--zenoh-config", str(hub),
         "--map", str(map_path), "--trusted-key", str(ground_key[3]), "--foxglove", str(port),
         "--sample-period", "0.2", "--duration", "60", "--record", str(tmp_path / "live.mcap")],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    links = []
    try:
        url = f"ws://127.0.0.1:{port}"

        async def scenario():
            # connect first (retrying until the monitor serves), then start the agents
            for _ in range(200):
                try:
                    async with websockets.connect(url, subprotocols=[SUBPROTOCOL], open_timeout=2):
                        break
                except OSError:
                    await asyncio.sleep(0.1)
            else:
                raise AssertionError("the monitor's Foxglove server never came up")
            n = 6
            t_first = {}

            def start_agents():
                link_session = sessions(member)
                for i in range(n):
                    start = np.array([1.0 + 0.5 * i, 0.1 * i - 0.3, 0.0])
                    vel = np.array([0.05, 0.0, 0.0])
                    t0 = time.time()
                    link = AgentZenohLink(None, "alpha", 100 + i, [ground_key[1]], False, lambda m: None,
                                          lambda c: None, session=link_session).start()
                    link.start_telemetry(lambda s=start, v=vel, t0=t0, i=i: snap(
                        agent_id=100 + i, position_map_m=s + v * (time.time() - t0), velocity_map_m_s=v,
                        map_sha256=cmap.sha256, map_version=cmap.map_version), rate_hz=10)
                    links.append(link)
                t_first["t"] = time.monotonic()

            def done(got):
                agents = [m for _, m in got.get(fs.TOPIC_AGENTS, []) if len(m.data)]
                cvs = [m for _, m in got.get(fs.TOPIC_CVS, [])
                       if np.nansum(cloud_points(m, fs.CV_DTYPE)["density_kg_m3"]) > 0]
                arrows = [m for _, m in got.get(fs.TOPIC_SCENE, [])
                          if any(e.id == "velocity" and len(e.arrows) == n for e in m.entities)]
                return bool(agents) and bool(cvs) and bool(arrows) and len(cloud_points(agents[-1], fs.AGENT_DTYPE)) == n

            loop = asyncio.get_running_loop()
            loop.call_later(0.5, start_agents)
            got = await collect(url, done, timeout_s=30)
            return got, t_first["t"], n

        got, t_first, n = asyncio.run(scenario())
    finally:
        for link in links:
            link.close()
        os.killpg(monitor.pid, signal.SIGINT)
        out, _ = monitor.communicate(timeout=30)
    advertised = {t: (name, enc) for t, name, enc in got["_advertised"]}
    assert advertised[fs.TOPIC_AGENTS] == ("foxglove.PointCloud", "protobuf")
    assert advertised[fs.TOPIC_CVS] == ("foxglove.PointCloud", "protobuf")
    assert advertised[fs.TOPIC_SCENE] == ("foxglove.SceneUpdate", "protobuf")
    assert advertised[fs.TOPIC_FIDELITY] == ("fisc.Fidelity", "json")
    full = [(t, m) for t, m in got[fs.TOPIC_AGENTS] if len(cloud_points(m, fs.AGENT_DTYPE)) == n]
    dense = [(t, m) for t, m in got[fs.TOPIC_CVS] if np.nansum(cloud_points(m, fs.CV_DTYPE)["density_kg_m3"]) > 0]
    assert full and dense, out.decode(errors="replace")[-3000:]
    assert full[0][0] - t_first < 5.0 and dense[0][0] - t_first < 5.0
    pts = cloud_points(full[-1][1], fs.AGENT_DTYPE)
    assert sorted(pts["agent_id"].tolist()) == list(range(100, 100 + n))
    order = np.argsort(pts["agent_id"])
    # positions are the agents' own (x advanced by 0.05 m/s since start), in the map frame
    np.testing.assert_allclose(pts["y"][order], 0.1 * np.arange(n) - 0.3, atol=1e-6)
    assert np.all(pts["x"][order] >= 1.0 + 0.5 * np.arange(n) - 1e-6)
    assert np.all(pts["x"][order] < 1.0 + 0.5 * np.arange(n) + 0.05 * 30)
    assert set(pts["state"].tolist()) == {fs.tc.STATES.index("FLOW")}
    cvs = cloud_points(dense[-1][1], fs.CV_DTYPE)
    assert len(cvs) == cmap.n_cv and np.nanmax(cvs["density_kg_m3"]) > 0
    # the scene carries the wall and, once all are heard, one velocity arrow per agent
    scenes = [{e.id: e for e in m.entities} for _, m in got[fs.TOPIC_SCENE]]
    assert all(len(s["duct_wall"].lines) >= 5 for s in scenes)
    assert any(len(s["velocity"].arrows) == n for s in scenes)


def test_the_shipped_layout_is_the_generated_one_and_names_only_fisc_channels():
    shipped = Path(__file__).resolve().parents[2] / "docs" / "foxglove_layout.json"
    assert json.loads(shipped.read_text()) == json.loads(fs.layout_json())
    text = shipped.read_text()
    for topic in (fs.TOPIC_AGENTS, fs.TOPIC_CVS, fs.TOPIC_SCENE, fs.TOPIC_FIDELITY, fs.TOPIC_STATES):
        assert topic in text


def test_arrow_quaternions_turn_x_onto_the_velocity():
    from scipy.spatial.transform import Rotation

    v = np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, -3.0], [-1.0, 0, 0], [1.0, 1.0, 1.0], [0, 0, 0]])
    q = fs.arrow_quaternions(v)
    turned = Rotation.from_quat(q).apply(np.array([1.0, 0, 0]))
    unit = np.divide(v, np.linalg.norm(v, axis=1, keepdims=True), out=np.tile([1.0, 0, 0], (len(v), 1)),
                     where=np.linalg.norm(v, axis=1, keepdims=True) > 0)
    np.testing.assert_allclose(turned, unit, atol=1e-12)


def test_a_flight_log_that_cannot_open_its_file_or_port_names_it(tmp_path):
    import socket

    from fisc_ground.monitor.flight_log import FlightLog, FlightLogError, LogSettings

    with pytest.raises(FlightLogError, match="nowhere/x.mcap"):
        FlightLog(LogSettings(), mcap_path=tmp_path / "nowhere" / "x.mcap")
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(FlightLogError, match=f"127.0.0.1:{port}"):
            FlightLog(LogSettings(), mcap_path=tmp_path / "x.mcap", ws_port=port)
    with pytest.raises(ValueError, match="MCAP file or a WebSocket port"):
        FlightLog(LogSettings())
