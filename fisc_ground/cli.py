"""``fisc-ground``: fit, sign, inspect, plot and distribute FISC command maps.

Thin entry point: parse arguments, set up logging, call one ``run_*`` function.  Exit codes
(``fisc_agent.common.cli_common``): 0 success, 1 runtime failure or a missing optional package, 2 bad
usage or invalid input (a failed map check, a bad reference file: the message says which).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path

from fisc_agent.common.cli_common import (EXIT_CODES_EPILOG, EXIT_FAILURE, EXIT_USAGE, add_logging_args, console_exit,
                                   missing_extra, missing_dependency_message, number_or, positive_number, setup_logging,
                                   sig3)
from fisc_agent.map.separation import DEFAULT_POSITION_SIGMA_M, DEFAULT_VEHICLE_RADIUS_M
from fisc_ground.fit.scaling import DEFAULT_DISPERSION_RATIO, DEFAULT_MAX_SPEED_M_S, KINETIC_DISPERSION_RATIO
from fisc_ground.fit.staircase import DEFAULT_STAIRCASE_CONTRAST
from fisc_ground.fit.staggered import (AUTO_CONTINUITY_WEIGHTS, AUTO_DENSITY_AMPLITUDES, STATIC_VELOCITY_BUDGET,
                                   STATIC_VELOCITY_LIMIT)

log = logging.getLogger("fisc_ground")


def _n_range(text: list[str]) -> tuple[int, int]:
    lo, hi = int(text[0]), int(text[1])
    if not 1 <= lo <= hi:
        raise argparse.ArgumentTypeError(f"--n-range needs 1 <= N_MIN <= N_MAX, got {lo} {hi}")
    return lo, hi


def _scale(text: str) -> float | None:
    if text == "auto":
        return None
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError("--scale must be positive or 'auto'")
    return value


def _non_negative_m(flag: str):
    """argparse type: a finite number of metres >= 0 (the error names ``flag``)."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} must be a number of metres, got {text!r}") from None
        if not (math.isfinite(value) and value >= 0):
            raise argparse.ArgumentTypeError(f"{flag} must be a finite number >= 0 m, got {text!r}")
        return value
    return parse


def fit_config_from_args(args: argparse.Namespace):
    """The ``fisc_ground.maps.build.FitConfig`` of parsed ``fisc-ground fit`` arguments."""
    from fisc_ground.maps.build import FitConfig, fit_overrides

    n_min, n_max = _n_range(args.n_range)
    given = {"continuity_weight": args.continuity_weight, "density_amplitude": args.density_amplitude,
             "staircase_contrast": args.staircase_contrast}
    given = {k: v for k, v in given.items() if v is not None}
    if given and args.preset == "paper":
        flags = ", ".join("--" + k.replace("_", "-") for k in given)
        raise ValueError(f"{flags}: the paper's schema-1 map has no designed density (drop --preset paper)")
    design = fit_overrides(given)
    return FitConfig(cell_size_m=args.cell_size, n_min=n_min, n_max=n_max, scale=args.scale,
                     max_speed_m_s=args.max_speed, kappa=args.kappa, dispersion_ratio=args.dispersion_ratio,
                     agent_mass_kg=args.agent_mass, min_nodes=args.min_nodes, seed=args.seed,
                     staggered=args.preset != "paper", vehicle_radius_m=args.vehicle_radius,
                     position_sigma_m=args.position_sigma, length_scale=args.length_scale, **design)


def run_fit(args: argparse.Namespace) -> int:
    """``fisc-ground fit``: reference -> partition -> fit -> written (optionally signed) map."""
    from fisc_ground.maps.build import build_map
    from fisc_ground.maps.write import read_signing_key, write_map
    from fisc_ground.reference.load import load_reference

    config = fit_config_from_args(args)
    key = read_signing_key(args.sign) if args.sign else None
    with _status(f"loading reference {args.reference}"):
        field = load_reference(args.reference, pressure_kind=args.pressure_kind)
    log.info("reference %s: %d nodes (%s pressure)", field.name, field.n_nodes, field.pressure_kind)
    with _status("partitioning and fitting"):
        meta, arrays = build_map(field, config)
    sha = write_map(args.output, meta, arrays, key)
    fit = meta["fit"]
    print(f"wrote {args.output}: {meta['n_cv']} CVs, S={sig3(meta['scale'])}, kappa={sig3(meta['kappa'])}, "
          f"fit {sig3(fit['seconds'] * 1e3)} ms, velocity RMSE {sig3(fit['velocity_rmse'])} m/s, "
          f"pressure RMSE {sig3(fit['pressure_rmse'])}, {'signed' if key else 'unsigned'}, sha256 {sha[:16]}...")
    print(f"  {separation_line(meta['separation'])}")
    return 0


def run_score_flight(args: argparse.Namespace) -> int:
    """``fisc-ground score-flight``: score each flight log against the map's CFD reference."""
    from fisc_agent.flight.flightlog import read_flight_log
    from fisc_agent.map.codec import load_map
    from fisc_agent.map.wall import map_wall
    from fisc_ground.maps.duct_wall import duct_wall_from_reference
    from fisc_agent.map.separation import map_separation
    from fisc_ground.fields.flight_score import gnss_vx_from_rows, score_track, track_from_rows, wall_track_from_rows
    from fisc_ground.reference.load import load_reference

    cmap = load_map(args.map)
    spec = args.reference or cmap.body.get("provenance", {}).get("reference", {}).get("source", "")
    spec = spec.removeprefix("builtin:")
    if not spec:
        raise ValueError(f"{args.map}: the map records no reference; pass --reference")
    ref = load_reference(spec)
    wall = map_wall(cmap.arrays) or duct_wall_from_reference(ref)  # the wall the agent turned at, where carried
    tracks = []
    for path in args.logs:
        rows = read_flight_log(path)
        tracks.append(wall_track_from_rows(rows))
        score = score_track(*track_from_rows(rows), ref, cmap.scale, *args.x_range, wall=wall,
                            gnss_vx_m_s=gnss_vx_from_rows(rows))
        if args.json:
            print(json.dumps({"log": str(path), **score.as_dict()}))
        else:
            print(f"{path}: {'crossed' if score.crossed else 'did not cross'}"
                  f"{' (held)' if score.held else ''}, max excursion {sig3(score.max_excursion_m)} m, "
                  f"velocity nRMSE {sig3(score.velocity_nrmse)} (by the GNSS receiver's velocity "
                  f"{sig3(score.velocity_nrmse_gnss)}; {score.n_samples} samples, peak flown "
                  f"{sig3(score.peak_flown_m_s)} of {sig3(score.peak_target_m_s)} m/s), crossing {sig3(score.crossing_time_s)} s")
    if len(args.logs) >= 2:
        _print_fleet_approach(args, tracks, map_separation(cmap.body).d_min_m)
    return 0


def _print_fleet_approach(args: argparse.Namespace, tracks: list, d_min_m: float) -> None:
    """The fleet's closest approach over several logs on their shared wall clock (``wall_time_s``),
    positions interpolated on a common ``--period`` time base; vehicles are named by their log."""
    import numpy as np

    from fisc_ground.fields.separation_stats import common_time_base, track_approach

    t, pos = common_time_base(tracks, args.period, max_gap_s=args.max_gap)
    res = track_approach(t, np.arange(len(tracks)), pos, d_min_m)
    names = [str(p) for p in args.logs]
    pair = [names[res.id_a], names[res.id_b]] if res.id_a >= 0 else None
    if args.json:
        print(json.dumps({"fleet": {**res.as_dict(), "closest_approach_logs": pair, "logs": names,
                                    "period_s": args.period}}))
    elif pair is None:
        print(f"fleet of {len(names)} logs: never two vehicles with a position at the same wall time")
    else:
        print(f"fleet of {len(names)} logs: closest approach {sig3(res.distance_m)} m between {pair[0]} and {pair[1]} "
              f"at wall time {res.time_s:.1f} s; {res.near_misses} near-misses < d_min {sig3(d_min_m)} m")


def inspect_summary(cmap) -> dict:
    """The ``inspect --json`` object (its keys are a contract)."""
    import dataclasses

    from fisc_agent.map.lookup import map_flight_settings
    from fisc_ground.fit.length_scale import map_length_scale

    body = cmap.body
    return {
        "n_cv": cmap.n_cv,
        "cell_size": cmap.cell_size_m,
        "scale": cmap.scale,
        "kappa": float(body["kappa"]),
        "n_range": list(body["n_range"]),
        "schema_version": body["schema_version"],
        "map_version": cmap.map_version,
        "sha256": cmap.sha256,
        "signed": cmap.signed,
        "public_key": cmap.public_key,
        "fit_seconds": body.get("fit", {}).get("seconds"),
        "fit_velocity_rmse": body.get("fit", {}).get("velocity_rmse"),
        "fit_pressure_rmse": body.get("fit", {}).get("pressure_rmse"),
        "agent_mass_kg": body["agent_mass_kg"],
        "max_speed_m_s": body.get("max_speed_m_s"),
        "grid": body["grid"],
        "created_utc": body.get("created_utc"),
        "software_version": body.get("software_version"),
        "reference": body.get("provenance", {}).get("reference"),
        "n_star_histogram": {str(int(k)): int(v) for k, v in zip(*_unique(cmap["n_star"]))},
        "reversed_flow_cvs": int((cmap["target_velocity_m_s"][:, 0] < 0).sum()),
        "flight": dataclasses.asdict(map_flight_settings(cmap)),
        "design": body.get("staggered"),
        "length_scale": map_length_scale(body),
        "separation": separation_summary(body),
    }


def separation_summary(body: dict) -> dict:
    """The ``separation`` object of ``inspect --json``: the map's radius, sigma and d_min (the defaults
    for a map without them), and its budget where recorded (None for maps fitted before issue 37)."""
    from fisc_agent.map.separation import map_separation

    sep = map_separation(body)
    recorded = body.get("separation") or {}
    out = {"vehicle_radius_m": sep.vehicle_radius_m, "position_sigma_m": sep.position_sigma_m,
           "d_min_m": sep.d_min_m, "recorded": bool(recorded)}
    for key in ("max_in_tunnel", "densest_nn_m", "near_fraction", "mean_transit_s", "flux_period_s",
                "inlet_period_s", "admission_period_s", "limit", "in_tunnel_admitted", "tunnel_volume_m3"):
        out[key] = recorded.get(key)
    return out


def separation_line(sep: dict) -> str:
    """What a map allows, in one sentence (``fisc-ground fit`` and ``inspect``)."""
    d = sep["d_min_m"]
    if sep.get("max_in_tunnel") is None:
        return (f"d_min = {sig3(d)} m (r {sig3(sep['vehicle_radius_m'])} m, sigma {sig3(sep['position_sigma_m'])} m); "
                "no budget recorded (a map fitted before issue 37: refit it)")
    return (f"at most {sep['max_in_tunnel']} vehicles in the tunnel at once at d_min = {sig3(d)} m (densest CV: "
            f"expected nearest neighbour {sig3(sep['densest_nn_m'])} m, {sep['near_fraction']:.0%} of its vehicles "
            f"inside d_min as a random gas); admit one vehicle every {sig3(sep['admission_period_s'])} s "
            f"(set by the {sep['limit']}: flux budget {sig3(sep['flux_period_s'])} s, inlet spacing "
            f"{sig3(sep['inlet_period_s'])} s), {sig3(sep['in_tunnel_admitted'])} in the tunnel on average over "
            f"a mean transit of {sig3(sep['mean_transit_s'])} s")


def _unique(a):
    import numpy as np

    return np.unique(a, return_counts=True)


def run_inspect(args: argparse.Namespace) -> int:
    """``fisc-ground inspect``: verify a map and print its summary (text or JSON)."""
    from fisc_agent.map.codec import load_map

    cmap = load_map(args.map, trusted_key=args.trusted_key)
    summary = inspect_summary(cmap)
    if args.json:
        from fisc_ground.fields.field_report import json_safe

        print(json.dumps(json_safe(summary), indent=None if args.compact else 2, allow_nan=False))
        return 0
    ref = summary["reference"] or {}
    print(f"{args.map}: OK (schema v{summary['schema_version']}, sha256 {summary['sha256']})")
    print(f"  signature    : {'verified, key ' + summary['public_key'] if summary['signed'] else 'none'}"
          + (" (trusted)" if args.trusted_key and summary['signed'] else ""))
    print(f"  reference    : {ref.get('name')} ({ref.get('source')}, {ref.get('pressure_kind')} pressure)")
    print(f"  control vols : {summary['n_cv']} cubes of {summary['cell_size']} m, grid {summary['grid']['shape']}")
    print(f"  scaling      : S = {summary['scale']:.4g}, kappa = {summary['kappa']:.4g}, max speed "
          f"{summary['max_speed_m_s']} m/s, agent mass {summary['agent_mass_kg']} kg")
    print(f"  N range      : {summary['n_range']}, N* histogram {summary['n_star_histogram']}")
    print(f"  fit          : {summary['fit_seconds'] * 1e3:.1f} ms, velocity RMSE "
          f"{summary['fit_velocity_rmse']:.3e} m/s, pressure RMSE {summary['fit_pressure_rmse']:.3e}")
    print(f"  reversed flow: {summary['reversed_flow_cvs']} CVs; created {summary['created_utc']} "
          f"by fisc {summary['software_version']}; map version {summary['map_version']}")
    flight = summary["flight"]
    print(f"  flight       : {flight['mode']}, look-ahead {flight['lookahead_s']:g} s"
          + (f", persistence {flight['persistence_s']:g} s" if flight["mode"] == "kinetic" else "")
          + (" (recommended)" if summary["schema_version"] >= 2 else " (schema 1: the paper's Algorithm 1)"))
    print(f"  design       : {_design_line(summary['design'])}")
    L = summary["length_scale"]
    print(f"  length scale : L = {L:g}" + ("" if L == 1 else f" (lengths x{L:g}, speeds x1, times x{L:g} against "
                                                            "the reference)"))
    print(f"  separation   : {separation_line(summary['separation'])}")
    return 0


def _design_line(design: dict | None) -> str:
    """The designed density of a schema-2 map's ``staggered`` table in one line."""
    if not design:
        return "none (no staggered field)"
    parts = [f"staircase contrast {design['staircase_contrast']:g}" if design.get("staircase_contrast") is not None
             else "every covered cube"]
    for key, label in (("continuity_weight", "continuity weight"), ("density_amplitude", "density amplitude")):
        if design.get(key) is not None:
            parts.append(f"{label} {design[key]:g} ({design.get(key + '_mode', 'fixed')})")
    if design.get("static_velocity_nrmse") is not None:
        parts.append(f"static field velocity nRMSE {design['static_velocity_nrmse']:.3f}")
    parts.append(f"max divergence {design['max_divergence']:.1e}")
    return ", ".join(parts)


def run_keygen(args: argparse.Namespace) -> int:
    """``fisc-ground keygen``: write an Ed25519 key pair."""
    from fisc_ground.maps.write import generate_keypair

    key_path, pub_path = generate_keypair(args.output)
    print(f"wrote {key_path} (private, keep on the ground station) and {pub_path} (give to agents)")
    return 0


def run_plot(args: argparse.Namespace) -> int:
    """``fisc-ground plot``: write the map's CFD-vs-fit figures."""
    from fisc_agent.map.codec import load_map
    from fisc_ground.figures.plots import plot_map_figures

    cmap = load_map(args.map, trusted_key=args.trusted_key)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    for path in plot_map_figures(cmap, out):
        print(path)
    return 0


class _status:
    """A spinner on stderr while a step runs (silent when stderr is not a terminal)."""

    def __init__(self, text: str) -> None:
        self.text = text
        self._cm = None

    def __enter__(self):
        if sys.stderr.isatty():
            from rich.console import Console

            self._cm = Console(stderr=True).status(self.text)
            self._cm.__enter__()
        return self

    def __exit__(self, *exc):
        if self._cm is not None:
            self._cm.__exit__(*exc)
        return False


def build_parser() -> argparse.ArgumentParser:
    """The ``fisc-ground`` argument parser with every sub-command."""
    parser = argparse.ArgumentParser(prog="fisc-ground", description=__doc__.splitlines()[0], epilog=EXIT_CODES_EPILOG)
    add_logging_args(parser)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("fit", help="fit a command map from a CFD reference field",
                       description="Import REFERENCE, partition it into cubic control volumes, run the "
                                   "paper's velocity fitting and write a verified (optionally signed) map.")
    p.add_argument("reference", metavar="REFERENCE",
                   help="a built-in name (cd_nozzle_inviscid, cd_nozzle, analytic) or a file: Fluent-style "
                        "node CSV, axisymmetric CSV (x,r,u_x,u_r,p[,rho]) or VTK/VTU")
    p.add_argument("-o", "--output", required=True, type=Path, metavar="MAP", help="map file to write (.fiscmap)")
    p.add_argument("--cell-size", type=float, default=0.5, metavar="L", help="CV edge length [m] (default 0.5)")
    p.add_argument("--n-range", nargs=2, default=["2", "10"], metavar=("N_MIN", "N_MAX"),
                   help="candidate agent counts per CV (default 2 10)")
    p.add_argument("--scale", type=_scale, default=None, metavar="S|auto",
                   help="speed scaling S (default auto: largest S keeping commands within --max-speed)")
    p.add_argument("--max-speed", type=float, default=DEFAULT_MAX_SPEED_M_S, metavar="V",
                   help=f"agent speed limit [m/s] (default {DEFAULT_MAX_SPEED_M_S:g}, as fisc-sim run)")
    p.add_argument("--kappa", type=float, default=None, help="pressure mapping factor (default: auto)")
    p.add_argument("--dispersion-ratio", type=float, default=None, metavar="R",
                   help="with --kappa auto: the largest rms velocity spread the fit may ask for, as a ratio of the "
                        f"peak target speed (default {KINETIC_DISPERSION_RATIO:g}; {DEFAULT_DISPERSION_RATIO:g} with "
                        "--preset paper); a hotter swarm trades velocity for pressure and density fidelity "
                        "(docs/studies/fidelity.md, 'Velocity against density')")
    p.add_argument("--agent-mass", type=float, default=1.0, metavar="KG", help="agent mass (default 1 kg)")
    p.add_argument("--min-nodes", type=int, default=1, help="reference nodes a CV needs to exist (default 1)")
    p.add_argument("--pressure-kind", choices=["auto", "gauge", "absolute"], default="auto",
                   help="how the file states pressure (default: detect)")
    p.add_argument("--seed", type=int, default=0, help="seed of the fit's perturbed initialisation")
    p.add_argument("--sign", type=Path, metavar="KEYFILE", help="sign with this Ed25519 key (from keygen)")
    p.add_argument("--preset", choices=("default", "paper"), default="default",
                   help="default: schema-2 map with the continuity-consistent staggered field, the designed "
                        "swarm density and recommended flight settings; paper: the paper's schema-1 map")
    p.add_argument("--continuity-weight", type=number_or("auto", "auto"), default=None,
                   metavar="BETA|auto",
                   help="designed density: 0 = the CFD's density pattern, 1 = the pattern continuity allows at "
                        "the CFD velocity; higher follows the CFD velocity more closely and its density less. "
                        f"Default auto: the lowest of {', '.join(f'{b:g}' for b in AUTO_CONTINUITY_WEIGHTS)} whose "
                        f"static field at amplitude 1 keeps the velocity nRMSE within {STATIC_VELOCITY_LIMIT:g}")
    p.add_argument("--density-amplitude", type=number_or("auto", "auto"), default=None,
                   metavar="K|auto",
                   help="designed density contrast over the staircase's own; above 1 the density follows the CFD "
                        "more closely and the velocity less (docs/studies/fidelity.md, 'Velocity against density'). "
                        f"Default auto: the largest of {', '.join(f'{k:g}' for k in AUTO_DENSITY_AMPLITUDES)} whose "
                        f"static field keeps the velocity nRMSE within {STATIC_VELOCITY_BUDGET:g}")
    p.add_argument("--staircase-contrast", type=number_or("off", "off"), default=None, metavar="C|off",
                   help="designed staircase: per x slice only the most covered cubes that make the swarm's density "
                        "at the CFD velocity follow the CFD's density pattern with contrast C become CVs "
                        f"(default {DEFAULT_STAIRCASE_CONTRAST:g}); off: every cube the reference covers "
                        "(docs/staircase.md, 'The designed staircase')")
    s = p.add_argument_group("separation and size (docs/deployment.md, 'Separation and the tunnel's size')")
    s.add_argument("--vehicle-radius", type=_non_negative_m("--vehicle-radius"), default=DEFAULT_VEHICLE_RADIUS_M,
                   metavar="M", help="vehicle radius r, props included [m]; with --position-sigma it sets the spacing "
                                     "the map is designed for, d_min = 2 r + 3 sqrt(2) sigma")
    s.add_argument("--position-sigma", type=_non_negative_m("--position-sigma"), default=DEFAULT_POSITION_SIGMA_M,
                   metavar="M", help="1-sigma position error of a vehicle relative to its neighbours [m] (GNSS: "
                                     "nearby receivers share most of their error)")
    s.add_argument("--length-scale", type=positive_number("a length scale L"), default=1.0, metavar="L",
                   help="fly the same flow in an airspace L times larger: lengths and CVs x L, speeds kept within "
                        "--max-speed, times x L (the tunnel holds about L^3 times the vehicles at one d_min)")
    p.set_defaults(func=run_fit)

    p = sub.add_parser("inspect", help="verify a map and summarise it",
                       description="Verify a map (structure, schema version, sha256, signature) and summarise it: "
                                   "the reference, CVs, scaling, fit, the recommended flight settings and the "
                                   "designed density (schema 2). Any failed check exits 2 with the reason.")
    p.add_argument("map", metavar="MAP", type=Path)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--compact", action="store_true", help="with --json: one line")
    p.add_argument("--trusted-key", type=Path, metavar="PUB", help="require a valid signature by this key")
    p.set_defaults(func=run_inspect)

    p = sub.add_parser("keygen", help="create an Ed25519 ground key pair",
                       description="Write NAME.key (private) and NAME.pub (public) for signing maps and commands.")
    p.add_argument("-o", "--output", required=True, metavar="NAME", help="path stem of the key files")
    p.set_defaults(func=run_keygen)

    p = sub.add_parser("plot", help="draw CFD-target vs fitted fields of a map (PNG)",
                       description="XZ-plane contours of CFD target vs fitted velocity, pressure, density and N* "
                                   "(the paper's figures 5a/5b, 7a/7b, 8a/8b) with the CV grid.")
    p.add_argument("map", metavar="MAP", type=Path)
    p.add_argument("-o", "--output", required=True, metavar="DIR", help="output folder")
    p.add_argument("--trusted-key", type=Path, metavar="PUB", help="require a valid signature by this key")
    p.set_defaults(func=run_plot)

    p = sub.add_parser("score-flight", help="score flown passes (fisc-agent --flight-log) against the CFD",
                       description="Per flight log: crossed without a hold, largest excursion outside the duct wall, "
                                   "axial-velocity nRMSE against S x the CFD (by the autopilot's velocity estimate, "
                                   "and by the GNSS receiver's own velocity where the log has it), crossing time "
                                   "(fisc_ground.fields.flight_score).")
    p.add_argument("logs", metavar="LOG", type=Path, nargs="+", help="flight log CSV files")
    p.add_argument("--map", required=True, type=Path, help="the map flown (its scale S and reference)")
    p.add_argument("--reference", help="reference flow (default: the one recorded in the map)")
    p.add_argument("--x-range", nargs=2, type=float, default=(0.0, 15.0), metavar=("X_LO", "X_HI"),
                   help="the duct's axial extent scored [m]")
    p.add_argument("--json", action="store_true", help="print one JSON object per log (and one 'fleet' object)")
    p.add_argument("--period", type=positive_number("seconds"), default=0.1, metavar="S",
                   help="common time base of several logs for the fleet's closest approach [s]")
    p.add_argument("--max-gap", type=positive_number("seconds"), default=1.0, metavar="S",
                   help="a vehicle's positions are not interpolated across gaps longer than this [s]")
    p.set_defaults(func=run_score_flight)

    try:
        from fisc_ground.zenoh.cli import add_parsers
    except ImportError as exc:  # the Zenoh commands need eclipse-zenoh
        log.debug("zenoh commands unavailable: %s", exc)
    else:
        add_parsers(sub)
    for p in sub.choices.values():  # the logging options also after the command's name
        add_logging_args(p, subcommand=True)
    return parser


def main(argv: list[str] | None = None) -> int:
    """``fisc-ground`` entry point; returns the exit code (``fisc_agent.common.cli_common``)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    setup_logging(args)
    from fisc_agent.map.codec import MapError

    try:
        return int(args.func(args) or 0)
    except (MapError, FileExistsError, FileNotFoundError, ValueError) as exc:  # ReferenceError is a ValueError
        print(f"fisc-ground {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except ModuleNotFoundError as exc:
        if missing_extra(exc) is None:
            raise
        print(missing_dependency_message(f"fisc-ground {args.command}", exc), file=sys.stderr)
        return EXIT_FAILURE


def console() -> None:
    """The ``fisc-ground`` console script (``pyproject.toml``): ``main()`` through ``console_exit``."""
    console_exit(main)


if __name__ == "__main__":
    console()
