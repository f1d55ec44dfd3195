"""Zero-config lab discovery: how long until ``fisc-ground monitor`` hears every agent of
``fisc-sim emulate --swarm`` started beside it, with no publish and no config file.

    python benchmarks/bench_discovery.py               # 20 agents, both start orders
    python benchmarks/bench_discovery.py --agents 50 --gap 2

For each order (monitor first, emulate first) both processes are started ``--gap`` seconds
apart, on a free lab port (``FISC_ZENOH_PORT``; never 7447, which may be in use); the monitor
records (``--record``) and the receive time of each agent's first message is read back.
Printed: agents heard, and the time from the first launch until the first and the last agent
was heard.  The issue's target: all 20 within 10 s.  Most of that time is the emulation's own
start (map, launch plan, spawning its emulator and agent processes), not discovery.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fisc_agent.zenoh.session import PORT_ENV  # noqa: E402
from fisc_ground.monitor.recording import iter_messages, read_recording  # noqa: E402
from tests.ports import free_tcp_port as free_port  # noqa: E402


def one(order: tuple[str, str], agents: int, gap_s: float, window_s: float, work: Path) -> dict:
    """Start both processes in ``order``; returns agents heard and first/last heard [s after launch]."""
    env = {**os.environ, PORT_ENV: str(free_port())}
    rec = work / f"{order[0]}-first.mcap"
    argv = {
        "monitor": [sys.executable, "-m", "fisc_ground.cli", "monitor", "--swarm", "demo", "--duration",
                    str(window_s), "--record", str(rec)],  # the monitor's defaults otherwise
        "emulate": [sys.executable, "-m", "sim.cli", "emulate", "--agents", str(agents), "--duration",
                    str(window_s + 10), "--swarm", "demo", "--trusted-key", str(work / "ground.pub"), "-o",
                    str(work / f"emu-{order[0]}"), "--no-compare", "--no-figures", "-q"],
    }
    procs = {}
    t0 = time.time()
    try:
        for name in order:
            procs[name] = subprocess.Popen(argv[name], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            time.sleep(gap_s)
        procs["monitor"].wait(timeout=window_s + 60)
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.terminate()
                p.wait(timeout=30)
    first: dict[int, float] = {}
    for t, aid, _ in iter_messages(read_recording(rec)):
        first.setdefault(aid, t - t0)
    times = sorted(first.values())
    return {"heard": len(first), "first_s": times[0] if times else None, "all_s": times[-1] if times else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--agents", type=int, default=20)
    ap.add_argument("--gap", type=float, default=0.5, help="seconds between the two starts (default 0.5)")
    ap.add_argument("--window", type=float, default=20.0, help="monitor duration [s] (default 20)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        subprocess.run([sys.executable, "-m", "fisc_ground.cli", "keygen", "-o", str(work / "ground")], check=True,
                       capture_output=True)
        print(f"| order | agents heard | first heard | all {args.agents} heard |")
        print("|---|---|---|---|")
        for order in (("monitor", "emulate"), ("emulate", "monitor")):
            r = one(order, args.agents, args.gap, args.window, work)
            fmt = (lambda v: "-" if v is None else f"{v:.1f} s")
            print(f"| {order[0]} first | {r['heard']} / {args.agents} | {fmt(r['first_s'])} | "
                  f"{fmt(r['all_s']) if r['heard'] == args.agents else 'not all'} |", flush=True)


if __name__ == "__main__":
    main()
