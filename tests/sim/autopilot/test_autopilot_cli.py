"""``fisc-sim autopilot`` options and the emulator as a subprocess (clean exit on SIGINT/SIGTERM)."""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys

import pytest
from pymavlink import mavutil

from autopilot_testkit import Client

from ...ports import free_udp_port
from sim.autopilot import cli

ML = mavutil.mavlink


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="fisc-sim")
    cli.add_parser(parser.add_subparsers(dest="command"))
    return parser.parse_args(argv)


def test_add_parser_defaults_and_options():
    args = _parse(["autopilot", "--mavlink", "udpin:0.0.0.0:14540"])
    assert args.func is cli.run and args.personality == "px4" and args.start == (0.0, 0.0, 0.0)
    assert args.loss == 0.0 and args.latency == 0.0 and args.position_dropout == [] and args.sysid == 1
    args = _parse(["autopilot", "--mavlink", "udpout:127.0.0.1:14550", "--personality", "ardupilot",
                   "--start", "1,2,-3", "--rate-position", "50", "--loss", "0.1", "--latency", "0.2",
                   "--sysid", "7", "--position-dropout", "5,2", "--position-dropout", "20,1"])  # fmt: skip
    assert args.start == (1.0, 2.0, -3.0) and args.rate_position == 50.0 and args.sysid == 7
    assert args.position_dropout == [(5.0, 2.0), (20.0, 1.0)]


@pytest.mark.parametrize("bad", [["--start", "1,2"], ["--loss", "2"], ["--position-dropout", "x"],
                                 ["--personality", "inav"]])  # fmt: skip
def test_bad_options_are_rejected(bad, capsys):
    with pytest.raises(SystemExit):
        _parse(["autopilot", "--mavlink", "udpin:0.0.0.0:14540", *bad])


def test_bad_endpoint_returns_exit_code_2():
    assert cli.run(_parse(["autopilot", "--mavlink", "serial:/dev/ttyS0:57600"])) == 2


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_subprocess_serves_until_signal_and_exits_cleanly(sig):
    port = free_udp_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "sim.autopilot.cli", "--mavlink", f"udpin:127.0.0.1:{port}",
         "--personality", "ardupilot", "--sysid", "5", "--start", "0,0,-2"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    c = Client(f"udpout:127.0.0.1:{port}", target_system=5)
    try:
        hb = c.wait("HEARTBEAT", tick=c.heartbeat, timeout=8.0)
        assert hb.autopilot == ML.MAV_AUTOPILOT_ARDUPILOTMEGA
        assert hb.base_mode & ML.MAV_MODE_FLAG_SAFETY_ARMED  # airborne start
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=8)
    finally:
        c.close()
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err.decode()
    assert b"stopped" in err
