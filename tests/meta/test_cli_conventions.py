"""The conventions shared by the three CLIs (issue 10 part 5, ``fisc_agent.common.cli_common``)."""

from __future__ import annotations

import argparse
import logging

import pytest

from fisc_agent.common.cli_common import log_level, missing_dependency_message, sig3


def _all_parsers() -> dict[str, argparse.ArgumentParser]:
    from fisc_agent.cli import build_parser as agent
    from fisc_ground.cli import build_parser as ground
    from sim.cli import build_parser as simcli

    out = {"fisc-agent": agent()}
    for prog, parser in (("fisc-ground", ground()), ("fisc-sim", simcli())):
        out[prog] = parser
        for a in parser._actions:
            if isinstance(a, argparse._SubParsersAction):
                out.update({f"{prog} {name}": p for name, p in a.choices.items()})
    return out


def test_every_command_has_the_logging_options():
    parsers = _all_parsers()
    assert len(parsers) >= 15
    missing = {name: [o for o in ("-v", "-q", "--log-level") if o not in p._option_string_actions]
               for name, p in parsers.items()}
    assert not {k: v for k, v in missing.items() if v}, missing


def test_output_is_spelled_dash_o_dash_dash_output():
    shown = {}
    for name, p in _all_parsers().items():
        for a in p._actions:
            if "-o" in a.option_strings or a.dest in ("out", "output", "out_dir"):
                shown[name] = a.option_strings
    assert shown and all(opts == ["-o", "--output"] for opts in shown.values()), shown
    parsers = _all_parsers()
    assert parsers["fisc-sim run"].parse_args(["--out", "x"]).output == "x"  # the old spelling still parses


@pytest.mark.parametrize("argv, level", [([], logging.INFO), (["-v"], logging.DEBUG), (["-q"], logging.WARNING),
                                         (["-qq"], logging.ERROR), (["-v", "--log-level", "error"], logging.ERROR)])
def test_logging_levels(argv, level):
    from sim.cli import build_parser

    assert log_level(build_parser().parse_args([*argv, "bench"])) == level
    assert log_level(build_parser().parse_args(["bench", *argv])) == level  # after the command's name too


@pytest.mark.parametrize("value, text", [(0.0662122248319372, "0.0662"), (12433, "12433"), (13.4468, "13.4"),
                                         (float("nan"), "n/a"), (None, "n/a"), (1234.5, "1.23e+03")])
def test_three_significant_digits(value, text):
    assert sig3(value) == text


def test_missing_package_names_the_extra():
    exc = ModuleNotFoundError("No module named 'scipy.sparse'", name="scipy.sparse")
    assert "pip install 'fisc[ground]'" in missing_dependency_message("fisc-ground fit", exc)
    assert "pip install 'fisc[sim]'" in missing_dependency_message("fisc-sim run", exc, umbrella="sim")
    dask = ModuleNotFoundError("No module named 'dask'", name="dask")
    assert "pip install 'fisc[sweep]'" in missing_dependency_message("fisc-sim sweep", dask, umbrella="sim")


def test_every_console_script_ends_through_console_exit():
    """``pyproject.toml``'s scripts are the CLIs' ``console`` functions, which end the process
    through ``cli_common.console_exit`` (no collector passes at shutdown)."""
    import importlib
    import inspect
    import tomllib
    from pathlib import Path

    scripts = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())["project"]["scripts"]
    assert set(scripts) == {"fisc-agent", "fisc-ground", "fisc-sim"}
    for name, target in scripts.items():
        module, func = target.split(":")
        assert func == "console", name
        assert "console_exit(main)" in inspect.getsource(getattr(importlib.import_module(module), func)), name


def test_console_exit_exits_with_mains_code_and_the_collector_frozen(tmp_path):
    """``console_exit``: the code ``main()`` returned, ``atexit`` handlers still run, every object
    alive by then frozen out of the shutdown collections, and output written."""
    import subprocess
    import sys

    script = tmp_path / "prog.py"
    script.write_text(
        "import atexit, gc, sys\n"
        "from fisc_agent.common.cli_common import console_exit\n"
        "atexit.register(lambda: print('frozen', gc.get_freeze_count() > 1000, flush=True))\n"
        "def main():\n"
        "    print('ran', end=' ')\n"
        "    return 3\n"
        "console_exit(main)\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 3, done.stderr
    assert done.stdout == "ran frozen True\n"
