"""Benchmark of the vectorised velocity fitting (prints figures; not a test).

    python benchmarks/bench_fit.py [--n-large 1000000] [--sample 200] [--chunk 32768]

1. the reference map (cd_nozzle_inviscid): partition + default kappa + fit time;
2. a synthetic field of ``--n-large`` CVs: fit time, peak traced memory and process max RSS;
3. a straightforward loop of ``scipy.optimize.least_squares`` (``fit_cv_reference``, 9
   candidates per CV) over ``--sample`` of the same CVs, and the per-CV speed ratio.

Targets (issue): ratio >= 100x, reference fit < 0.1 s, 10^6 CVs < 60 s in < 4 GiB.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

from fisc_ground.fit.fitting import DEFAULT_CHUNK_CVS, fit_cv_reference, fit_rmse, fit_velocities
from fisc_ground.fit.partition import partition, partition_field
from fisc_ground.fit.scaling import choose_kappa, choose_scale, default_max_dispersion, swarm_pressure_target

SHARED_CSV = Path(__file__).resolve().parents[2] / "shared/reference/cd_nozzle_inviscid/fluent_export_3d.csv"


def load_reference_cvs():
    """The reference CVs: built-in field if available, else the shared Fluent export."""
    try:
        from fisc_ground.reference.builtin import load_builtin  # type: ignore[import-not-found]

        return "builtin:cd_nozzle_inviscid", partition_field(load_builtin("cd_nozzle_inviscid"))
    except ImportError:
        pass
    path = SHARED_CSV if SHARED_CSV.exists() else Path("/work/shared/reference/cd_nozzle_inviscid/fluent_export_3d.csv")
    try:
        from fisc_ground.reference.fluent_csv import read_fluent_csv

        return str(path), partition_field(read_fluent_csv(path))
    except ImportError:
        data = np.loadtxt(path, delimiter=",", skiprows=1)
        return str(path), partition(data[:, 1:4], data[:, 6:9], data[:, 4], data[:, 5])


def synthetic_targets(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Nozzle-like random targets: u_x in [-3, 14] m/s, small cross flow, P in [0, 125]."""
    rng = np.random.default_rng(seed)
    vt = np.empty((n, 3))
    vt[:, 0] = rng.uniform(-3.0, 14.0, n)
    vt[:, 1:] = rng.normal(0.0, 0.7, (n, 2))
    pt = rng.uniform(0.0, 125.0, n)
    return vt, pt


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-large", type=int, default=1_000_000, help="CVs of the synthetic field")
    ap.add_argument("--sample", type=int, default=200, help="CVs fitted by the least_squares loop")
    ap.add_argument("--chunk", type=int, default=DEFAULT_CHUNK_CVS, help="CVs per processing chunk")
    args = ap.parse_args(argv)

    print(f"python {sys.version.split()[0]}, numpy {np.__version__}")

    # 1. reference map
    source, cvs = load_reference_cvs()
    disp = default_max_dispersion(cvs.target_velocity_m_s)
    kappa = choose_kappa(cvs.target_pressure_gauge_pa, cvs.cell_volume_m3, 1.0, 2, disp)
    pt_ref = swarm_pressure_target(cvs.target_pressure_gauge_pa, kappa)
    fit_velocities(cvs.target_velocity_m_s[:8], pt_ref[:8], cvs.cell_volume_m3)  # warm-up
    runs = [fit_velocities(cvs.target_velocity_m_s, pt_ref, cvs.cell_volume_m3) for _ in range(5)]
    ref = runs[-1]
    v_rmse, p_rmse = fit_rmse(ref, cvs.target_velocity_m_s, pt_ref)
    s = choose_scale(ref.velocities_m_s)
    print(f"\n[reference] {source}")
    print(f"  CVs {cvs.n_cv}, grid {cvs.shape}, kappa {kappa:.4g}, max dispersion {disp:.3f} m/s, S {s:.4f}")
    print(f"  fit time {min(r.seconds for r in runs) * 1e3:.1f} ms (best of 5; median "
          f"{np.median([r.seconds for r in runs]) * 1e3:.1f} ms)  [target < 100 ms]")
    print(f"  converged {ref.converged.sum()}/{ref.n_cv}, iterations max {ref.iterations.max()}, "
          f"N* counts {dict((int(k), int(c)) for k, c in zip(*np.unique(ref.n_star, return_counts=True)))}")
    print(f"  velocity RMSE {v_rmse:.3e} m/s, pressure RMSE {p_rmse:.3e}")

    # 2. synthetic large field
    n = args.n_large
    vt, pt = synthetic_targets(n)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    tracemalloc.start()
    t0 = time.perf_counter()
    big = fit_velocities(vt, pt, 0.125, chunk_cvs=args.chunk)
    wall = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    v_rmse, p_rmse = fit_rmse(big, vt, pt)
    result_mib = sum(a.nbytes for a in (big.velocities_m_s, big.candidate_loss, big.mean_velocity_m_s)) / 2**20
    print(f"\n[synthetic] {n} CVs, chunk {args.chunk}")
    print(f"  fit time {big.seconds:.2f} s (wall {wall:.2f} s), {big.seconds / n * 1e6:.2f} us/CV  [target < 60 s]")
    print(f"  peak traced memory {peak / 2**20:.0f} MiB (result arrays {result_mib:.0f} MiB), "
          f"process max RSS {rss1:.0f} MiB (before {rss0:.0f} MiB)  [target < 4096 MiB]")
    print(f"  converged {big.converged.sum()}/{n}, iterations max {big.iterations.max()}, "
          f"velocity RMSE {v_rmse:.3e}, pressure RMSE {p_rmse:.3e}")

    # 3. straightforward loop of scipy.optimize.least_squares over a sample of the same CVs
    m = min(args.sample, n)
    idx = np.random.default_rng(1).choice(n, size=m, replace=False)
    t0 = time.perf_counter()
    agree = 0
    for j in idx:
        _, n_ref, loss_ref, _ = fit_cv_reference(vt[j], pt[j], 0.125, seed=int(j))
        agree += int(n_ref == big.n_star[j] and loss_ref < 1e-6)
    loop = (time.perf_counter() - t0) / m
    vec = big.seconds / n
    print(f"\n[least_squares loop] {m} CVs x 9 candidates: {loop * 1e3:.1f} ms/CV; "
          f"same N* and loss < 1e-6 on {agree}/{m}")
    print(f"  vectorised {vec * 1e6:.2f} us/CV -> speed ratio {loop / vec:.0f}x  [target >= 100x]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
