"""``fisc_ground.figures.workers``: a run's figures shared by two processes, the same files either way."""

from __future__ import annotations

import multiprocessing
import os
import time
from functools import partial
from pathlib import Path

import pytest

from fisc_ground.figures.workers import render_figures
from fisc_ground.figures.forked import can_fork

needs_fork = pytest.mark.skipif(not can_fork(), reason="fork-based figure process not available here")


def _write(path: Path, text: str, delay_s: float = 0.0) -> Path:
    """A stand-in figure job: waits (a slow figure), writes its text and the pid that drew it."""
    time.sleep(delay_s)
    path.write_text(f"{text} {os.getpid()}")
    return path


def _fail(path: Path) -> Path:
    raise ValueError(f"no data for {path.name}")


def _jobs(tmp_path: Path, n: int, delay_s: float) -> dict:
    return {f"fig{i}": partial(_write, tmp_path / f"fig{i}.txt", f"figure {i}", delay_s) for i in range(n)}


@needs_fork
def test_two_processes_share_the_jobs_and_every_job_runs_once(tmp_path):
    paths = render_figures(_jobs(tmp_path, 8, 0.2))
    assert list(paths) == [f"fig{i}" for i in range(8)]  # the jobs' order, whoever drew them
    pids = set()
    for i in range(8):
        text, pid = paths[f"fig{i}"].read_text().split(" ")[-2:]
        assert paths[f"fig{i}"] == tmp_path / f"fig{i}.txt" and text == str(i)
        pids.add(int(pid))
    assert os.getpid() in pids and len(pids) == 2  # eight 0.2 s jobs: the forked process took some
    assert paths["fig0"].read_text().split(" ")[-1] == str(os.getpid())  # the first job is drawn here


def test_without_parallel_every_job_runs_here(tmp_path):
    paths = render_figures(_jobs(tmp_path, 3, 0.0), parallel=False)
    assert {p.read_text().split(" ")[-1] for p in paths.values()} == {str(os.getpid())}


@needs_fork
def test_a_job_failing_in_the_second_process_raises_here_with_its_traceback(tmp_path):
    # this process draws the first job, the forked one starts on the second
    jobs = {"slow": partial(_write, tmp_path / "slow.txt", "slow", 1.0), "bad": partial(_fail, tmp_path / "bad.png")}
    with pytest.raises(ValueError, match="no data for bad.png") as err:
        render_figures(jobs)
    assert any("raised in the forked process fisc-figures" in note for note in err.value.__notes__)
    assert (tmp_path / "slow.txt").exists()


@needs_fork
def test_a_job_failing_here_raises_its_own_error_and_stops_the_other_process(tmp_path):
    # the failing first job is drawn here while the forked process sleeps in the second
    jobs = {"bad": partial(_fail, tmp_path / "bad.png"), "slow": partial(_write, tmp_path / "slow.txt", "slow", 5.0)}
    t0 = time.monotonic()
    with pytest.raises(ValueError, match="no data for bad.png"):
        render_figures(jobs)
    assert time.monotonic() - t0 < 4.0  # the forked process was stopped, not waited for
    assert multiprocessing.active_children() == []
