"""Independent recomputation of the DESIGN.md section 4 fidelity figures from a ``fields.csv``.

Deliberately shares no code with ``fisc_ground.fields.metrics`` (standard library only), so that a test
comparing the two catches a bug in either.  CVs compared: ``samples > 0`` and finite values.

* velocity: u_hat = u / max(u) of swarm and CFD separately, nRMSE = sqrt(mean((a - b)^2));
* pressure, density: min-max normalisation of each field, then the same nRMSE;
* Pearson correlation of the raw fields.

Usable as a script: ``python tests/sim/fidelity_check.py out/run/fields.csv``.
"""

from __future__ import annotations

import csv
import math
import sys

PAIRS = {
    "velocity": ("swarm_u_axial", "target_u_axial", "max"),
    "pressure": ("swarm_pressure", "target_pressure", "minmax"),
    "density": ("swarm_density", "target_density", "minmax"),
}


def _read(path: str) -> list[dict[str, float]]:
    with open(path, newline="") as fh:
        return [{k: float(v) if v not in ("", None) else math.nan for k, v in row.items()} for row in csv.DictReader(fh)]


def _norm(values: list[float], kind: str) -> list[float]:
    if kind == "max":
        top = max(values)
        return [v / top for v in values]
    lo, hi = min(values), max(values)
    return [(v - lo) / (hi - lo) for v in values]


def _pearson(a: list[float], b: list[float]) -> float:
    n = len(a)
    ma, mb = sum(a) / n, sum(b) / n
    sab = sum((x - ma) * (y - mb) for x, y in zip(a, b))
    saa = sum((x - ma) ** 2 for x in a)
    sbb = sum((y - mb) ** 2 for y in b)
    return sab / math.sqrt(saa * sbb)


def fidelity_from_csv(path: str, min_samples: float = 1.0) -> dict[str, float]:
    """{``nrmse_<q>``, ``pearson_<q>``, ``n_<q>``} for q in velocity, pressure, density."""
    rows = [r for r in _read(path) if r["samples"] >= min_samples]
    out: dict[str, float] = {}
    for q, (swarm, target, kind) in PAIRS.items():
        sel = [r for r in rows if math.isfinite(r[swarm]) and math.isfinite(r[target])]
        a = _norm([r[swarm] for r in sel], kind)
        b = _norm([r[target] for r in sel], kind)
        out[f"nrmse_{q}"] = math.sqrt(sum((x - y) ** 2 for x, y in zip(a, b)) / len(a))
        out[f"pearson_{q}"] = _pearson([r[swarm] for r in sel], [r[target] for r in sel])
        out[f"n_{q}"] = len(sel)
    return out


if __name__ == "__main__":
    for p in sys.argv[1:]:
        f = fidelity_from_csv(p)
        print(p, " ".join(f"{q} {f['nrmse_' + q]:.3f} (r {f['pearson_' + q]:.2f})" for q in PAIRS))
