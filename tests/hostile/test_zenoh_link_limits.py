"""Issue 12, agent side: the Zenoh link's own limits on a real (local, loopback-only) session."""

from __future__ import annotations

import json
import os

import pytest

from fisc_agent.map.chunks import CHUNK_HEADER, CHUNK_MAGIC, CHUNK_VERSION, KIND_CHUNK
from fisc_agent.zenoh.link import AgentZenohLink

from ..zenoh.conftest import wait_for
from ..optional import require_module

zenoh = require_module("zenoh")


@pytest.fixture()
def session():
    cfg = zenoh.Config()
    for key, value in {"mode": "peer", "listen": {"endpoints": []}, "connect": {"endpoints": []},
                       "scouting": {"multicast": {"enabled": False}}}.items():
        cfg.insert_json5(key, json.dumps(value))
    s = zenoh.open(cfg)
    yield s
    s.close()


def test_payloads_beyond_the_receive_queue_are_dropped_uncopied_and_counted(session):
    link = AgentZenohLink(None, "alpha", 1, None, True, lambda m: None, lambda c: None, session=session,
                          rx_queue_bytes=10_000)
    link.start()
    try:
        session.put("fisc/alpha/map", os.urandom(50_000))  # larger than the whole queue
        assert wait_for(lambda: link.stats.map_messages_dropped == 1, 5)
        bogus = CHUNK_HEADER.pack(CHUNK_MAGIC, CHUNK_VERSION, KIND_CHUNK, 0, 5, os.urandom(32), 64, 0, 1, 0)
        for _ in range(100):
            session.put("fisc/alpha/map", bogus + os.urandom(64))  # each completes and fails its sha256
        # every message is accounted for: refused after reassembly, or dropped by the full queue
        assert wait_for(lambda: link.stats.maps_rejected + link.stats.map_messages_dropped == 101, 5), \
            (link.stats, link.rlog.counts())
        assert link.stats.maps_rejected >= 1 and link.stats.last_reject_reason == "chunks"
        assert link.rlog.count("map:chunks") == link.stats.maps_rejected
        assert link.rlog.count("rx:queue_full") == link.stats.map_messages_dropped
    finally:
        link.close()
