"""A ``fisc-sim emulate`` killed -9 takes its worker processes with it (issue 38's faults): a daemon
worker would otherwise outlive it and fly its vehicles, and publish their telemetry, to the end of
the run."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sim.emulate.workers import ParentWatch

ROOT = Path(__file__).resolve().parents[2]


def test_parent_watch_tells_the_parent_that_started_it_from_another():
    assert not ParentWatch().gone()
    assert not ParentWatch(os.getppid()).gone()
    assert ParentWatch(os.getppid() + 1).gone()  # re-parented: the pid it started with is not its parent


def _children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` (Linux /proc)."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(d.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc to find the workers")
def test_workers_of_an_emulate_killed_9_stop_within_seconds(tmp_path):
    err = tmp_path / "emulate.err"
    with open(err, "w") as fh:
        proc = subprocess.Popen([sys.executable, "-m", "sim.cli", "emulate", "--agents", "2", "--duration", "120",
                                 "-o", str(tmp_path / "out"), "--no-compare", "--no-figures"],
                                cwd=ROOT, stdout=subprocess.DEVNULL, stderr=fh)
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and "vehicles launched" not in err.read_text():  # flying: in the run's loop
            assert proc.poll() is None, err.read_text()[-2000:]
            time.sleep(0.2)
        workers = [c for c in _children(proc.pid) if "multiprocessing" in
                   (Path("/proc") / str(c) / "cmdline").read_bytes().decode(errors="replace")]
        assert len(workers) >= 2, (workers, err.read_text()[-2000:])  # an emulator and an agent worker
        time.sleep(2.0)
        assert all(_alive(w) for w in workers)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        t_kill = time.monotonic()
        while time.monotonic() - t_kill < 10 and any(_alive(w) for w in workers):
            time.sleep(0.1)
        left = [w for w in workers if _alive(w)]
        assert not left, f"workers {left} still running 10 s after their emulate was killed"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
