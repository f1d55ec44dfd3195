"""The lab mesh without a hub (issue 38), with real processes and no config file: the process
holding the lab port leaves, and the others neither lose each other nor become invisible to a
``status`` started afterwards (``tests/zenoh/hub_exit.py``; 10 trials at 20 agents:
``benchmarks/bench_hub_exit.py``)."""

from __future__ import annotations

import signal
import subprocess
import sys

import pytest

from .hub_exit import Trial, run_trial

pytestmark = pytest.mark.slow

TRIALS = [
    pytest.param(Trial(agents=5, order=("z1", "monitor", "z2"), gap_s=0.0, kill_signal=signal.SIGKILL, pause_s=0.5),
                 id="monitor-then-z2-kill9-status-at-once"),
    pytest.param(Trial(agents=5, order=("z1", "z2", "monitor"), gap_s=0.5, kill_signal=signal.SIGTERM, pause_s=4.0),
                 id="z2-then-monitor-term-status-4s-later"),
    pytest.param(Trial(agents=5, order=("z1", "monitor", "z2"), gap_s=1.5, kill_signal=signal.SIGTERM, pause_s=1.5),
                 id="monitor-then-z2-term-status-1.5s-later"),
]


@pytest.fixture(scope="module")
def ground_pub(tmp_path_factory):
    d = tmp_path_factory.mktemp("mesh")
    subprocess.run([sys.executable, "-m", "fisc_ground.cli", "keygen", "-o", str(d / "ground")], check=True,
                   capture_output=True)
    return d / "ground.pub"


@pytest.mark.parametrize("trial", TRIALS)
def test_the_port_holder_leaves_and_nobody_is_lost(trial, ground_pub, tmp_path):
    (tmp_path / "ground.pub").write_bytes(ground_pub.read_bytes())
    out = run_trial(trial, tmp_path)
    assert out.listed == out.expected, out
    assert out.worst_gap_s < 3.0, out  # the monitor never had a z2 agent stale
    assert out.passed, out
