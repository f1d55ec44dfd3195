"""``fisc-sim sweep SPEC.toml -o DIR``: argument parsing and progress for ``sim.sweep.run`` (thin)."""

from __future__ import annotations

import argparse
import logging
import os
import sys

from fisc_agent.common.cli_common import EXIT_FAILURE, EXIT_OK, EXIT_USAGE, add_output_arg, sig3


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``sweep`` on the ``fisc-sim`` subparsers; returns the new parser."""
    p = subparsers.add_parser(
        "sweep", help="a grid of run configurations on dask.distributed: one table, one figure per metric",
        description="Run every point of SPEC's grid (maps or CFD cases x fit settings x modes x seeds; "
                    "sim.sweep.spec documents the TOML) as one dask task each, on a LocalCluster or any dask "
                    "scheduler, and write results.csv (one row per run), one PNG per metric and sweep.json. "
                    "benchmarks/fidelity_table.toml is the fidelity table of docs/studies/fidelity.md.")
    p.add_argument("spec", metavar="SPEC.toml", help="sweep spec (TOML)")
    add_output_arg(p, required=True, metavar="DIR", help="output directory")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="address of a running dask scheduler (e.g. tcp://head:8786, or a dask-jobqueue "
                        "cluster's); default: a LocalCluster on this machine")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="LocalCluster worker processes (default: the CPU count)")
    p.add_argument("--serial", action="store_true", help="no dask: run the points one after the other here")
    p.add_argument("--parquet", action="store_true", help="also write results.parquet (needs pandas, pyarrow)")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``fisc-sim sweep``; prints a one-line summary; returns the exit code."""
    from sim.sweep.spec import METRICS, SweepSpecError, load_spec, run_serial
    from sim.sweep.run import local_cluster, run_distributed, write_outputs

    try:
        spec = load_spec(args.spec)
    except (OSError, SweepSpecError) as exc:
        print(f"fisc-sim sweep: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if args.workers is not None and args.workers < 1:
        print("fisc-sim sweep: error: --workers must be >= 1", file=sys.stderr)
        return EXIT_USAGE
    if args.parquet:  # fail before the runs, not after them
        try:
            import pandas  # noqa: F401
            import pyarrow  # noqa: F401
        except ImportError as exc:
            print(f"fisc-sim sweep: error: --parquet needs pandas and pyarrow ({exc.name} is missing): "
                  "pip install pandas pyarrow", file=sys.stderr)
            return EXIT_FAILURE
    n = len(spec.points())
    show = not getattr(args, "quiet", 0)
    settings = {"scheduler": args.scheduler or ("serial" if args.serial else "LocalCluster")}
    try:
        if args.serial:
            rows = run_serial(spec)
        else:
            from dask.distributed import Client

            if logging.getLogger().getEffectiveLevel() > logging.DEBUG:  # dask's INFO chatter only with -v
                logging.getLogger("distributed").setLevel(logging.WARNING)

            cluster = None if args.scheduler else local_cluster(args.workers or os.cpu_count() or 1)
            with Client(args.scheduler or cluster) as client:
                settings["workers"] = len(client.scheduler_info()["workers"])
                rows = run_distributed(spec, client, _bar(n) if show else None)
            if cluster is not None:
                cluster.close()
    except (ValueError, OSError) as exc:  # a map or reference a point names that fails its checks
        print(f"\nfisc-sim sweep: error: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    paths = write_outputs(spec, rows, args.output, parquet=args.parquet, figures=not args.no_figures,
                          settings=settings)
    best = min(rows, key=lambda r: r["nrmse_velocity"] if r["nrmse_velocity"] == r["nrmse_velocity"] else 9e9)
    print(f"wrote {paths['table']}: {len(rows)} runs, {len(METRICS)} metrics; lowest velocity nRMSE "
          f"{sig3(best['nrmse_velocity'])} (run {best['index']}); {sig3(sum(r['wall_s'] for r in rows))} s of runs")
    return EXIT_OK


def _bar(total: int):
    """A one-line text progress bar on stderr."""

    def update(done: int, _total: int) -> None:
        width = 30
        fill = int(width * done / max(total, 1))
        tty = sys.stderr.isatty()
        end = "\n" if done == total or not tty else ""
        start = "\r" if tty else ""
        print(f"{start}sweep [{'#' * fill}{'.' * (width - fill)}] {done}/{total} runs", end=end,
              file=sys.stderr, flush=True)

    return update
