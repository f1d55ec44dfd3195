"""Shared fixtures for the Zenoh tests: real sessions, peer mode, loopback, explicit ports."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh  # a dependency: missing means broken, not skipped

from fisc_agent.map.codec import encode_map
from fisc_ground.maps.write import generate_keypair, read_signing_key

from ..ports import free_tcp_port as free_port  # noqa: F401 (the zenoh tests import it from here)




def listening(port: int) -> bool:
    """A TCP socket of this machine listens on ``port`` (read from /proc: no probe connection)."""
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            cols = line.split()
            if int(cols[1].rsplit(":", 1)[1], 16) == port and cols[3] == "0A":
                return True
    return False


def write_config(path: Path, listen: list[str], connect: list[str], gossip: bool = True, extra: dict | None = None) -> Path:
    """A standard Zenoh JSON5 config: peer mode, multicast scouting off, explicit endpoints."""
    cfg = {"mode": "peer", "listen": {"endpoints": listen}, "connect": {"endpoints": connect},
           "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": gossip}}}
    cfg.update(extra or {})
    path.write_text("// FISC test config\n" + json.dumps(cfg, indent=2))
    return path


def map_parts(version: int, nx: int = 12, ny: int = 4, nz: int = 4, n_max: int = 4, seed: int = 0) -> tuple[dict, dict]:
    """A small tunnel-like map: every cell of an nx x ny x nz grid (l = 0.5 m) is a CV."""
    rng = np.random.default_rng(seed)
    cell = 0.5
    origin = np.array([0.0, -ny * cell / 2, -nz * cell / 2])
    idx = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
    n = len(idx)
    grid = np.arange(n, dtype=np.int32).reshape(nx, ny, nz)
    centers = origin + (idx + 0.5) * cell
    vel = rng.normal(size=(n, n_max, 3)) * 0.3 + np.array([3.0, 0.0, 0.0])
    meta = {"map_version": version, "n_cv": n,
            "grid": {"origin_m": origin.tolist(), "cell_size_m": cell, "shape": [nx, ny, nz]},
            "n_range": [2, n_max], "scale": 1.0, "kappa": 1e-3, "agent_mass_kg": 1.5}
    arrays = {
        "cv_center_m": centers, "cv_index": idx, "grid_cv": grid, "n_star": np.full(n, n_max),
        "fit_velocity_m_s": vel, "fit_mean_velocity_m_s": vel.mean(axis=1), "fit_pressure": np.ones(n),
        "fit_loss": np.zeros(n), "target_velocity_m_s": vel.mean(axis=1),
        "target_pressure_gauge_pa": 100.0 - centers[:, 0] * 5.0, "target_density_kg_m3": 1.2 - 0.001 * centers[:, 0],
        "swarm_pressure_target": np.ones(n), "node_count": np.full(n, 5),
    }
    return meta, arrays


@pytest.fixture()
def ground_key(tmp_path):
    key, pub = generate_keypair(tmp_path / "ground")
    return read_signing_key(key), bytes.fromhex(pub.read_text().strip()), key, pub


@pytest.fixture()
def make_map(ground_key):
    def make(version: int, signing_key: bytes | None | str = "ground", **kw) -> bytes:
        meta, arrays = map_parts(version, **kw)
        key = ground_key[0] if signing_key == "ground" else signing_key
        return encode_map(meta, arrays, key)
    return make


@pytest.fixture()
def net(tmp_path):
    """Hub config (listens) and a factory of member configs (connect to the hub)."""
    port = free_port()
    hub = write_config(tmp_path / "hub.json5", [f"tcp/127.0.0.1:{port}"], [])
    member = write_config(tmp_path / "member.json5", ["tcp/127.0.0.1:0"], [f"tcp/127.0.0.1:{port}"])
    return hub, member


@pytest.fixture()
def sessions():
    """Open sessions through ``open(config_path)``; all are closed at teardown."""
    opened = []

    def open_(path):
        s = zenoh.open(zenoh.Config.from_file(str(path)))
        opened.append(s)
        return s
    yield open_
    for s in reversed(opened):
        if not s.is_closed():
            s.close()


def wait_for(pred, timeout_s: float = 10.0, period_s: float = 0.02) -> bool:
    """Poll ``pred`` until true or the timeout (the tests' only waiting primitive)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(period_s)
    return bool(pred())


def snap(**fields):
    """A runner ``AgentSnapshot`` for link tests: an armed agent in FLOW with fresh fixes, no map,
    now; ``fields`` (the snapshot's own field names) override."""
    import math

    from fisc_agent.flight.tick import AgentSnapshot

    base = dict(time_s=time.monotonic(), wall_time_s=time.time(), agent_id=0, state="FLOW", reason="test",
                position_map_m=None, velocity_map_m_s=None, setpoint_map_m_s=None, cv_id=-1, map_sha256=None,
                map_version=None, link_ok=True, heartbeat_age_s=0.1, position_age_s=0.1, autopilot="px4",
                armed=True, mode="offboard", laps=0, failsafe=False, outside_map=False)
    base.update(fields)
    if base["position_map_m"] is not None:
        base["position_map_m"] = tuple(float(v) for v in base["position_map_m"])
    if base["velocity_map_m_s"] is not None:
        base["velocity_map_m_s"] = tuple(float(v) for v in base["velocity_map_m_s"])
    assert all(math.isfinite(v) for v in (base["time_s"], base["wall_time_s"]))
    return AgentSnapshot(**base)
