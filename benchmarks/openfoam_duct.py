"""duct_c: a converging-diverging duct of our own solved with OpenFOAM, then fitted and flown.

The case is written by the inviscid reference's own generator
(``../shared/reference/cd_nozzle_inviscid/case/make_case.py``: axisymmetric 5-degree wedge,
rhoSimpleFoam, laminar with slip walls) with another geometry, solved with Debian's OpenFOAM v1912
(``apt-get install openfoam``), exported by that folder's ``post.py`` (the Fluent-style node CSV and
the axisymmetric CSV) and by ``foamToVTK`` (the VTU), fitted with ``fisc-ground fit`` and flown with
``fisc-sim run --map``::

    python benchmarks/openfoam_duct.py -o out/duct_c                 # about 1 min of OpenFOAM, then ~20 s
    python benchmarks/openfoam_duct.py -o out/duct_c --iterations 3000 --shared ../shared

docs/studies/fidelity.md ("Ducts not seen when the defaults were chosen") has the measured rows.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

log = logging.getLogger("openfoam_duct")

#: The geometry (make_case.radius): R = Rt + (Rin - Rt)/2 (1 + cos(pi x / xt)) up to the throat,
#: then Rt + (Rout - Rt)/2 (1 - cos(pi (x - xt) / (L - xt))).
DUCT_C = dict(L=14.0, Rin=1.6, Rt=0.9, xt=7.0, Rout=1.4, Uin=3.0, Nx=280, Nr=60)
NAME = "duct_c"
OPENFOAM_STEPS = (
    ["blockMesh"],
    ["checkMesh"],
    ["rhoSimpleFoam"],
    ["postProcess", "-func", "writeCellCentres", "-latestTime"],
    ["foamToVTK", "-latestTime", "-no-boundary", "-no-lagrangian", "-fields", "(U p rho T)"],
)


def _generator(shared: Path):
    """The reference's make_case and post modules (post imports make_case: one CASES dict)."""
    case_dir = shared / "reference" / "cd_nozzle_inviscid" / "case"
    if not (case_dir / "make_case.py").is_file():
        raise FileNotFoundError(f"{case_dir / 'make_case.py'}: the reference case generator is missing (--shared?)")
    sys.path.insert(0, str(case_dir))
    make_case = importlib.import_module("make_case")
    post = importlib.import_module("post")
    make_case.CASES[NAME] = DUCT_C
    return make_case, post


def _set_iterations(case: Path, iterations: int) -> None:
    """endTime and writeInterval of system/controlDict (the generator writes 3000 / 1000)."""
    path = case / "system" / "controlDict"
    lines = path.read_text().splitlines()
    for i, line in enumerate(lines):
        key = line.split()[0] if line.split() else ""
        if key in ("endTime", "writeInterval") and not line.startswith(" "):
            lines[i] = f"{key:<16}{iterations};"
    path.write_text("\n".join(lines) + "\n")


def solve(out: Path, shared: Path, iterations: int) -> Path:
    """Write, solve and export the case under ``out``; the VTU's path."""
    for tool in ("blockMesh", "rhoSimpleFoam", "foamToVTK"):
        if shutil.which(tool) is None:
            raise RuntimeError(f"{tool} not found: install OpenFOAM (apt-get install openfoam)")
    make_case, post = _generator(shared)
    case = out / NAME
    if case.exists():
        shutil.rmtree(case)
    make_case.make(NAME, str(out))
    _set_iterations(case, iterations)
    env = dict(os.environ, WM_PROJECT_DIR=os.environ.get("WM_PROJECT_DIR", "/usr/share/openfoam"))
    for step in OPENFOAM_STEPS:
        log.info("OpenFOAM: %s", " ".join(step))
        with open(case / f"log.{step[0]}", "w") as fh:
            done = subprocess.run(step, cwd=case, env=env, stdout=fh, stderr=subprocess.STDOUT)
        if done.returncode != 0:
            raise RuntimeError(f"{step[0]} failed (exit {done.returncode}); see {case / f'log.{step[0]}'}")
    log.info("exporting the Fluent-style and axisymmetric CSVs (post.py)")
    post.main(NAME, str(case), str(out), 0.1, str(out / "u_x.png"))
    vtus = sorted((case / "VTK").rglob("internal.vtu"))
    if not vtus:
        raise RuntimeError(f"foamToVTK wrote no internal.vtu under {case / 'VTK'}")
    return vtus[-1]


def fly(out: Path, reference: Path) -> None:
    """``fisc-ground fit`` the reference and fly the default and the paper preset on it."""
    bin_dir = Path(sys.executable).parent
    for preset in ("default", "paper"):
        fiscmap = out / f"{NAME}_{preset}.fiscmap"
        subprocess.run([str(bin_dir / "fisc-ground"), "fit", str(reference), "--preset", preset, "-o", str(fiscmap)],
                       check=True)
        subprocess.run([str(bin_dir / "fisc-sim"), "run", "--map", str(fiscmap), "--preset", preset,
                        "-o", str(out / f"run_{preset}")], check=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("-o", "--output", type=Path, default=Path("out") / NAME, help="output folder (default out/duct_c)")
    p.add_argument("--shared", type=Path, default=Path(__file__).resolve().parents[2] / "shared",
                   help="the shared folder holding reference/cd_nozzle_inviscid/case (default ../shared)")
    p.add_argument("--iterations", type=int, default=1000,
                   help="rhoSimpleFoam iterations (default 1000; residuals fall below 1e-8 by ~300)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    args.output.mkdir(parents=True, exist_ok=True)
    vtu = solve(args.output.resolve(), args.shared.resolve(), args.iterations)
    fly(args.output.resolve(), vtu)
    log.info("fields, metrics and figures: %s/run_default and %s/run_paper", args.output, args.output)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
