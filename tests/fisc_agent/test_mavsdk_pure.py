"""MAVSDK backend pieces that need no MAVSDK (issue 36 item 6): the bounded drop-oldest command queue
and the setpoint-stall rule of the watchdog."""

from __future__ import annotations

import queue
import threading

import pytest

from fisc_agent.mavlink.mavsdk_backend import (LANDED_OF, SETPOINT_STALL_S, DropOldestQueue, setpoint_stalled)
from fisc_agent.flight.health import LandedState


def test_the_queue_drops_the_oldest_when_full_and_counts_it():
    q = DropOldestQueue(3)
    for i in range(3):
        q.put(i)
    assert q.dropped == 0 and q.qsize() == 3          # exactly full: nothing dropped
    q.put(3)
    q.put(4)
    assert q.dropped == 2 and [q.get(0.1) for _ in range(3)] == [2, 3, 4]
    with pytest.raises(queue.Empty):
        q.get(0.01)
    with pytest.raises(ValueError):
        DropOldestQueue(0)


def test_the_queue_never_blocks_a_producer_and_stays_bounded_under_threads():
    q = DropOldestQueue(4)

    def produce():
        for i in range(500):
            q.put(i)
    threads = [threading.Thread(target=produce) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(5)
    assert q.qsize() == 4 and q.dropped == 4 * 500 - 4


@pytest.mark.parametrize("age_s, stalled", [(0.0, False), (SETPOINT_STALL_S, False), (SETPOINT_STALL_S + 1e-6, True)])
def test_setpoint_stall_boundary(age_s, stalled):
    assert setpoint_stalled(10.0, 10.0 + age_s, in_offboard=True) is stalled


def test_no_stall_before_any_setpoint_or_outside_offboard():
    assert not setpoint_stalled(None, 1e9, in_offboard=True)
    assert not setpoint_stalled(10.0, 1e9, in_offboard=False)   # a pilot's mode: stop() would request Hold


def test_mavsdk_landed_states_map_onto_ours():
    assert LANDED_OF == {"ON_GROUND": LandedState.ON_GROUND, "IN_AIR": LandedState.IN_AIR,
                         "TAKING_OFF": LandedState.TAKEOFF, "LANDING": LandedState.LANDING}
