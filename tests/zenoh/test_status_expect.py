"""``fisc-ground status --expect N``: exit 1 when fewer than N agents answer (issue 38), and the
silence alarms it shares with the monitor (every agent stale vs some stale) at their boundaries."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from fisc_agent.zenoh import telemetry_codec as tc
from fisc_agent.zenoh.link import AgentZenohLink
from fisc_agent.zenoh.session import PORT_ENV, LabDiscovery, open_lab_session
from fisc_ground.monitor.alarms import fleet_alarms
from fisc_ground.zenoh.fleet import expect_shortfall, listen

from .conftest import free_port, snap


def _report(live: list[int], stale: list[int]) -> dict:
    return {"agents": [{"id": i, "stale": False} for i in live] + [{"id": i, "stale": True} for i in stale],
            "alarms": []}


def test_expect_counts_answering_agents_at_the_boundary():
    assert expect_shortfall(_report([1, 2, 3], []), 3) is None          # equal
    assert expect_shortfall(_report([1, 2, 3], []), 2) is None          # more than expected
    assert expect_shortfall(_report([1, 2, 3], []), 4) == "only 3 of 4 expected agents answered; 1 never heard"
    # a stale agent does not answer, and is named
    assert expect_shortfall(_report([1, 2], [7]), 3) == \
        "only 2 of 3 expected agents answered; heard but silent since: 7"
    assert expect_shortfall(_report([1, 2], [7]), 2) is None
    assert expect_shortfall(_report([], []), 1) == "only 0 of 1 expected agents answered; 1 never heard"
    assert expect_shortfall(_report([], [4, 5]), 3) == \
        "only 0 of 3 expected agents answered; heard but silent since: 4, 5; 1 never heard"


class _Heard:
    """A telemetry listener's snapshot: agent 5, last heard ``age_s`` ago."""

    def __init__(self, age_s: float) -> None:
        self.age_s = age_s

    def snapshot(self) -> dict:
        return {5: (None, time.time() - self.age_s)}


def test_listening_ends_once_the_expected_agents_answer_and_not_on_a_stale_one():
    t0 = time.monotonic()
    assert list(listen(_Heard(0.0), 30.0, expect=1, stale_after_s=3.0)) == [5]  # answered: at once
    assert time.monotonic() - t0 < 15.0
    for expect, age_s in ((2, 0.0), (1, 3.5), (None, 0.0)):  # one short; heard but stale; no --expect
        t0 = time.monotonic()
        listen(_Heard(age_s), 0.3, expect=expect, stale_after_s=3.0)
        assert time.monotonic() - t0 >= 0.3, (expect, age_s)  # the whole window


def test_every_agent_stale_is_told_apart_from_some_stale():
    ids = np.array([3, 1])
    healthy = tc.Telemetry(agent_id=1, seq=1, time_s=0, position_m=(0, 0, 0), velocity_m_s=(0, 0, 0))
    records, _ = tc.decode_many([tc.encode(healthy)] * 2)
    assert fleet_alarms(np.array([], dtype=np.int64), records[:0], np.array([], dtype=bool), 3.0) == []
    assert fleet_alarms(ids, records, np.array([True, True]), 3.0) == []
    assert fleet_alarms(ids, records, np.array([True, False]), 3.0)[0] == "stale (not heard for 3 s): agents 1"
    assert fleet_alarms(ids, records, np.array([False, False]), 3.0)[0] == \
        "every agent stale: none of the 2 agents heard in the last 3 s"
    assert fleet_alarms(ids[:1], records[:1], np.array([False]), 3.0)[0].startswith("every agent stale")


@pytest.mark.slow
def test_status_process_exits_non_zero_below_the_expected_count():
    """A lab-default agent link publishes; ``status --expect 1`` exits 0, ``--expect 2`` exits 1
    and says how many answered."""
    port = free_port()
    session = open_lab_session(LabDiscovery(port=port))
    link = AgentZenohLink(None, "ex", 5, None, True, lambda m: None, lambda c: None, session=session).start()
    link.start_telemetry(lambda: snap(agent_id=5, position_map_m=(1.0, 0.0, 0.0)), rate_hz=10)
    env = {**os.environ, PORT_ENV: str(port)}
    try:
        for expect, wait_s, code in ((1, 30, 0), (2, 2, 1)):  # the first returns once agent 5 is heard
            t0 = time.monotonic()
            out = subprocess.run([sys.executable, "-m", "fisc_ground.cli", "status", "--swarm", "ex", "--wait",
                                  str(wait_s), "--expect", str(expect)], env=env, capture_output=True, text=True,
                                 timeout=60)
            assert out.returncode == code, (expect, out.stdout, out.stderr)
            assert time.monotonic() - t0 < (15 if code == 0 else 60), expect
            assert ("only 1 of 2 expected agents answered; 1 never heard" in out.stderr + out.stdout) == (code == 1)
        bad = subprocess.run([sys.executable, "-m", "fisc_ground.cli", "status", "--swarm", "ex", "--expect", "0"],
                             env=env, capture_output=True, text=True, timeout=60)
        assert bad.returncode == 2 and "--expect" in bad.stderr
    finally:
        link.close()
        session.close()
