"""Parameter sweeps of ``fisc-sim run`` configurations: the spec, its grid, one point (pure).

A sweep spec is a TOML file::

    [base]                      # RunConfig fields shared by every run (sim.run.RunConfig)
    scenario = "reservoir"
    max_speed_m_s = 2.0

    [base.fit]                  # FitConfig fields of the maps fitted by the sweep (fisc_ground.maps.build)
    cell_size_m = 0.5

    [grid]                      # the product of these lists, in this order
    map = ["cd_nozzle_inviscid", "cd_nozzle", "my_cases.py:duct"]
    configuration = [           # a list of tables: each entry sets several fields at once
        {label = "paper", preset = "paper"},
        {label = "default"},
        {label = "slot:0.5", mode = "slot", lookahead_s = 0.5},
    ]
    seed = [0, 1]

    [grid.fit]                  # fit settings varied by the grid (dimension names fit.<field>)
    max_speed_m_s = [2.0, 3.0]
    staircase_contrast = [0.4, "off"]   # "auto" and "off" stand for None, as on the fisc-ground command line

``map`` values are what ``RunConfig.map`` takes (a ``.fiscmap`` file, a built-in reference name
or a CFD file; relative paths are relative to the spec file) or ``FILE.py:FUNCTION``, a function
of no arguments returning a ``fisc_ground.reference.field.ReferenceField`` (a CFD case of your
own).  Every point is one ``sim.run.simulate`` of its ``RunConfig`` on its map, scored by
``sim.report.compute_metrics``; ``run_point`` returns one row of the tidy table (one row per
run: the grid values, then the metrics).  ``sim.sweep.run`` executes the grid on dask.
"""

from __future__ import annotations

import importlib.util
import itertools
import math
import time
import tomllib
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

#: Metric columns of the table, in order (all from ``sim.report.compute_metrics``).
METRICS = ("nrmse_velocity", "nrmse_pressure", "nrmse_density", "pearson_velocity", "pearson_pressure",
           "pearson_density", "spread_ratio_median", "n_cv_compared", "escaped", "injected")
#: Columns that depend on the machine, not on the configuration (left out of comparisons).
TIMING_COLUMNS = ("wall_s",)


class SweepSpecError(ValueError):
    """A sweep spec is invalid; the message names the file and the key."""


@dataclass(frozen=True)
class SweepPoint:
    """One run of the grid: where it sits in the grid and what it runs."""

    index: int
    """Position in the grid (row order of the table)."""
    labels: tuple[tuple[str, Any], ...]
    """(dimension, value) per grid dimension; inline-table values show their ``label``."""
    run: dict[str, Any]
    """``sim.run.RunConfig`` fields (``map`` resolved; figures off: the sweep draws its own)."""
    fit: dict[str, Any]
    """``fisc_ground.maps.build.FitConfig`` overrides of a map fitted for this run."""


@dataclass(frozen=True)
class SweepSpec:
    """A parsed sweep spec."""

    path: Path | None
    """The spec file (relative map paths are resolved against its folder)."""
    base: dict[str, Any]
    """RunConfig fields shared by every run."""
    base_fit: dict[str, Any]
    """FitConfig fields shared by every fitted map."""
    grid: tuple[tuple[str, tuple[Any, ...]], ...]
    """(dimension, values) in product order; ``fit.<field>`` dimensions set FitConfig fields."""

    def points(self) -> list[SweepPoint]:
        """Every point of the grid, in product order (the last dimension varies fastest)."""
        from fisc_ground.maps.build import fit_overrides

        names = [n for n, _ in self.grid]
        out = []
        for i, combo in enumerate(itertools.product(*(v for _, v in self.grid))):
            run, fit, labels = dict(self.base), fit_overrides(self.base_fit), []
            for name, value in zip(names, combo):
                if isinstance(value, dict):
                    entry = dict(value)
                    label = entry.pop("label", None)
                    for key, v in entry.items():
                        if key.startswith("fit."):
                            fit.update(fit_overrides({key.removeprefix("fit."): v}))
                        else:
                            run[key] = v
                    labels.append((name, label if label is not None else _compact(entry)))
                elif name.startswith("fit."):
                    fit.update(fit_overrides({name.removeprefix("fit."): value}))
                    labels.append((name, value))
                else:
                    run[name] = value
                    labels.append((name, value))
            if isinstance(run.get("map"), str):
                run["map"] = _resolve_map(run["map"], self.path)
            run["figures"] = False
            out.append(SweepPoint(i, tuple(labels), run, fit))
        return out


def _compact(entry: dict) -> str:
    return ",".join(f"{k}={v}" for k, v in entry.items()) or "-"


def _resolve_map(spec: str, spec_path: Path | None) -> str:
    """A relative file of the spec's folder becomes absolute (workers may run elsewhere)."""
    if spec_path is None:
        return spec
    file_part = spec.split(":", 1)[0] if ".py:" in spec else spec
    candidate = spec_path.parent / file_part
    if not Path(file_part).is_absolute() and candidate.exists():
        return str(candidate.resolve()) + spec[len(file_part):]
    return spec


def _field_names(cls) -> set[str]:
    return {f.name for f in fields(cls)}


def parse_spec(data: dict[str, Any], path: Path | None = None) -> SweepSpec:
    """Check and parse a spec's TOML tables (``SweepSpecError`` names the bad key)."""
    from fisc_ground.maps.build import FitConfig
    from sim.run import RunConfig

    where = str(path) if path is not None else "sweep spec"
    unknown = set(data) - {"base", "grid"}
    if unknown:
        raise SweepSpecError(f"{where}: unknown table(s) {sorted(unknown)}; a spec has [base] and [grid]")
    run_fields, fit_fields = _field_names(RunConfig) - {"out_dir"}, _field_names(FitConfig)
    base = dict(data.get("base", {}))
    base_fit = base.pop("fit", {})

    def check(key: str, ctx: str) -> None:
        if key.startswith("fit."):
            if key[4:] not in fit_fields:
                raise SweepSpecError(f"{where}: {ctx}: {key!r} is not a FitConfig field ({', '.join(sorted(fit_fields))})")
        elif key not in run_fields and key != "label":
            raise SweepSpecError(f"{where}: {ctx}: {key!r} is not a RunConfig field ({', '.join(sorted(run_fields))})")

    for key in base:
        check(key, "[base]")
    for key in base_fit:
        check("fit." + key, "[base.fit]")
    grid_tbl = dict(data.get("grid", {}))
    grid_fit = grid_tbl.pop("fit", {})
    dims: list[tuple[str, tuple[Any, ...]]] = []
    for name, values in [*grid_tbl.items(), *(("fit." + k, v) for k, v in grid_fit.items())]:
        if not isinstance(values, list) or not values:
            raise SweepSpecError(f"{where}: [grid] {name}: expected a non-empty list, got {values!r}")
        if all(isinstance(v, dict) for v in values):
            for v in values:
                for key in v:
                    check(key, f"[grid] {name}")
        else:
            check(name, "[grid]")
        dims.append((name, tuple(values)))
    spec = SweepSpec(path, base, base_fit, tuple(dims))
    for p in spec.points():  # every point must make a valid RunConfig / FitConfig before anything runs
        try:
            run_config(p)
            FitConfig(**p.fit)
            if p.fit and str(p.run.get("map") or "").endswith(".fiscmap"):
                raise ValueError(f"fit settings {p.fit} cannot apply to a ready-made map {p.run['map']}")
        except (TypeError, ValueError) as exc:
            raise SweepSpecError(f"{where}: grid point {dict(p.labels)}: {exc}") from None
    return spec


def load_spec(path: str | Path) -> SweepSpec:
    """Read and parse a TOML sweep spec."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise SweepSpecError(f"{path}: not valid TOML: {exc}") from None
    return parse_spec(data, path.resolve())


def run_config(point: SweepPoint):
    """The ``sim.run.RunConfig`` of a point."""
    from sim.run import RunConfig

    return RunConfig(**point.run)


def point_map(point: SweepPoint):
    """The command map a point flies: ``sim.run.load_command_map`` with the point's fit settings,
    or a ``FILE.py:FUNCTION`` reference fitted with them."""
    from fisc_ground.maps.build import DEFAULT_REFERENCE, FitConfig, build_map, build_map_from_reference
    from sim.run import load_command_map

    cfg = run_config(point)
    spec = cfg.map
    # as sim.run.load_command_map fits: the run's speed limit, schema 1 for the paper preset
    fit = FitConfig(**{"max_speed_m_s": cfg.max_speed_m_s, "staggered": cfg.preset != "paper", **point.fit})
    if spec is not None and ".py:" in spec:
        from fisc_agent.map.codec import decode_map
        from fisc_agent.map.codec import encode_map

        file, func = spec.rsplit(":", 1)
        field = load_case_function(file, func)()
        meta, arrays = build_map(field, fit)
        return decode_map(encode_map(meta, arrays), source=spec)
    if not point.fit:
        return load_command_map(spec, cfg.max_speed_m_s, cfg.preset)
    return build_map_from_reference(spec or DEFAULT_REFERENCE, fit)


def load_case_function(file: str, func: str):
    """The function ``func`` of the Python case file ``file`` (a ``FILE.py:FUNCTION`` map spec)."""
    spec = importlib.util.spec_from_file_location(f"fisc_sweep_case_{Path(file).stem}", file)
    if spec is None or spec.loader is None:
        raise ValueError(f"{file}: cannot load a Python case file")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    try:
        return getattr(module, func)
    except AttributeError:
        raise ValueError(f"{file}: no function {func!r}") from None


def run_point(point: SweepPoint) -> dict[str, Any]:
    """Fit (or load) the point's map, simulate, score: one row of the tidy table."""
    from sim.report import compute_metrics
    from sim.run import simulate

    cfg = run_config(point)
    cmap = point_map(point)
    t0 = time.perf_counter()
    result = simulate(cfg, cmap)
    wall = time.perf_counter() - t0
    m = compute_metrics(result)
    row: dict[str, Any] = {"index": point.index, **{k: v for k, v in point.labels}}
    row.update(mode_flown=result.settings.mode, lookahead_s_flown=result.settings.lookahead_s,
               map_schema=cmap.schema_version, scale=result.scale)
    values = {**m, "spread_ratio_median": m["spread_realised_over_fitted"]["median"],
              "escaped": m["agents"]["escaped"], "injected": m["agents"]["injected"]}
    for name in METRICS:
        v = values.get(name)
        row[name] = float("nan") if v is None else v
    row["wall_s"] = wall
    return row


def run_serial(spec: SweepSpec) -> list[dict[str, Any]]:
    """Every point in this process, in grid order (the reference of the distributed run)."""
    return [run_point(p) for p in spec.points()]


def rows_equal(a: list[dict], b: list[dict], rel: float = 1e-12) -> bool:
    """Same rows, same values (NaN equals NaN), timing columns ignored."""
    if len(a) != len(b):
        return False
    for ra, rb in zip(a, b):
        if set(ra) != set(rb):
            return False
        for k in ra:
            if k in TIMING_COLUMNS:
                continue
            va, vb = ra[k], rb[k]
            if isinstance(va, float) and isinstance(vb, float):
                if not (math.isnan(va) and math.isnan(vb)) and not math.isclose(va, vb, rel_tol=rel, abs_tol=0.0):
                    return False
            elif va != vb:
                return False
    return True


def with_base(spec: SweepSpec, **run_fields: Any) -> SweepSpec:
    """``spec`` with ``[base]`` fields overridden (e.g. a shorter duration for a quick look)."""
    return replace(spec, base={**spec.base, **run_fields})
