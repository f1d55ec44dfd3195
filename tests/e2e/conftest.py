"""Helpers for the end-to-end tests that run the real console scripts as separate processes.

Everything here is about *running* processes safely, not about FISC itself:

- ``free_tcp_port`` / ``free_udp_port``: loopback ports the OS reports free;
- ``write_zenoh_config``: a standard Zenoh JSON5 file (peer mode, multicast scouting off,
  explicit loopback endpoints), as docs/zenoh.md describes;
- ``cli``: the argv of an installed console script (``fisc-agent``, ``fisc-ground``,
  ``fisc-sim``) next to the running interpreter, or ``python -m`` its module;
- ``Processes``: starts long-running processes each in its own session (process group), logs
  stdout+stderr to a file per process, and kills whole process groups on ``stop_all`` (SIGTERM,
  then SIGKILL).  Every instance is also registered for an ``atexit`` sweep, and on Linux each
  child gets SIGKILL when the test process dies (PR_SET_PDEATHSIG), so an interrupted or killed
  run leaks nothing;
- ``run_cli``: a short-lived command with a timeout (killed on expiry), output captured;
- ``poll``: the only waiting primitive (no fixed sleeps where a condition can be polled).
"""

from __future__ import annotations

import atexit
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import pytest

from ..ports import free_tcp_port, free_udp_port  # noqa: F401 (the e2e tests import them from here)

_MODULES = {"fisc-agent": "fisc_agent.cli", "fisc-ground": "fisc_ground.cli", "fisc-sim": "sim.cli"}


def write_zenoh_config(path: Path, listen: list[str], connect: list[str]) -> Path:
    """A standard Zenoh JSON5 config: peer mode, multicast scouting off, explicit endpoints."""
    body = json.dumps({"mode": "peer", "listen": {"endpoints": listen}, "connect": {"endpoints": connect},
                       "scouting": {"multicast": {"enabled": False}}}, indent=2)
    path.write_text(f"// FISC e2e test config ({path.name}): peer mode on loopback, no multicast\n{body}\n")
    return path


def cli(name: str) -> list[str]:
    """argv prefix of an installed console script (falls back to ``python -m module``)."""
    script = Path(sys.executable).parent / name
    if script.is_file() and os.access(script, os.X_OK):
        return [str(script)]
    return [sys.executable, "-m", _MODULES[name]]


def child_env() -> dict[str, str]:
    """Environment of the children: unbuffered output so the logs are complete at any time."""
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def run_cli(argv: list[Any], timeout_s: float = 60.0, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """Run a short command to completion (killed after ``timeout_s``), output captured as text."""
    return subprocess.run([str(a) for a in argv], capture_output=True, text=True, timeout=timeout_s, cwd=cwd,
                          env=child_env())


def poll(pred: Callable[[], Any], timeout_s: float, period_s: float = 0.1) -> Any:
    """Call ``pred`` until it returns something truthy (returned) or ``timeout_s`` passes (None)."""
    end = time.monotonic() + timeout_s
    while True:
        value = pred()
        if value:
            return value
        if time.monotonic() >= end:
            return None
        time.sleep(period_s)


@dataclass
class Proc:
    """One long-running child process."""

    name: str
    argv: list[str]
    popen: subprocess.Popen
    log_path: Path
    started_s: float = field(default_factory=time.monotonic)

    @property
    def alive(self) -> bool:
        return self.popen.poll() is None

    def log_tail(self, lines: int = 25) -> str:
        try:
            text = self.log_path.read_text(errors="replace")
        except OSError:
            return "(no log)"
        return "\n".join(text.splitlines()[-lines:])


_LIVE: list["Processes"] = []


class Processes:
    """Long-running children, each in its own process group, killed as groups on ``stop_all``."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.procs: list[Proc] = []
        _LIVE.append(self)

    def start(self, name: str, argv: list[Any], cwd: Path | None = None) -> Proc:
        argv = [str(a) for a in argv]
        log_path = self.log_dir / f"{name}.log"
        with open(log_path, "wb") as log:
            log.write(("$ " + " ".join(argv) + "\n").encode())
            log.flush()
            popen = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                     cwd=cwd, env=child_env(), start_new_session=True,
                                     preexec_fn=_die_with_parent)
        proc = Proc(name, argv, popen, log_path)
        self.procs.append(proc)
        return proc

    def stop(self, proc: Proc, timeout_s: float = 8.0) -> int | None:
        """SIGTERM the process group, wait, then SIGKILL it; returns the exit code."""
        if proc.alive:
            _signal_group(proc.popen.pid, signal.SIGTERM)
            try:
                proc.popen.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                pass
        _signal_group(proc.popen.pid, signal.SIGKILL)  # stragglers in the group, if any
        try:
            return proc.popen.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            return None

    def stop_all(self, order: Callable[[Proc], int] | None = None) -> None:
        """Stop every child: SIGTERM to whole batches at once (batches by ascending ``order``
        rank; one batch without it), wait up to 8 s, SIGKILL what is left of each group, reap."""
        batches: dict[int, list[Proc]] = {}
        for p in self.procs:
            batches.setdefault(order(p) if order else 0, []).append(p)
        for _, batch in sorted(batches.items()):
            for p in batch:
                if p.alive:
                    _signal_group(p.popen.pid, signal.SIGTERM)
            end = time.monotonic() + 8.0
            for p in batch:
                try:
                    p.popen.wait(timeout=max(0.1, end - time.monotonic()))
                except subprocess.TimeoutExpired:
                    pass
                _signal_group(p.popen.pid, signal.SIGKILL)
                try:
                    p.popen.wait(timeout=5.0)
                except subprocess.TimeoutExpired:
                    pass
        if self in _LIVE:
            _LIVE.remove(self)

    def dead(self) -> list[Proc]:
        """Children that exited (none should while a test runs)."""
        return [p for p in self.procs if not p.alive]

    def report(self, lines: int = 15) -> str:
        """Every child's state and log tail (for assertion messages)."""
        out = []
        for p in self.procs:
            rc = p.popen.poll()
            out.append(f"--- {p.name} ({'running' if rc is None else f'exited {rc}'}) {p.log_path}\n"
                       f"{p.log_tail(lines)}")
        return "\n".join(out)


def _die_with_parent() -> None:
    """In the child before exec (Linux): SIGKILL it if the test process dies without cleaning
    up (e.g. itself SIGKILLed), since its own session escapes the terminal's signals."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _signal_group(pid: int, sig: int) -> None:
    try:
        os.killpg(pid, sig)  # start_new_session: the child leads its own group (pgid == pid)
    except (ProcessLookupError, PermissionError):
        pass


@atexit.register
def _sweep() -> None:
    """Last resort (interrupted run): kill every group still registered."""
    for procs in list(_LIVE):
        for p in procs.procs:
            _signal_group(p.popen.pid, signal.SIGKILL)


@pytest.fixture()
def processes(tmp_path):
    """Function-scoped ``Processes`` (logs in tmp_path/logs); all groups killed at teardown."""
    procs = Processes(tmp_path / "logs")
    yield procs
    procs.stop_all()
