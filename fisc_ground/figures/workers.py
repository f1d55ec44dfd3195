"""Render a run's independent figures on two processes.

A run writes about ten matplotlib figures, each a few tenths of a second of single-threaded
drawing; on a 2-core machine a second process (``fisc_ground.figures.forked``) halves that wall time.
Both processes take the next job from one shared counter, so a slow figure does not leave a core
idle.  Without ``fork`` the jobs run one after the other here; the files are the same either way.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Mapping
from pathlib import Path

from fisc_ground.figures.forked import ForkedCall, can_fork

FigureJob = Callable[[], Path]
"""Draws one figure, writes it and returns its path."""


def _take_jobs(jobs: Mapping[str, FigureJob], names: list[str], counter) -> dict[str, Path]:
    """Run jobs ``names[counter]`` (the counter shared with the other process) until none is left."""
    done: dict[str, Path] = {}
    while True:
        with counter.get_lock():
            k = counter.value
            counter.value += 1
        if k >= len(names):
            return done
        done[names[k]] = jobs[names[k]]()


def render_figures(jobs: Mapping[str, FigureJob], parallel: bool = True) -> dict[str, Path]:
    """Run every job once (in ``jobs``' order, heaviest first balances best); name -> path.

    With ``parallel`` (and ``can_fork``) a forked process shares the jobs: this process draws the
    first job, the forked one starts on the second, and then each takes the next one left.  A job
    that fails in either process raises here."""
    names = list(jobs)
    if not (parallel and len(names) > 1 and can_fork()):
        return {n: jobs[n]() for n in names}
    counter = multiprocessing.get_context("fork").Value("i", 1)
    other = ForkedCall(_take_jobs, jobs, names, counter, name="fisc-figures")
    try:
        paths = {names[0]: jobs[names[0]]()}
        paths.update(_take_jobs(jobs, names, counter))
    except BaseException:
        other.cancel()
        raise
    paths.update(other.result())
    return {n: paths[n] for n in names}
