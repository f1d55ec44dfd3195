"""The README's figure, docs/img/swarm_vs_cfd.png: the CFD's density beside the swarm's, from a main job.

    fisc-sim run -o out/run && python tools/readme_figure.py out/run docs/img/swarm_vs_cfd.png

Both panels are the XZ plane of ``fisc_ground.figures.plots`` (min-max normalised, as in
``density_cfd_fit_swarm.png``), with the swarm's time-averaged velocity as arrows on its panel.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

from fisc_ground.figures import plots
from fisc_ground.reference.analytic import tunnel_radius_m


def _columns(path: Path) -> dict[str, np.ndarray]:
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}


def _minmax(v: np.ndarray) -> np.ndarray:
    lo, hi = np.nanmin(v), np.nanmax(v)
    return (v - lo) / (hi - lo)


def main(argv: list[str] | None = None) -> int:
    """Write the figure of the run folder ``run`` to ``out``."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a fisc-sim run folder (fields.csv, metrics.json)")
    ap.add_argument("out", type=Path, help="the PNG to write")
    a = ap.parse_args(argv)
    f = _columns(a.run / "fields.csv")
    m = json.loads((a.run / "metrics.json").read_text())
    c = np.stack([f["cv_x"], f["cv_y"], f["cv_z"]], axis=1)
    ok = f["samples"] >= 10
    swarm_rho = np.where(ok, f["swarm_density"], np.nan)
    swarm_v = np.where(ok[:, None], np.stack([f["swarm_u_x"], f["swarm_u_y"], f["swarm_u_z"]], axis=1), np.nan)
    cfd = "(a) CFD density (inviscid converging-diverging tunnel)"
    cfg = m["config"]
    swarm = (f"(b) swarm density and velocity, {cfg['agents']} drones over {cfg['duration_s']:.0f} s "
             f"(density nRMSE {m['nrmse_density']:.2f}, Pearson {m['pearson_density']:.2f})")
    cell_m = float(np.diff(np.unique(c[:, 0])).min())
    fig = plots.xz_comparison_figure(
        c, {cfd: _minmax(f["target_density"]), swarm: _minmax(swarm_rho)}, cell_m,
        "The swarm beside the CFD (XZ plane, min-max normalised)", label="(rho - min) / (max - min)",
        vectors={swarm: swarm_v}, wall_radius=lambda x: tunnel_radius_m(np.clip(x, 0.0, 15.0)))
    fig.set_dpi(90)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=90)
    print(f"wrote {a.out} ({a.out.stat().st_size / 1e3:.0f} kB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
