"""``fisc-sim``: the simulator's command line (thin: argument parsing and progress only).

Subcommands: ``run`` (sim.run), ``bench`` (sim.bench), ``autopilot`` (sim.autopilot.cli, the
MAVLink autopilot emulator) and ``emulate`` (sim.emulate.cli, a swarm of emulated autopilots).
"""

from __future__ import annotations

import argparse
import math
import sys
from contextlib import contextmanager

from fisc_agent.common.cli_common import (EXIT_CODES_EPILOG, EXIT_FAILURE, EXIT_USAGE, add_logging_args, add_output_arg,
                                   console_exit, missing_dependency_message, missing_extra, setup_logging, sig3)
from fisc_agent.map.lookup import COMMAND_MODES
from sim.plant.fit import PLANT_PRESETS
from sim.run import RESERVOIR_DURATION_S, RESERVOIR_WINDOW_S


def _agents(text: str):
    """--agents: a non-negative integer or 'fitted' (N* as fitted)."""
    if text == "fitted":
        return "fitted"
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--agents: an integer or 'fitted', got {text!r}") from None


def _add_run(sub) -> None:
    p = sub.add_parser("run", help="simulate a swarm on a command map and write fields, metrics, report, figures",
                       description="Paper Case 2 (reservoir) or Case 1 (seed) on a command map; with no options the "
                                   "paper's Case 2 on the embedded default map for 300 s, written to out/run.")
    p.add_argument("--map", default=None, help="a .fiscmap file, or a reference (built-in name such as cd_nozzle, "
                                               "or a CFD file) fitted now; default: the embedded default map")
    p.add_argument("--scenario", choices=("reservoir", "seed"), default="reservoir",
                   help="reservoir = paper Case 2 (default), seed = paper Case 1")
    p.add_argument("--agents", type=_agents, default=None,
                   help="population target N: N* scaled by N / sum N* (seed: exactly N seeded; reservoir: source "
                        "rate scaled alike), or 'fitted' for N* as fitted. Default 1000 (the paper's population)")
    p.add_argument("--duration", type=float, default=None,
                   help=f"simulated seconds (default: {RESERVOIR_DURATION_S:g} for reservoir, 20 for seed)")
    p.add_argument("--average-window", type=float, default=None,
                   help=f"time-average the fields over the last S seconds (default: {RESERVOIR_WINDOW_S:g} for "
                        "reservoir, the whole run for seed)")
    p.add_argument("--plant", choices=tuple(PLANT_PRESETS), default="paper",
                   help="vehicle model: the paper's quadrotor, or px4-sih (fitted to real PX4 SITL flights with stock "
                        "parameters; px4-sih-tuned: a tuned velocity loop; sim.plant.fit)")
    p.add_argument("--preset", choices=("default", "paper"), default="default",
                   help="default: schema-2 map (continuity-consistent staggered field, designed density) flown "
                        "with its recommended settings; paper: the paper's Algorithm 1 (schema-1 map, mean "
                        "commands, no look-ahead)")
    p.add_argument("--mode", choices=COMMAND_MODES, default=None,
                   help="command mode (default: the map's recommended one; see --preset)")
    p.add_argument("--collisions", action="store_true", help="enable the collision layer")
    p.add_argument("--safety-net", action="store_true",
                   help="fly the agents' separation safety net (fisc_agent.flight.safety_net, the map's d_min) "
                        "between the command and the plant; metrics.json reports safety_net_acting_fraction")
    p.add_argument("--staggered-admission", action="store_true",
                   help="reservoir: admit one agent per the map's admission period (fisc-ground inspect), as "
                        "fisc-agent --entry-stagger auto does, instead of the paper's source-rate batches")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--scale", type=float, default=None, help="override the map's speed scale S (paper: 0.1)")
    p.add_argument("--max-speed", type=float, default=None,
                   help="agent speed limit [m/s] setting S of a map fitted by the run (no --map, or a reference "
                        "spec; default 2 = the paper's speed regime); a .fiscmap keeps its S")
    p.add_argument("--lookahead", type=float, default=None, metavar="SECONDS",
                   help="command look-ahead t_lead [s]: fly the command at x + u t_lead to compensate the plant "
                        "lag (default: the map's recommended value, 0.5 s; 0 with --preset paper)")
    p.add_argument("--x-axial", type=float, default=math.inf, help="seed: fill CVs with centre x <= this [m]")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    add_output_arg(p, aliases=("--out",), default="out/run", help="output directory (default out/run)")
    p.add_argument("--mcap", default=None, metavar="FILE",
                   help="also write the run as a Foxglove/MCAP flight log (the channels of fisc-ground monitor "
                        "--record; fisc-ground replay reads it)")


def _add_bench(sub) -> None:
    p = sub.add_parser("bench", help="agent-steps/s of the swarm core at 1e3..1e6 agents, the paper run, RotorPy")
    p.add_argument("--sizes", default="1e3,1e4,1e5,1e6", help="comma-separated agent counts")
    p.add_argument("--steps", type=int, default=20, help="steps per size (default 20)")
    p.add_argument("--no-rotorpy", action="store_true", help="skip the RotorPy comparison")
    p.add_argument("--no-paper-run", action="store_true",
                   help="skip the timings of the paper's run (paper preset and default)")


@contextmanager
def _progress(enabled: bool, label: str):
    if not enabled:
        yield None
        return
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    with Progress(TextColumn(label), BarColumn(), TextColumn("{task.percentage:>3.0f}%"), TimeElapsedColumn(),
                  TimeRemainingColumn(), transient=False) as prog:
        task = prog.add_task(label, total=1.0)
        yield lambda frac: prog.update(task, completed=frac)


def run_config_from_args(args: argparse.Namespace):
    """The ``sim.run.RunConfig`` of parsed ``fisc-sim run`` arguments (``ValueError`` names a bad option)."""
    from sim.run import RunConfig

    extra = {}
    if args.agents is not None:
        extra["agents"] = None if args.agents == "fitted" else args.agents
    if args.max_speed is not None:
        extra["max_speed_m_s"] = args.max_speed
    return RunConfig(map=args.map, scenario=args.scenario, duration_s=args.duration,
                     average_window_s=args.average_window, mode=args.mode, collisions=args.collisions,
                     safety_net=args.safety_net, staggered_admission=args.staggered_admission,
                     seed=args.seed, scale=args.scale, x_axial_m=args.x_axial,
                     figures=not args.no_figures,
                     lookahead_s=args.lookahead, preset=args.preset, plant=args.plant, out_dir=args.output,
                     mcap=args.mcap, **extra)


def _cmd_run(args) -> int:
    from sim.run import run

    cfg = run_config_from_args(args)
    show = not args.quiet and sys.stderr.isatty()
    with _progress(show, f"{cfg.scenario}/{cfg.preset}") as cb:
        res = run(cfg, progress=cb)
    m = res.metrics
    a = m["agents"]
    print(f"wrote {args.output}: nRMSE velocity {sig3(m['nrmse_velocity'])}, pressure {sig3(m['nrmse_pressure'])}, "
          f"density {sig3(m['nrmse_density'])}; agents injected {a['injected']} exited {a['exited']} "
          f"escaped {a['escaped']} alive {a['alive']}; {sig3(m['wall_time_s'])} s wall")
    return 0


def _cmd_bench(args) -> int:
    from sim.bench import run_bench

    sizes = [int(float(s)) for s in args.sizes.split(",") if s.strip()]
    for line in run_bench(sizes, steps=args.steps, rotorpy=not args.no_rotorpy, paper_run=not args.no_paper_run):
        print(line, flush=True)
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``fisc-sim`` argument parser with every sub-command."""
    parser = argparse.ArgumentParser(prog="fisc-sim", description="FISC headless swarm simulator",
                                     epilog=EXIT_CODES_EPILOG)
    add_logging_args(parser)
    sub = parser.add_subparsers(dest="command", required=True)
    _add_run(sub)
    _add_bench(sub)
    # `fisc-sim autopilot`: the MAVLink autopilot emulator (sim/autopilot/cli.py)
    from sim.autopilot import cli as autopilot_cli

    autopilot_cli.add_parser(sub)
    # `fisc-sim emulate`: a swarm of emulated autopilots flown by real agents (sim/emulate/cli.py)
    from sim.emulate import cli as emulate_cli

    emulate_cli.add_parser(sub)
    from sim.sweep import cli as sweep_cli  # `fisc-sim sweep`: run grids on dask (sim/sweep/cli.py)

    sweep_cli.add_parser(sub)
    for p in sub.choices.values():  # the logging options also after the command's name
        if "--log-level" not in p._option_string_actions:
            add_logging_args(p, subcommand=True)
    return parser


def main(argv: list[str] | None = None) -> int:
    """``fisc-sim`` entry point; returns the exit code (``fisc_agent.common.cli_common``)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    setup_logging(args, fmt="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return _dispatch(parser, args)
    except ModuleNotFoundError as exc:
        if missing_extra(exc) is None:
            raise
        print(missing_dependency_message(f"fisc-sim {args.command}", exc, umbrella="sim"), file=sys.stderr)
        return EXIT_FAILURE


def _dispatch(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    if args.command == "run":
        try:
            return _cmd_run(args)
        except ValueError as exc:  # bad options, a map that fails a check (MapError), a mode the map lacks
            print(f"fisc-sim run: error: {exc}", file=sys.stderr)
            return EXIT_USAGE
    if args.command == "bench":
        return _cmd_bench(args)
    if args.command == "autopilot":
        from sim.autopilot import cli as autopilot_cli

        return int(autopilot_cli.run(args) or 0)
    if args.command == "emulate":
        from sim.emulate import cli as emulate_cli

        return int(emulate_cli.run(args) or 0)
    if args.command == "sweep":
        from sim.sweep import cli as sweep_cli

        return sweep_cli.run(args)
    parser.error(f"unknown command {args.command}")
    return EXIT_USAGE


def console() -> None:
    """The ``fisc-sim`` console script (``pyproject.toml``): ``main()`` through ``console_exit``."""
    console_exit(main)


if __name__ == "__main__":
    console()
