"""The fidelity table of docs/simulation.md, reproducibly (prints markdown; not a test).

    python benchmarks/fidelity_table.py --jobs 2                      # presets x references (~1 min)
    python benchmarks/fidelity_table.py --jobs 2 --modes slot:0.5 staggered:0.5 kinetic:0.5
    python benchmarks/fidelity_table.py --scenario seed

Rows: reference x configuration, Case 2 (reservoir) unless ``--scenario seed``, every other
setting at the ``fisc-sim run`` defaults (1000 agents, 300 s averaged over the last 100 s, seed 0,
maps fitted with a 2 m/s speed limit).  Configurations: ``paper`` = ``--preset paper`` (schema-1
map, Algorithm 1: mean commands, no look-ahead), ``default`` = the default schema-2 map flown with
its recommended settings, and any ``MODE:LOOKAHEAD`` given with ``--modes`` (flown on the
schema-2 map).  References: the two shipped CFD solutions and ``duct_b``, a duct of our own from
the analytic oracle (quasi-1-D isentropic flow with the streamline-slope radial velocity) with a
shape unlike the tunnel's: short converging part, throat at x = 4 m, long diffuser to an outlet
wider than the inlet (``duct_b_radius_m``).  Nothing in the method is tuned to it.
"""

from __future__ import annotations

import argparse
import math
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from sim.report import compute_metrics
from sim.run import RunConfig, load_command_map, simulate

REFERENCES = ("cd_nozzle_inviscid", "cd_nozzle", "duct_b")
MAX_SPEED_M_S = 2.0

HEADER = ("| reference | configuration | mode | look-ahead [s] | map schema | S | nRMSE u | nRMSE P | nRMSE rho | "
          "r_u | r_P | r_rho | realised/fitted spread (median) | CVs compared | escaped / injected | wall [s] |")


def duct_b_radius_m(x_m):
    """Our own test duct: R = 0.8 + 0.3 (1 + cos(pi x / 4)) for x <= 4 m (R(0) = 1.4 m, throat
    R(4) = 0.8 m), then R = 0.8 + 0.45 (1 - cos(pi (x - 4) / 8)) up to x = 12 m (R(12) = 1.7 m)."""
    x = np.asarray(x_m, dtype=float)
    return np.where(x <= 4.0, 0.8 + 0.3 * (1.0 + np.cos(np.pi * x / 4.0)),
                    0.8 + 0.45 * (1.0 - np.cos(np.pi * (np.minimum(x, 12.0) - 4.0) / 8.0)))


def command_map(ref: str, preset: str):
    """The map a run of ``preset`` flies on reference ``ref`` (duct_b is built from the oracle)."""
    if ref != "duct_b":
        return load_command_map(ref, MAX_SPEED_M_S, preset)
    from fisc_agent.mapfile import decode_map
    from fisc_ground.mapbuild import FitConfig, build_map
    from fisc_agent.mapfile import encode_map
    from fisc_ground.reference.analytic import analytic_nozzle

    field = analytic_nozzle(duct_b_radius_m, length_m=12.0, inlet_velocity_m_s=3.0, name="duct_b")
    meta, arrays = build_map(field, FitConfig(max_speed_m_s=MAX_SPEED_M_S, staggered=preset != "paper"))
    return decode_map(encode_map(meta, arrays), source="duct_b")


def _f(v, fmt=".3f") -> str:
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def one_row(args: tuple) -> str:
    """Simulate one configuration and format its markdown row."""
    ref, label, scenario = args
    preset = "paper" if label == "paper" else "default"
    mode, lookahead = (None, None)
    if ":" in label:
        mode, la = label.split(":")
        lookahead = float(la)
    cmap = command_map(ref, preset)
    cfg = RunConfig(scenario=scenario, preset=preset, mode=mode, lookahead_s=lookahead, figures=False)
    t0 = time.perf_counter()
    r = simulate(cfg, cmap)
    wall = time.perf_counter() - t0
    m = compute_metrics(r)
    a = m["agents"]
    sr = m["spread_realised_over_fitted"]["median"]
    return (f"| {ref} | {label} | {r.settings.mode} | {r.settings.lookahead_s:g} | {cmap.schema_version} | "
            f"{r.scale:.3f} | {_f(m['nrmse_velocity'])} | {_f(m['nrmse_pressure'])} | {_f(m['nrmse_density'])} | "
            f"{_f(m['pearson_velocity'], '.2f')} | {_f(m['pearson_pressure'], '.2f')} | "
            f"{_f(m['pearson_density'], '.2f')} | {_f(sr, '.2f')} | {m['n_cv_compared']}/{m['n_cv']} | "
            f"{a['escaped']}/{a['injected']} | {wall:.1f} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--references", nargs="+", default=list(REFERENCES))
    ap.add_argument("--modes", nargs="*", default=[], metavar="MODE:LOOKAHEAD",
                    help="extra rows on the schema-2 map, e.g. slot:0.5 staggered:0.5")
    ap.add_argument("--scenario", choices=("reservoir", "seed"), default="reservoir")
    ap.add_argument("--jobs", type=int, default=1, help="parallel processes")
    a = ap.parse_args(argv)
    rows = [(ref, label, a.scenario) for ref in a.references for label in ["paper", "default", *a.modes]]
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
    print("Paper (Results and Discussion): velocity nRMSE 0.15-0.9, pressure 0-0.937, density 0.61-0.98.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
