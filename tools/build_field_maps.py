#!/usr/bin/env python3
"""Regenerate the built-in reference fields ``field_maps/<name>.npz`` from ``../shared/reference``.

Each built-in is the 3-D node field of the case's Fluent-style export
(``<case>/fluent_export_3d.csv``), read with ``read_fluent_csv`` and stored as exact float64
arrays (compressed) plus provenance: the CSV's sha256, the case README (its text and sha256)
and a one-line summary. Usage::

    python tools/build_field_maps.py [--reference-dir ../shared/reference] [--out field_maps]
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

from fisc_ground.reference.builtin import BUILTIN_FILES, field_from_npz_bytes, npz_payload
from fisc_ground.reference.fluent_csv import read_fluent_csv

REPO = Path(__file__).resolve().parents[1]
SOLVERS = {
    "cd_nozzle_inviscid": "OpenFOAM v1912 rhoSimpleFoam, laminar, slip walls (axisymmetric wedge)",
    "cd_nozzle": "OpenFOAM v1912 rhoSimpleFoam, RANS k-omega SST, no-slip walls (axisymmetric "
                 "wedge); separated on the diverging wall",
}


def summary_of(readme: str) -> str:
    """First non-heading paragraph of a README, joined to one line."""
    paras = [p.strip() for p in readme.split("\n\n") if p.strip()]
    for p in paras:
        if not p.startswith("#"):
            return " ".join(p.split())
    return ""


def build(reference_dir: Path, out_dir: Path) -> list[Path]:
    written = []
    for name, fname in BUILTIN_FILES.items():
        case = reference_dir / name
        csv = case / "fluent_export_3d.csv"
        readme = (case / "README.md").read_text(encoding="utf-8")
        field = read_fluent_csv(csv, pressure_kind="gauge", name=name)
        payload = npz_payload(field, origin=f"{name}/fluent_export_3d.csv",
                              summary=summary_of(readme), solver=SOLVERS.get(name, ""),
                              readme_md=readme)
        target = out_dir / fname
        tmp = target.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, **payload)
        check = field_from_npz_bytes(tmp.read_bytes(), name, str(tmp))
        for a, b in ((check.points_m, field.points_m), (check.velocity_m_s, field.velocity_m_s),
                     (check.pressure_gauge_pa, field.pressure_gauge_pa),
                     (check.density_kg_m3, field.density_kg_m3)):
            if not np.array_equal(a, b):
                raise SystemExit(f"{target}: round trip mismatch")
        tmp.replace(target)
        print(f"{target}: {field.n_nodes} nodes, {target.stat().st_size / 1e6:.2f} MB, "
              f"source sha256 {field.source_sha256[:16]}...")
        written.append(target)
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference-dir", type=Path, default=REPO.parent / "shared" / "reference")
    ap.add_argument("--out", type=Path, default=REPO / "field_maps")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    if not args.reference_dir.is_dir():
        print(f"reference dir not found: {args.reference_dir}", file=sys.stderr)
        return 2
    build(args.reference_dir, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
