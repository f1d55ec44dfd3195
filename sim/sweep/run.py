"""``fisc-sim sweep``: a sweep spec's grid on ``dask.distributed``, then the table and the figures.

``run_distributed(spec, client)`` submits one ``sim.sweep.spec.run_point`` task per grid point to a dask
client (a ``LocalCluster`` by default, any scheduler with ``--scheduler ADDRESS``; for SLURM/PBS
start a ``dask_jobqueue`` cluster and pass its scheduler address, see docs/simulation.md) and
returns the rows in grid order.  ``write_outputs`` writes ``results.csv`` (one row per run;
``results.parquet`` too when asked and pandas/pyarrow are installed), one PNG per metric and
``sweep.json`` (spec and settings).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import tempfile
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sim.sweep.spec import METRICS, SweepSpec, run_point

log = logging.getLogger(__name__)


def local_cluster(workers: int):
    """A ``LocalCluster`` of ``workers`` single-threaded processes (scheduler and dashboard on ephemeral ports)."""
    from dask.distributed import LocalCluster

    return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                        scheduler_port=0)


def run_distributed(spec: SweepSpec, client, progress: Callable[[int, int], None] | None = None) -> list[dict]:
    """Every point of ``spec`` as a dask task on ``client``; rows in grid order.

    ``progress(done, total)`` is called as tasks finish.  A failing point raises its exception
    (the remaining tasks are cancelled).
    """
    from dask.distributed import as_completed

    points = spec.points()
    futures = [client.submit(run_point, p, key=f"fisc-sweep-{p.index}-{os.getpid()}-{id(spec)}", pure=False)
               for p in points]
    rows: dict[int, dict] = {}
    try:
        for done, fut in enumerate(as_completed(futures), start=1):
            row = fut.result()
            rows[row["index"]] = row
            if progress is not None:
                progress(done, len(points))
    finally:
        client.cancel([f for f in futures if not f.done()])
    return [rows[p.index] for p in points]


def _atomic_text(path: Path, write: Callable[[Any], None]) -> Path:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", newline="") as fh:
            write(fh)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise
    return path


def write_csv(rows: list[dict], path: Path) -> Path:
    """The tidy table as CSV (columns of the first row; NaN written as ``nan``)."""
    columns = list(rows[0]) if rows else ["index"]

    def write(fh):
        w = csv.DictWriter(fh, fieldnames=columns)
        w.writeheader()
        w.writerows(rows)

    return _atomic_text(path, write)


def write_parquet(rows: list[dict], path: Path) -> Path:
    """The tidy table as Parquet (needs pandas and pyarrow)."""
    import pandas as pd

    tmp = path.with_name(f".{path.name}.tmp")
    pd.DataFrame(rows).to_parquet(tmp, index=False)
    os.replace(tmp, path)
    return path


def varying_dimensions(spec: SweepSpec) -> list[str]:
    """Grid dimensions with more than one value."""
    return [name for name, values in spec.grid if len(values) > 1]


def write_metric_figures(spec: SweepSpec, rows: list[dict], out: Path) -> dict[str, Path]:
    """One PNG per metric: a bar per configuration (mean over seeds, min-max whiskers)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dims = [d for d in varying_dimensions(spec) if d != "seed"]
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for row in rows:
        groups[tuple(row[d] for d in dims)].append(row)
    labels = [" / ".join(str(v) for v in key) or "all" for key in groups]
    paths = {}
    for metric in METRICS:
        values = [[float(r[metric]) for r in members] for members in groups.values()]
        mean = [sum(v) / len(v) if all(math.isfinite(x) for x in v) else math.nan for v in values]
        lo = [m - min(v) if math.isfinite(m) else 0.0 for m, v in zip(mean, values)]
        hi = [max(v) - m if math.isfinite(m) else 0.0 for m, v in zip(mean, values)]
        fig, ax = plt.subplots(figsize=(7.0, 0.6 + 0.35 * len(labels)))
        ax.barh(range(len(labels)), [0.0 if not math.isfinite(m) else m for m in mean], xerr=[lo, hi],
                color="tab:blue", ecolor="0.3", capsize=2)
        ax.set_yticks(range(len(labels)), labels, fontsize=8)
        ax.invert_yaxis()
        ax.set_xlabel(metric)
        ax.set_title(f"{metric} by {' / '.join(dims) or 'run'}", fontsize=9)
        fig.tight_layout()
        path = out / f"{metric}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths[metric] = path
    return paths


def write_outputs(spec: SweepSpec, rows: list[dict], out: str | Path, *, parquet: bool = False,
                  figures: bool = True, settings: dict | None = None) -> dict[str, Path]:
    """``results.csv`` (+ ``results.parquet``), one figure per metric, ``sweep.json``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"table": write_csv(rows, out / "results.csv")}
    if parquet:
        paths["parquet"] = write_parquet(rows, out / "results.parquet")
    if figures and rows:
        paths.update(write_metric_figures(spec, rows, out))
    info = {"spec": str(spec.path) if spec.path else None, "base": spec.base, "base_fit": spec.base_fit,
            "grid": {name: list(values) for name, values in spec.grid}, "runs": len(rows), **(settings or {})}
    paths["sweep"] = _atomic_text(out / "sweep.json", lambda fh: json.dump(info, fh, indent=2, default=str))
    return paths
