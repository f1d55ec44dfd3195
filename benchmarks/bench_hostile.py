"""Issue 12 acceptance run: a flying agent under 10 oversized chunk headers per second.

    python benchmarks/bench_hostile.py                # 30 s flood (the issue's numbers)
    python benchmarks/bench_hostile.py --seconds 60

Runs ``tests/hostile/test_agent_under_attack.py::test_oversized_chunk_headers_cost_no_memory_and_no_setpoints``
with ``FISC_HOSTILE_FLOOD_S`` set: real ``fisc-agent`` and ``fisc-sim autopilot`` processes, a
real Zenoh session, and a UDP relay in front of the emulator that timestamps every setpoint.
Each flood message is 83 bytes: a chunk header claiming a 2^30-byte map of a newer and newer
``map_version`` plus 11 bytes.  Prints (and writes with ``--json``) the agent's resident
memory before and at its peak, and the setpoints the emulator received (mean per second,
fewest in any whole second, longest gap).  Pass: memory < +50 MB, >= 19 setpoints/s.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TEST = "tests/hostile/test_agent_under_attack.py::test_oversized_chunk_headers_cost_no_memory_and_no_setpoints"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=30.0, help="flood duration [s]")
    p.add_argument("--json", type=Path, help="also write the numbers to this file")
    a = p.parse_args(argv)
    env = dict(os.environ, FISC_HOSTILE_FLOOD_S=str(a.seconds))
    timeout = int(a.seconds) + 120
    out = subprocess.run([sys.executable, "-m", "pytest", "-q", "-s", "-p", "no:cacheprovider",
                          "-o", f"timeout={timeout}", TEST], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=timeout + 60)
    m = re.search(r"chunk flood: (\{.*\})", out.stdout)
    if m is None:
        print(out.stdout[-4000:], out.stderr[-2000:], sep="\n")
        return 1
    numbers = ast.literal_eval(m.group(1))
    numbers["rss_delta_mb"] = round(numbers["rss_peak_mb"] - numbers["rss_before_mb"], 1)
    numbers["passed"] = out.returncode == 0
    print(json.dumps(numbers, indent=1))
    if a.json:
        a.json.write_text(json.dumps(numbers, indent=1) + "\n")
    return 0 if out.returncode == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
