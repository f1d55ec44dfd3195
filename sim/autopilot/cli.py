"""``fisc-sim autopilot``: run one emulated PX4/ArduPilot autopilot on a MAVLink endpoint.

The lead wires :func:`add_parser` into the ``fisc-sim`` argparse tree; :func:`run` serves in real
time until SIGINT/SIGTERM and returns the process exit code.  ``python -m sim.autopilot.cli``
runs it stand-alone (same options).
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from typing import Sequence

from fisc_agent.common.cli_common import EXIT_CODES_EPILOG, EXIT_USAGE, add_logging_args, setup_logging
from sim.autopilot.faults import parse_dropout
from sim.autopilot.server import DEFAULT_HOME_LLA, AutopilotEmulator

__all__ = ["add_parser", "configure_parser", "run", "main"]

_log = logging.getLogger(__name__)


def _triple(text: str) -> tuple[float, float, float]:
    parts = text.split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected three comma-separated numbers") from None
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"{text!r}: expected three comma-separated numbers, got {len(values)}")
    return values  # type: ignore[return-value]


def _dropout(text: str) -> tuple[float, float]:
    try:
        return parse_dropout(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _probability(text: str) -> float:
    try:
        p = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0.0 <= p <= 1.0:
        raise argparse.ArgumentTypeError(f"loss probability must be in [0, 1], got {p}")
    return p


def configure_parser(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``autopilot`` options to ``p``."""
    p.add_argument("--mavlink", required=True, metavar="URL",
                   help="endpoint: udpin:HOST:PORT, udpout:HOST:PORT, tcpin:HOST:PORT, tcp:HOST:PORT "
                        "(e.g. udpout:127.0.0.1:14540 to reach MAVSDK's udpin://0.0.0.0:14540)")
    p.add_argument("--personality", choices=("px4", "ardupilot"), default="px4",
                   help="autopilot to emulate (default px4)")
    p.add_argument("--start", type=_triple, default=(0.0, 0.0, 0.0), metavar="N,E,D",
                   help="start position in local NED [m] (default 0,0,0 on the ground; D<0 starts airborne, armed, holding)")
    p.add_argument("--home", type=_triple, default=DEFAULT_HOME_LLA, metavar="LAT,LON,ALT",
                   help="geodetic origin of local NED [deg, deg, m AMSL] (default PX4 SITL's Zurich)")
    p.add_argument("--sysid", type=int, default=1, help="MAVLink system id (default 1)")
    p.add_argument("--rate-position", type=float, default=20.0, metavar="HZ",
                   help="LOCAL_POSITION_NED / GLOBAL_POSITION_INT rate [Hz] (default 20)")
    p.add_argument("--rate-attitude", type=float, default=10.0, metavar="HZ", help="ATTITUDE rate [Hz] (default 10)")
    p.add_argument("--loss", type=_probability, default=0.0, metavar="P",
                   help="drop each incoming and outgoing message with probability P (default 0)")
    p.add_argument("--latency", type=float, default=0.0, metavar="S", help="delay outgoing messages by S seconds")
    p.add_argument("--position-dropout", type=_dropout, action="append", default=[], metavar="START,DURATION",
                   help="no position messages (and no position estimate) from START for DURATION seconds "
                        "after start; repeatable")
    p.add_argument("--seed", type=int, default=0, help="seed of the packet-loss random stream (default 0)")
    add_logging_args(p, subcommand=True)
    p.set_defaults(func=run)
    return p


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``autopilot`` sub-command on a ``fisc-sim`` subparsers object."""
    p = subparsers.add_parser(
        "autopilot",
        help="MAVLink autopilot emulator (PX4 / ArduPilot Copter) on the velocity plant",
        description="Emulate a PX4 or ArduPilot Copter autopilot flying the paper's VelocityPlant, "
                    "in real time, until SIGINT/SIGTERM. See docs/autopilot_emulator.md.",
    )
    return configure_parser(p)


def run(args: argparse.Namespace) -> int:
    """Serve until SIGINT/SIGTERM; returns the exit code (0 clean, 2 bad endpoint/options)."""
    setup_logging(args, fmt="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        emulator = AutopilotEmulator(
            args.mavlink, args.personality, tuple(args.start), sysid=args.sysid, home_lla=tuple(args.home),
            rate_position_hz=args.rate_position, rate_attitude_hz=args.rate_attitude, loss=args.loss,
            latency_s=args.latency, position_dropouts=tuple(args.position_dropout), seed=args.seed,
        )  # fmt: skip
        emulator.open()
    except (ValueError, OSError) as exc:
        _log.error("autopilot: %s", exc)
        return EXIT_USAGE
    stop = threading.Event()

    def _handle(signum: int, _frame: object) -> None:
        _log.info("autopilot: signal %d, stopping", signum)
        stop.set()

    previous = {s: signal.signal(s, _handle) for s in (signal.SIGINT, signal.SIGTERM)}
    host, port = emulator.local_address
    _log.info("autopilot %s sysid %d serving %s (local %s:%d)", args.personality, args.sysid, args.mavlink, host, port)
    try:
        emulator.run(stop)
    finally:
        emulator.stop()
        for s, h in previous.items():
            signal.signal(s, h)
    _log.info("autopilot: stopped (%s)", emulator.stats)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Stand-alone entry point (``python -m sim.autopilot.cli``)."""
    parser = configure_parser(argparse.ArgumentParser(prog="fisc-sim autopilot", epilog=EXIT_CODES_EPILOG))
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
