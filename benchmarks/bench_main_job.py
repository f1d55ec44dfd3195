"""Wall time of the README's main job, ``fisc-sim run -o DIR`` (issue 9: under 10 s on 2 cores).

Runs the command as a user does (a fresh process each time): once cold (an empty numba cache, so
its kernels compile) and then ``--runs`` times warm, and prints each run's wall time with the
simulation loops' times (``metrics.json``: ``wall_time_s`` of the default run and of the paper
companion, which flies beside it in a forked process).  Then, in this process, the run's figures
drawn one after the other and on two processes (``fisc_ground.figures.workers``), alternately,
with their ratio.  The host's load moves all of these; compare numbers from one invocation.

``--baseline CHECKOUT`` times another source tree's main job too (``python -m sim.cli run`` with
that tree first on the path, this environment's packages), in pairs alternating with this one's,
and prints the median of the paired ratios: the way to tell a change from the host's drift.

    python benchmarks/bench_main_job.py            # 1 cold + 3 warm runs, 3 figure rounds
    git worktree add /tmp/base HEAD~1 && python benchmarks/bench_main_job.py --baseline /tmp/base --pairs 8
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _fisc_sim() -> list[str]:
    exe = Path(sys.executable).with_name("fisc-sim")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "sim.cli"]


def time_run(out: Path, env: dict[str, str], cmd: list[str] | None = None,
             cwd: Path | None = None) -> tuple[float, dict]:
    """Wall time of one ``fisc-sim run -o out`` (``cmd``: another tree's ``fisc-sim``) and its
    metrics.json."""
    t0 = time.perf_counter()
    subprocess.run((_fisc_sim() if cmd is None else cmd) + ["run", "-o", str(out)], env=env, cwd=cwd,
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0, json.loads((out / "metrics.json").read_text())


def _baseline_sim(checkout: Path) -> tuple[list[str], dict[str, str]]:
    """The command and environment of ``fisc-sim`` from the source tree ``checkout``."""
    if not (checkout / "sim" / "cli.py").is_file():
        raise SystemExit(f"--baseline {checkout}: no sim/cli.py there (a checkout of this repository?)")
    path = os.pathsep.join([str(checkout), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return [sys.executable, "-m", "sim.cli"], {"PYTHONPATH": path}


def time_pairs(checkout: Path, pairs: int, tmp: Path) -> None:
    """``pairs`` runs each of the baseline's and this tree's main job, alternating (after one
    untimed run of each, which fills their numba caches); prints each pair and the medians."""
    base_cmd, base_env = _baseline_sim(checkout)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp / "numba-cache"))
    benv = dict(env, NUMBA_CACHE_DIR=str(tmp / "numba-cache-baseline"), **base_env)
    here = _fisc_sim()

    def one(cmd: list[str], run_env: dict[str, str], out: Path) -> tuple[float, float]:
        wall, metrics = time_run(out, run_env, cmd, cwd=tmp)
        return wall, metrics["wall_time_s"]

    one(base_cmd, benv, tmp / "warm-base")
    one(here, env, tmp / "warm-here")
    base, mine = [], []
    for k in range(pairs):
        base.append(one(base_cmd, benv, tmp / f"base{k}"))
        mine.append(one(here, env, tmp / f"here{k}"))
        print(f"pair {k}: baseline {base[-1][0]:5.2f} s (loop {base[-1][1]:.2f} s), "
              f"this tree {mine[-1][0]:5.2f} s (loop {mine[-1][1]:.2f} s)", flush=True)
    for i, what in ((0, "wall"), (1, "simulation loop")):
        ratio = statistics.median(m[i] / b[i] for b, m in zip(base, mine))
        print(f"{what}: baseline median {statistics.median(b[i] for b in base):.2f} s, this tree "
              f"{statistics.median(m[i] for m in mine):.2f} s; median paired ratio {ratio:.2f}")


def time_figures(rounds: int) -> tuple[list[float], list[float]]:
    """Serial and two-process wall times of one run's figures, alternating."""
    from fisc_ground.figures.field_figures import write_run_figures
    from sim.run import RunConfig, run

    with tempfile.TemporaryDirectory() as tmp:
        res = run(RunConfig(out_dir=tmp, figures=False))
        serial, parallel = [], []
        for _ in range(rounds):
            for flag, into in ((False, serial), (True, parallel)):
                t0 = time.perf_counter()
                write_run_figures(res.field_run, Path(tmp), parallel=flag)
                into.append(time.perf_counter() - t0)
    return serial, parallel


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3, help="warm runs after the cold one (default 3)")
    ap.add_argument("--figure-rounds", type=int, default=3, help="serial/parallel figure rounds (default 3)")
    ap.add_argument("--baseline", type=Path, metavar="CHECKOUT",
                    help="a checkout of this repository (e.g. a git worktree of an older commit): time "
                         "its main job too, alternating with this one's, and print the paired ratios")
    ap.add_argument("--pairs", type=int, default=6, help="alternating run pairs with --baseline (default 6)")
    args = ap.parse_args()
    if args.baseline is not None:
        with tempfile.TemporaryDirectory() as tmp:
            time_pairs(args.baseline.resolve(), args.pairs, Path(tmp))
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, NUMBA_CACHE_DIR=str(Path(tmp) / "numba-cache"))
        rows = []
        for k in range(1 + args.runs):
            wall, m = time_run(Path(tmp) / f"run{k}", env)
            paper = m.get("paper_preset", {}).get("wall_time_s")
            rows.append(wall)
            print(f"{'cold' if k == 0 else 'warm'} run {k}: {wall:5.2f} s wall; simulation loop {m['wall_time_s']:.2f} s"
                  + (f" + paper companion {paper:.2f} s" if paper is not None else ""), flush=True)
        if args.runs:
            print(f"warm median {statistics.median(rows[1:]):.2f} s, cold {rows[0]:.2f} s (aim: under 10 s)")
    serial, parallel = time_figures(args.figure_rounds)
    print(f"figures: serial median {statistics.median(serial):.2f} s, two processes {statistics.median(parallel):.2f} s"
          f" (ratio {statistics.median(parallel) / statistics.median(serial):.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
