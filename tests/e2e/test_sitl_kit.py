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
