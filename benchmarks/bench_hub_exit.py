"""The issue-38 hub-exit sequence, 10 times with varied start orders and timings.

    python benchmarks/bench_hub_exit.py                  # 10 trials, 20 agents per emulation
    python benchmarks/bench_hub_exit.py --trials 3 --agents 5

Each trial (``tests/zenoh/hub_exit.py``): ``fisc-sim emulate --swarm z1`` takes the lab port,
``fisc-ground monitor --swarm z2`` and ``fisc-sim emulate --swarm z2`` join, z1 is killed
(SIGTERM or SIGKILL), and ``fisc-ground status --swarm z2`` (its default 2 s window) must list
every z2 agent while the monitor never has one silent for 3 s; the status's wall time is
reported beside (the issue asks for 5 s).  One line per trial, then one summary line.
"""

from __future__ import annotations

import argparse
import random
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.zenoh.hub_exit import Trial, run_trial  # noqa: E402

ORDERS = (("z1", "monitor", "z2"), ("z1", "z2", "monitor"))


def trials(count: int, agents: int, seed: int) -> list[Trial]:
    """``count`` trials cycling start orders and kill signals, with random gaps and pauses."""
    rng = random.Random(seed)
    return [Trial(agents=agents, order=ORDERS[i % 2], gap_s=rng.choice((0.0, 0.5, 2.0)),
                  kill_signal=(signal.SIGTERM, signal.SIGKILL)[(i // 2) % 2], pause_s=rng.uniform(0.5, 10.0))
            for i in range(count)]


def main() -> int:
    """Run the trials; exit 0 when every one passed."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=10)
    ap.add_argument("--agents", type=int, default=20)
    ap.add_argument("--seed", type=int, default=38)
    args = ap.parse_args()
    passed, times = 0, []
    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        subprocess.run([sys.executable, "-m", "fisc_ground.cli", "keygen", "-o", str(work / "ground")], check=True,
                       capture_output=True)
        for i, t in enumerate(trials(args.trials, args.agents, args.seed)):
            (work / str(i)).mkdir()
            (work / str(i) / "ground.pub").write_bytes((work / "ground.pub").read_bytes())
            o = run_trial(t, work / str(i))
            passed += o.passed
            times.append(o.status_s)
            print(f"trial {i}: order {'/'.join(t.order)} gap {t.gap_s:g} s, {signal.Signals(t.kill_signal).name}, "
                  f"status {t.pause_s:.1f} s later: listed {o.listed}/{o.expected} in {o.status_s:.1f} s, "
                  f"monitor's worst silence {o.worst_gap_s:.1f} s -> {'ok' if o.passed else 'FAIL'} {o.detail}",
                  flush=True)
    count = len(times)
    asked = [t for t in times if t == t] or [float("nan")]  # NaN: no status was asked (set-up failed)
    fast = sum(t <= 5.0 for t in asked)
    print(f"hub exit: {passed}/{count} passed, status took {min(asked):.1f}-{max(asked):.1f} s "
          f"(within 5 s: {fast}/{count}; {args.agents} agents per emulation)")
    return 0 if passed == count else 1


if __name__ == "__main__":
    sys.exit(main())
