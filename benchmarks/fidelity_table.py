"""The fidelity table of docs/simulation.md, reproducibly (prints markdown; not a test).

    python benchmarks/fidelity_table.py                 # the full table (a few minutes on 2 cores)
    python benchmarks/fidelity_table.py --quick         # no collision rows
    python benchmarks/fidelity_table.py --jobs 2 --lookahead 0 0.5 --max-speed 2 5

Rows: reference (cd_nozzle_inviscid = the default map's reference, cd_nozzle = the RANS
reference) x case (2 = reservoir, 1 = seed) x mode (mean, slot) x collisions (off, on) x
look-ahead x speed limit, every other setting at the ``fisc-sim run`` defaults (1000 agents,
300 s reservoir averaged over the last 100 s, 20 s seeding averaged over the whole run,
seed 0).  Each map is fitted once per speed limit with the default fit settings.  The
paper's reported ranges are printed below the table.
"""

from __future__ import annotations

import argparse
import itertools
import time
from concurrent.futures import ProcessPoolExecutor

from sim.report import PAPER_FIGURES, compute_metrics
from sim.run import RunConfig, load_command_map, simulate

REFERENCES = ("cd_nozzle_inviscid", "cd_nozzle")
CASES = (("reservoir", "2 (reservoir)"), ("seed", "1 (seed)"))
MODES = ("mean", "slot")

HEADER = ("| reference | case | mode | v_max [m/s] | S | look-ahead [s] | collisions | nRMSE u | nRMSE P | "
          "nRMSE rho | r_P | r_rho | centreline u / P / rho | P_random nRMSE | rho_open nRMSE | CVs compared | "
          "alive (end) | escaped / injected | wall [s] |")


def _f(v, fmt=".3f") -> str:
    return "n/a" if v is None else format(v, fmt)


def one_row(args: tuple) -> str:
    """Simulate one configuration and format its markdown row."""
    ref, scenario, case, mode, collisions, lookahead, vmax = args
    cmap = load_command_map(ref, vmax)
    cfg = RunConfig(map=ref, scenario=scenario, mode=mode, collisions=collisions, lookahead_s=lookahead,
                    max_speed_m_s=vmax, figures=False)
    t0 = time.perf_counter()
    r = simulate(cfg, cmap)
    wall = time.perf_counter() - t0
    m = compute_metrics(r)
    a = m["agents"]
    return (f"| {ref} | {case} | {mode} | {vmax:g} | {r.scale:.3f} | {lookahead:g} | {'on' if collisions else 'off'} | "
            f"{_f(m['nrmse_velocity'])} | {_f(m['nrmse_pressure'])} | {_f(m['nrmse_density'])} | "
            f"{_f(m['pearson_pressure'], '.2f')} | {_f(m['pearson_density'], '.2f')} | "
            f"{_f(m['centreline_max_dev_velocity'], '.2f')} / {_f(m['centreline_max_dev_pressure'], '.2f')} / "
            f"{_f(m['centreline_max_dev_density'], '.2f')} | "
            f"{_f(m['other_pressures']['swarm_pressure_random']['nrmse_pressure'])} | "
            f"{_f(m['other_densities']['swarm_density_open_volume']['nrmse_density'])} | "
            f"{m['n_cv_compared']}/{m['n_cv']} | {a['alive']} | {a['escaped']}/{a['injected']} | {wall:.1f} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="skip the collision rows")
    ap.add_argument("--lookahead", type=float, nargs="+", default=[0.0, 0.5], help="look-ahead values [s]")
    ap.add_argument("--max-speed", type=float, nargs="+", default=[2.0], help="speed limits of the fitted maps [m/s]")
    ap.add_argument("--references", nargs="+", default=list(REFERENCES))
    ap.add_argument("--jobs", type=int, default=1, help="parallel processes")
    a = ap.parse_args(argv)
    rows = []
    for ref, (scenario, case), vmax, lookahead, mode, coll in itertools.product(
            a.references, CASES, a.max_speed, a.lookahead, MODES, (False,) if a.quick else (False, True)):
        rows.append((ref, scenario, case, mode, coll, lookahead, vmax))
    print(HEADER)
    print("|" + "---|" * HEADER.count(" | ") + "---|")
    if a.jobs > 1:
        with ProcessPoolExecutor(a.jobs) as ex:
            for line in ex.map(one_row, rows):
                print(line, flush=True)
    else:
        for row in rows:
            print(one_row(row), flush=True)
    print()
    print("Paper (Results and Discussion): " + "; ".join(f"{k} {v}" for k, v in PAPER_FIGURES.items()) + ".")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
