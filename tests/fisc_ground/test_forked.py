"""``fisc_ground.figures.forked.ForkedCall``: a call in a forked process, its result or its error here."""

from __future__ import annotations

import multiprocessing
import os
import signal
import time

import numpy as np
import pytest

from fisc_ground.figures.forked import ForkedCall, can_fork

pytestmark = pytest.mark.skipif(not can_fork(), reason="fork not available here")


class _Unpicklable(Exception):
    def __reduce__(self):
        raise TypeError("not picklable")


def _pid_and_sum(values: np.ndarray) -> tuple[int, float]:
    return os.getpid(), float(values.sum())


def _raise(kind: str):
    if kind == "value":
        raise ValueError("bad value 7")
    raise _Unpicklable("lost on the way")


def _die():
    os.kill(os.getpid(), signal.SIGKILL)


def test_the_result_comes_from_another_process_with_this_ones_data():
    data = np.arange(1000.0)  # inherited through the fork, not pickled
    pid, total = ForkedCall(_pid_and_sum, data).result()
    assert pid != os.getpid() and total == data.sum()
    assert multiprocessing.active_children() == []


def test_an_exception_there_is_raised_here_with_the_other_traceback_as_a_note():
    with pytest.raises(ValueError, match="bad value 7") as err:
        ForkedCall(_raise, "value", name="worker-x").result()
    note = "\n".join(err.value.__notes__)
    assert "raised in the forked process worker-x" in note and "_raise" in note


def test_an_exception_that_does_not_pickle_arrives_as_its_traceback():
    with pytest.raises(RuntimeError, match=r"(?s)in the forked process.*lost on the way"):
        ForkedCall(_raise, "unpicklable").result()


def test_a_process_that_dies_without_a_result_is_an_error_naming_its_exit_code():
    with pytest.raises(RuntimeError, match=r"ended without a result \(exit code -9\)"):
        ForkedCall(_die).result()


def test_cancel_stops_the_call_at_once():
    call = ForkedCall(time.sleep, 30.0)
    t0 = time.monotonic()
    call.cancel()
    assert time.monotonic() - t0 < 5.0 and multiprocessing.active_children() == []


def _report_can_fork(queue) -> None:
    queue.put(can_fork())


def test_a_daemonic_process_may_not_fork():
    """Daemonic processes (a sweep's workers) may not have children: callers work in place there."""
    ctx = multiprocessing.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_report_can_fork, args=(queue,), daemon=True)
    proc.start()
    assert queue.get(timeout=60) is False
    proc.join()
