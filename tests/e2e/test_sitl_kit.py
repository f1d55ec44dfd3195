"""The SITL harness's own logic that needs no autopilot (fast)."""

import subprocess
import sys
import time

import numpy as np
import pytest

from .sitl_kit import MachineLock, pass_states


def _takeoff_join_pass():
    """A take-off that drifts forward past x = 0 eight metres below the map, the join to the entry
    point in front of the inlet, then the pass along the axis and out (map frame, 10 Hz)."""
    takeoff = [((0.03 * k, 0.0, -8.0 + 0.1 * k), (0.3, 0.0, 1.0)) for k in range(10)]
    join = [((-1.5 + 0.1 * k, 0.2, 0.0), (0.05, 0.0, 0.0)) for k in range(15)]
    through = [((0.1 * k, 0.1, 0.0), (1.0, 0.0, 0.0)) for k in range(160)]
    pos, vel = zip(*(takeoff + join + through))
    return np.array(pos), np.array(vel), len(takeoff) + len(join)


def test_the_pass_begins_at_the_inlet_not_at_a_takeoff_that_drifts_forward():
    pos, vel, first = _takeoff_join_pass()
    states = pass_states(pos, vel, 0.0, 15.0, near_axis_m=3.0)
    assert np.flatnonzero(states == "FLOW")[0] == first
    past = np.flatnonzero(pos[:, 0] > 15.0)[0]
    assert np.all(states[first:past + 1] == "FLOW") and np.all(states[past + 1:] == "JOIN")
    # without the bound on the distance from the axis the take-off, 8 m below the map, began it
    assert np.flatnonzero(pass_states(pos, vel, 0.0, 15.0, near_axis_m=np.inf) == "FLOW")[0] == 0


def test_no_forward_motion_in_the_duct_means_no_pass():
    pos, vel, first = _takeoff_join_pass()
    assert np.all(pass_states(pos[:first], vel[:first], 0.0, 15.0, 3.0) == "JOIN")


def test_a_second_session_waits_for_the_first_sessions_vehicles(tmp_path):
    """Two sessions' SITL vehicles would share ports and PX4's /tmp sockets: the lock serialises them."""
    lock = tmp_path / "sitl.lock"
    code = ("import sys, time; from pathlib import Path; from tests.e2e.sitl_kit import MachineLock; "
            f"MachineLock(path=Path({str(lock)!r})).acquire(); print('held', flush=True); time.sleep(60)")
    other = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert other.stdout.readline().strip() == "held"
        t0 = time.monotonic()
        with pytest.raises(RuntimeError, match=rf"pid {other.pid}\)"):
            MachineLock(timeout_s=1.0, path=lock).acquire()
        assert time.monotonic() - t0 >= 1.0
    finally:
        other.kill()
        other.wait()
    mine = MachineLock(timeout_s=5.0, path=lock)
    mine.acquire()   # the holder is gone: the lock is free again
    mine.release()


def test_the_authority_flights_mode_requests_merge_ground_and_agent_and_set_self_resuming_holds_apart(tmp_path):
    """``test_authority_sitl._mode_requests``: the ground's and the agent's requests in time order; a jump hold's
    Hold and the OFFBOARD after its fix came back are in the whole sequence, not in the scripted one."""
    from datetime import datetime
    from types import SimpleNamespace

    from .test_authority_sitl import _mode_requests

    console = tmp_path / "agent.log"
    console.write_text("\n".join([
        "2026-12-06 04:20:22,827 INFO fisc_agent.mavlink.adapters: requesting set mode OFFBOARD",
        "2026-12-06 04:20:29,629 INFO fisc_agent.flight.mission: mission TAKEOFF -> HOLD (position jump: reset)",
        "2026-12-06 04:20:31,629 INFO fisc_agent.mavlink.adapters: requesting set mode AUTO.LOITER",
        "2026-12-06 04:20:31,677 INFO fisc_agent.flight.mission: mission HOLD -> TAKEOFF (position fix back)",
        "2026-12-06 04:20:31,700 INFO fisc_agent.mavlink.adapters: requesting set mode OFFBOARD",
        "2026-12-06 04:20:33,578 INFO fisc_agent.flight.mission: mission TAKEOFF -> HOLD (pilot override: x)",
        "2026-12-06 04:20:40,477 INFO fisc_agent.flight.mission: mission HOLD -> JOIN (already flying: taking over)",
        "2026-12-06 04:20:41,478 INFO fisc_agent.mavlink.adapters: requesting set mode OFFBOARD",
        "2026-12-06 04:20:45,000 WARNING fisc_agent.mavlink.adapters: still requesting set mode AUTO.LAND (attempt 5)",
    ]) + "\n")
    ground_hold_t = datetime(2026, 12, 6, 4, 20, 33).timestamp()  # the ground's Hold, before the agent sees it
    gcs = SimpleNamespace(mode_requests=[(ground_hold_t, "AUTO.LOITER")])
    every, scripted = _mode_requests(gcs, SimpleNamespace(log_path=console))
    assert every == ["OFFBOARD", "AUTO.LOITER", "OFFBOARD", "AUTO.LOITER", "OFFBOARD"]
    assert scripted == ["OFFBOARD", "AUTO.LOITER", "OFFBOARD"]
    assert _mode_requests(SimpleNamespace(mode_requests=[]), SimpleNamespace(log_path=tmp_path / "none")) == ([], [])
