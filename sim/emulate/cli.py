"""``fisc-sim emulate``: argument parsing and progress for ``sim.emulate`` (thin).

Wiring (in sim/cli.py)::

    from sim.emulate import cli as emulate_cli
    emulate_cli.add_parser(sub)                    # in build_parser
    if args.command == "emulate":
        return emulate_cli.run(args)               # in main
"""

from __future__ import annotations

import argparse
import sys

from fisc_agent.common.cli_common import EXIT_OK, EXIT_USAGE, add_output_arg, sig3
from fisc_agent.config import EXIT_POLICIES
from fisc_agent.map.lookup import COMMAND_MODES
from fisc_agent.common.names import prefix_arg, swarm_name_arg
from sim.emulate.config import PLANTS, EmulateConfig


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``emulate`` on the ``fisc-sim`` subparsers; returns the new parser."""
    p = subparsers.add_parser(
        "emulate", help="emulated swarm with MAVLink in the loop: N autopilot emulators + N fisc-agents",
        description="N autopilot emulators (PX4/ArduPilot personality, the paper's velocity plant) and N fisc-agent "
                    "control loops talking real MAVLink over loopback UDP fly the paper's Case 2 (vehicles take off "
                    "on the ground upstream of the inlet, join at the inlet at the source rate, flow, loop back) in "
                    "real time; writes the fisc-sim run outputs (fields.csv, metrics.json, figures, report.md) plus "
                    "emulation.json and comparison.json (difference to fisc-sim run on the same map with as many agents flowing).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--map", default=None,
                   help="a .fiscmap file, or a reference (built-in name or CFD file) fitted now; default: the embedded "
                        "default map (written to OUT/map.fiscmap for the agents)")
    p.add_argument("--agents", type=int, required=True, help="number of vehicles N (emulator + agent pairs)")
    p.add_argument("--duration", type=float, default=EmulateConfig.duration_s,
                   help=f"real seconds flown from the first launch (default {EmulateConfig.duration_s:g})")
    p.add_argument("--mode", choices=COMMAND_MODES, default=None,
                   help="agent command mode (default: the map's recommended mode)")
    p.add_argument("--lookahead", type=float, default=None, metavar="SECONDS",
                   help="agents' command look-ahead [s] (default: the map's recommended value)")
    p.add_argument("--preset", choices=("default", "paper"), default="default",
                   help="paper: the paper's schema-1 map flown with Algorithm 1 (mean, no look-ahead)")
    p.add_argument("--autopilot", choices=("px4", "ardupilot"), default="px4", help="personality of the emulators")
    p.add_argument("--plant", choices=PLANTS, default="paper",
                   help="vehicle model inside the emulators: the paper's quadrotor, or px4-sih (fitted to real PX4 "
                        "SITL flights with stock parameters; px4-sih-tuned: a tuned velocity loop; sim.plant.fit), "
                        "or px4-sih-loop (stock PX4's velocity PID on SIH's linear drag, which flies the agents' drag "
                        "feed-forward as PX4 does; sim.plant.px4_loop; --autopilot px4)")
    p.add_argument("--exit-policy", choices=EXIT_POLICIES, default="loop",
                   help="after the outlet: loop (fly back to the inlet), hold or land")
    p.add_argument("--open-loop", action="store_true",
                   help="agents fly fisc-sim run's command function at their position, without streamline tracking "
                        "(fisc-agent's default on a real vehicle, kept by default here)")
    p.add_argument("--entry-radius-fraction", type=float, default=EmulateConfig.entry_radius_fraction, metavar="F",
                   help="agents' entry points spread over this fraction of the inlet radius (1: every inlet CV, as "
                        "fisc-sim run injects; fisc-agent's default 0.6 keeps a real duct's wall clear)")
    p.add_argument("--fleet-mode", action="store_true",
                   help="agents fly as fisc-agent does on a real fleet: they resolve the map's recommended mode "
                        "themselves (a recommended kinetic flown on the staggered field, without its deviations) and "
                        "turn an explicit --mode kinetic's deviations within fisc-agent's wall margin; default: the "
                        "recommendation is given to them explicitly and its deviations reflect at the CV staircase, "
                        "as fisc-sim run's agents do")
    p.add_argument("--staggered-admission", action="store_true",
                   help="agents admit themselves from the map's admission budget (each in its entry window, "
                        "fisc-agent's default --entry-stagger auto), first passes and laps alike, as a real fleet "
                        "does; default: launches at the paper's source rate, as fisc-sim run's reservoir")
    p.add_argument("--start-spacing", type=float, default=EmulateConfig.start_spacing_m, metavar="M",
                   help="spacing of the ground start grid [m] (with --staggered-admission the joins wait for "
                        "their windows above it; default %(default)s)")
    p.add_argument("--geofence", choices=("return", "hold"), default=None,
                   help="agents leaving the CVs: return (fly back to the nearest CV, as fisc-sim run's return policy) "
                        "or hold; default: fisc-agent's (hold) with --fleet-mode, else return")
    p.add_argument("--rate", type=float, default=20.0, help="agent setpoint rate [Hz]")
    p.add_argument("--average-window", type=float, default=EmulateConfig.average_window_s,
                   help="time-average the fields over the last S seconds, as fisc-sim run "
                        f"(default {EmulateConfig.average_window_s:g})")
    p.add_argument("--estimate-error", action="store_true",
                   help="the emulated autopilots fly and report a state estimate that strays from the truth as stock "
                        "PX4's on SIH does (velocity 0.14/0.30/0.17 m/s N/E/D, ~3-4 s correlation; their GNSS "
                        "receivers report the truth); fields and profile then come from what they report, as a "
                        "ground station sees a real fleet")
    p.add_argument("--telemetry", choices=("full", "lean"), default="full",
                   help="full: the autopilots' default streams; lean: agents switch all but HEARTBEAT and "
                        "LOCAL_POSITION_NED off")
    p.add_argument("--physics-rate", type=float, default=50.0, help="emulator service rate [Hz]")
    p.add_argument("--physics-dt", type=float, default=0.02, help="emulated vehicle physics step [s]")
    p.add_argument("--workers", type=int, default=0,
                   help="processes for the emulators and, as many, for the agents (0: automatic)")
    p.add_argument("--no-compare", action="store_true", help="skip the fisc-sim run reference and comparison.json")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.add_argument("--seed", type=int, default=0, help="seed of the (first) reference fisc-sim run")
    p.add_argument("--reference-seeds", type=int, default=EmulateConfig.reference_seeds, metavar="K",
                   help="fisc-sim run references (seeds SEED..SEED+K-1) whose mean and spread the comparison uses")
    z = p.add_argument_group("Zenoh (watch the emulated fleet with fisc-ground monitor / status)")
    z.add_argument("--swarm", type=swarm_name_arg, metavar="NAME", help="publish each agent's telemetry on <prefix>/NAME/agents/<id>/telemetry")
    z.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config of the agents' sessions "
                   "(omitted: the lab default: meet at tcp/127.0.0.1:7447, then link directly)")
    z.add_argument("--safety-net", action="store_true",
                   help="the agents fly the separation safety net, hearing each other's telemetry (needs --swarm; "
                        "fisc-agent's default on a real fleet)")
    z.add_argument("--zenoh-prefix", type=prefix_arg, default="fisc", help="key expression prefix")
    z.add_argument("--telemetry-rate", type=float, default=5.0, metavar="HZ", help="telemetry rate per agent")
    z.add_argument("--trusted-key", metavar="PUB", help="ground public key the agents trust for maps and fleet "
                   "commands (required with --swarm)")
    add_output_arg(p, aliases=("--out",), required=True, help="output directory")
    p.add_argument("--mcap", default=None, metavar="FILE",
                   help="also write the flight as a Foxglove/MCAP flight log (the states the emulators report, the truth "
                        "unless --estimate-error, as telemetry: the channels of fisc-ground monitor --record)")
    p.add_argument("--flight-logs", default=None, metavar="DIR",
                   help="write each agent's own flight log to DIR/agent_<id>.csv (the CSV of fisc-agent "
                        "--flight-log: state, reported position/velocity, setpoint, CV, tracking parcel per tick)")
    return p


def config_from_args(args: argparse.Namespace):
    """The ``EmulateConfig`` of parsed arguments (``ValueError`` names a bad option)."""
    from sim.emulate import EmulateConfig

    return EmulateConfig(out_dir=args.output, map=args.map, agents=args.agents, duration_s=args.duration,
                         mode=args.mode, lookahead_s=args.lookahead, preset=args.preset, personality=args.autopilot, exit_policy=args.exit_policy,
                         geofence=args.geofence, tracking=not args.open_loop, safety_net=args.safety_net,
                         staggered_admission=args.staggered_admission, start_spacing_m=args.start_spacing,
                         fleet_mode=args.fleet_mode, estimate_error=args.estimate_error,
                         entry_radius_fraction=args.entry_radius_fraction,
                         rate_hz=args.rate, average_window_s=args.average_window, telemetry=args.telemetry,
                         physics_rate_hz=args.physics_rate, physics_dt_s=args.physics_dt, plant=args.plant,
                         emulator_workers=args.workers, agent_workers=args.workers,
                         compare=not args.no_compare, figures=not args.no_figures, seed=args.seed,
                         reference_seeds=args.reference_seeds,
                         swarm=args.swarm, zenoh_config=args.zenoh_config, zenoh_prefix=args.zenoh_prefix,
                         telemetry_rate_hz=args.telemetry_rate, trusted_key=args.trusted_key, mcap=args.mcap,
                         flight_logs=args.flight_logs)


def run(args: argparse.Namespace) -> int:
    """Run ``fisc-sim emulate``; prints a one-line summary; returns the exit code."""
    from sim.emulate import run as emulate

    try:
        cfg = config_from_args(args)
    except ValueError as exc:
        print(f"fisc-sim emulate: {exc}", file=sys.stderr)
        return EXIT_USAGE
    from fisc_agent.map.codec import MapError
    from fisc_ground.reference.field import ReferenceError

    show = not getattr(args, "quiet", 0) and sys.stderr.isatty()
    try:
        if show:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

            with Progress(TextColumn(f"emulate {cfg.agents} vehicles"), BarColumn(),
                          TextColumn("{task.percentage:>3.0f}%"), TimeElapsedColumn(), TimeRemainingColumn()) as prog:
                task = prog.add_task("emulate", total=1.0)
                res = emulate(cfg, progress=lambda f: prog.update(task, completed=f))
        else:
            res = emulate(cfg)
    except (MapError, ReferenceError) as exc:  # a bad --map file or reference: the reason, no traceback
        print(f"fisc-sim emulate: {exc}", file=sys.stderr)
        return EXIT_USAGE
    m, rt, en = res.run_result.metrics, res.realtime, res.entries
    print(f"wrote {args.output}: {en['vehicles_entered']}/{cfg.agents} vehicles entered the tunnel "
          f"({en['entries_total']} entries); nRMSE velocity {sig3(m['nrmse_velocity'])}, pressure "
          f"{sig3(m['nrmse_pressure'])}, density {sig3(m['nrmse_density'])}; real time "
          f"{'kept' if rt['keeps_real_time'] else 'NOT kept'} (setpoints {sig3(rt['setpoint_rate_mean_hz'])} Hz at the "
          f"autopilots, {sig3(1e3 * rt['cpu_per_agent'])} ms CPU per vehicle-second)")
    return EXIT_OK
