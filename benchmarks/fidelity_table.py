"""The fidelity table of docs/studies/fidelity.md, printed as markdown (not a test).

The table is the sweep spec ``benchmarks/fidelity_table.toml``; this script runs it through
``fisc-sim sweep``'s engine (``sim.sweep.spec``, ``sim.sweep.run``) and prints the rows::

    python benchmarks/fidelity_table.py --workers 2          # on a 2-worker dask LocalCluster
    python benchmarks/fidelity_table.py --workers 0          # serially in this process
    python benchmarks/fidelity_table.py --scenario seed
    fisc-sim sweep benchmarks/fidelity_table.toml -o out/fidelity   # the same runs: CSV + figures

``duct_b`` is a duct of our own from the analytic oracle (quasi-1-D isentropic flow with the
streamline-slope radial velocity) with a shape unlike the tunnel's: short converging part, throat
at x = 4 m, long diffuser to an outlet wider than the inlet (``duct_b_radius_m``).  Nothing in the
method is tuned to it.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

SPEC = Path(__file__).with_name("fidelity_table.toml")

HEADER = ("| reference | configuration | mode | look-ahead [s] | map schema | S | nRMSE u | nRMSE P | nRMSE rho | "
          "r_u | r_P | r_rho | realised/fitted spread (median) | CVs compared | escaped / injected | wall [s] |")


def duct_b_radius_m(x_m):
    """Our own test duct: R = 0.8 + 0.3 (1 + cos(pi x / 4)) for x <= 4 m (R(0) = 1.4 m, throat
    R(4) = 0.8 m), then R = 0.8 + 0.45 (1 - cos(pi (x - 4) / 8)) up to x = 12 m (R(12) = 1.7 m)."""
    x = np.asarray(x_m, dtype=float)
    return np.where(x <= 4.0, 0.8 + 0.3 * (1.0 + np.cos(np.pi * x / 4.0)),
                    0.8 + 0.45 * (1.0 - np.cos(np.pi * (np.minimum(x, 12.0) - 4.0) / 8.0)))


def duct_b_reference():
    """The ``duct_b`` reference field (a sweep-spec case: ``fidelity_table.py:duct_b_reference``)."""
    from fisc_ground.reference.analytic import analytic_nozzle

    return analytic_nozzle(duct_b_radius_m, length_m=12.0, inlet_velocity_m_s=3.0, name="duct_b")


def _f(v, fmt=".3f") -> str:
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def markdown_row(r: dict) -> str:
    """One row of the docs/studies/fidelity.md table from a sweep row."""
    ref = Path(str(r["map"]).split(":")[-1]).stem.removesuffix("_reference") if ".py:" in str(r["map"]) else r["map"]
    return (f"| {ref} | {r['configuration']} | {r['mode_flown']} | {r['lookahead_s_flown']:g} | {r['map_schema']} | "
            f"{r['scale']:.3f} | {_f(r['nrmse_velocity'])} | {_f(r['nrmse_pressure'])} | {_f(r['nrmse_density'])} | "
            f"{_f(r['pearson_velocity'], '.2f')} | {_f(r['pearson_pressure'], '.2f')} | "
            f"{_f(r['pearson_density'], '.2f')} | {_f(r['spread_ratio_median'], '.2f')} | {r['n_cv_compared']} | "
            f"{r['escaped']}/{r['injected']} | {r['wall_s']:.1f} |")


def main(argv: list[str] | None = None) -> int:
    from sim.sweep.spec import load_spec, run_serial, with_base

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", choices=("reservoir", "seed"), default="reservoir")
    ap.add_argument("--workers", type=int, default=2, help="dask LocalCluster workers (0: serial)")
    a = ap.parse_args(argv)
    spec = with_base(load_spec(SPEC), scenario=a.scenario)
    if a.workers > 0:
        from dask.distributed import Client

        from sim.sweep.run import local_cluster, run_distributed

        with local_cluster(a.workers) as cluster, Client(cluster) as client:
            rows = run_distributed(spec, client)
    else:
        rows = run_serial(spec)
    print(HEADER)
    print("|" + "---|" * HEADER.count(" | ") + "---|")
    for r in rows:
        print(markdown_row(r))
    print()
    print("Paper (Results and Discussion): velocity nRMSE 0.15-0.9, pressure 0-0.937, density 0.61-0.98.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
