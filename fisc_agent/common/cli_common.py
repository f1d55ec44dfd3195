"""Conventions shared by the three command lines (``fisc-agent``, ``fisc-ground``, ``fisc-sim``).

One logging convention (``-v``/``-q`` counted, or ``--log-level``), one output flag
(``-o/--output``, older spellings kept as hidden aliases), one exit-code table, figures in final
summary lines rounded to three significant digits, one message for a missing optional
dependency that names the extra to install, and one way for a console script to end
(``console_exit``).  Standard library only: ``fisc_agent`` stays lean.

Exit codes (README "Exit codes"):

==== =====================================================================
0    success
1    runtime failure (a mission failed, a run could not finish, a missing
     optional dependency)
2    bad usage or invalid input (options, map, reference file, endpoint)
==== =====================================================================
"""

from __future__ import annotations

import argparse
import gc
import logging
import math
import sys
from collections.abc import Callable
from enum import IntEnum
from typing import NoReturn


class ExitCode(IntEnum):
    """The one exit-code table of the three command lines."""

    OK = 0
    """Success (a ``fisc-agent`` mission finished, or was stopped by SIGINT/SIGTERM)."""
    FAILURE = 1
    """Runtime failure (e.g. ``Mission.failed``: could not arm)."""
    USAGE = 2
    """Bad usage or invalid input: options, map, reference file, endpoint (argparse's own code)."""


EXIT_OK, EXIT_FAILURE, EXIT_USAGE = ExitCode.OK, ExitCode.FAILURE, ExitCode.USAGE

EXIT_CODES_EPILOG = "Exit codes: 0 ok, 1 runtime failure, 2 bad usage or invalid input."
"""One line for every parser's epilog."""

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
"""Choices of ``--log-level``."""

#: Optional modules and the extra of ``pyproject.toml`` that installs each.
EXTRA_OF_MODULE = {
    "scipy": "ground",
    "matplotlib": "ground",
    "meshio": "ground",
    "rich": "ground",
    "foxglove": "ground",
    "mcap": "ground",
    "numba": "jit",
    "dask": "sweep",
    "distributed": "sweep",
    "mavsdk": "mavsdk",
}


def console_exit(main: Callable[[], int]) -> NoReturn:
    """Run a command line's ``main()`` as its console script and exit with its code, without the
    interpreter's garbage-collection passes at shutdown.

    At exit Python collects over every object still alive; after ``fisc-sim run`` (matplotlib,
    numba, scipy loaded: 140 000-210 000 objects) that took 0.45-0.6 s of a 10 s job.
    ``gc.freeze`` moves them out of the collector's reach first (measured: 0.05 s).  Shutdown is
    otherwise unchanged: ``atexit`` handlers run, logging flushes, files are closed.  ``main(argv)``,
    which tests call in-process, does not touch the collector: only the console script does, as the
    process ends."""
    code = main()
    gc.freeze()
    sys.exit(code)


def add_logging_args(parser: argparse.ArgumentParser, *, subcommand: bool = False) -> None:
    """Add ``-v/--verbose``, ``-q/--quiet`` (both counted) and ``--log-level`` to ``parser``.

    ``subcommand``: the parser is a sub-command's; its defaults are suppressed so the options work
    before or after the sub-command's name without one overriding the other.
    """
    default = argparse.SUPPRESS if subcommand else None
    g = parser.add_argument_group("logging")
    g.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS if subcommand else 0,
                   help="more logging (-v: DEBUG)")
    g.add_argument("-q", "--quiet", action="count", default=argparse.SUPPRESS if subcommand else 0,
                   help="less output: no progress bar; -q: WARNING, -qq: ERROR")
    g.add_argument("--log-level", choices=LOG_LEVELS, type=str.upper, default=default,
                   help="logging threshold (overrides -v/-q; default INFO)")


def log_level(args: argparse.Namespace, default: int = logging.INFO) -> int:
    """The logging level of parsed ``add_logging_args`` options."""
    name = getattr(args, "log_level", None)
    if name:
        return getattr(logging, name)
    steps = getattr(args, "quiet", 0) - getattr(args, "verbose", 0)
    return min(logging.ERROR, max(logging.DEBUG, default + 10 * steps))


def setup_logging(args: argparse.Namespace, default: int = logging.INFO,
                  fmt: str = "%(levelname)s %(name)s: %(message)s") -> int:
    """Configure the root logger from ``args`` (see ``log_level``); returns the level."""
    level = log_level(args, default)
    logging.basicConfig(level=level, format=fmt)
    logging.getLogger().setLevel(level)
    return level


def add_output_arg(parser: argparse.ArgumentParser, *, aliases: tuple[str, ...] = (), **kwargs) -> argparse.Action:
    """Add the one output flag ``-o/--output`` (dest ``output``); ``aliases`` are older spellings
    that still parse but are not shown in ``--help``."""
    action = parser.add_argument("-o", "--output", *aliases, dest="output", **kwargs)
    action.option_strings = ["-o", "--output"]  # aliases stay registered for parsing, hidden from help
    return action


def number_or(word: str, value: object, what: str = "a number") -> Callable[[str], object]:
    """An argparse type: a number (its range is checked by the command's config dataclass), or ``word``
    standing for ``value`` (``auto``, ``off``).  A bad value reads ``argument --flag: expected <what> or
    '<word>', got '<text>'``."""
    def parse(text: str) -> object:
        if text == word:
            return value
        try:
            return float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what} or {word!r}, got {text!r}") from None
    return parse


def positive_number(what: str = "a number") -> Callable[[str], float]:
    """An argparse type: a finite number > 0; a bad value reads ``argument --flag: expected <what>
    (a finite number > 0), got '<text>'``."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value > 0):
            raise argparse.ArgumentTypeError(f"expected {what} (a finite number > 0), got {text!r}")
        return value
    return parse


def sig3(value: float | int | None) -> str:
    """``value`` rounded to three significant digits for a summary line (``n/a`` when missing;
    integers, which are counts, stay exact)."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    if isinstance(value, int):
        return str(value)
    return f"{float(value):.3g}"


def missing_extra(exc: ModuleNotFoundError) -> str | None:
    """The ``pyproject.toml`` extra that installs the module ``exc`` did not find, or None."""
    name = (exc.name or "").split(".")[0]
    return EXTRA_OF_MODULE.get(name)


def missing_dependency_message(prog: str, exc: ModuleNotFoundError, umbrella: str | None = None) -> str:
    """``prog: error: ... needs the optional package X ...: pip install 'fisc[EXTRA]'`` (callers re-raise
    ``exc`` when no extra installs the module).  ``umbrella``: an extra that contains ``ground`` and
    ``jit`` (``sim``), named instead of them so one install brings everything the command needs."""
    extra = missing_extra(exc)
    if umbrella is not None and extra in ("ground", "jit"):
        extra = umbrella
    return (f"{prog}: error: this command needs the optional package {exc.name!r}, "
            f"not installed here: pip install 'fisc[{extra}]'")
