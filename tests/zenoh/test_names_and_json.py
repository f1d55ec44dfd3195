"""One swarm-name and prefix rule for every command; strict JSON from ``status --json`` (issue 12, findings 7)."""

from __future__ import annotations

import json
import math
import threading

import pytest

from fisc_agent.zenoh import telemetry_codec as tc
from fisc_agent.cli import build_parser as agent_parser
from fisc_agent.zenoh.fleet_commands import decode_command, encode_command
from fisc_agent.common.names import MAX_SWARM_NAME_BYTES, KeyNameError, check_prefix, check_swarm_name
from fisc_agent.zenoh.keys import Keys
from fisc_ground.cli import build_parser as ground_parser
from fisc_ground.cli import main as ground_main
from fisc_ground.zenoh.fleet import make_command
from sim.cli import build_parser as sim_parser



def _argvs(swarm: str, prefix: str = "fisc") -> dict[str, tuple]:
    return {
        "fisc-agent": (agent_parser(), ["--mavlink", "udpin:127.0.0.1:1", "--id", "1", "--swarm", swarm,
                                        "--zenoh-prefix", prefix]),
        "publish": (ground_parser(), ["publish", "m.fiscmap", "--swarm", swarm, "--prefix", prefix]),
        "cmd": (ground_parser(), ["cmd", "hold", "--swarm", swarm, "--prefix", prefix]),
        "status": (ground_parser(), ["status", "--swarm", swarm, "--prefix", prefix]),
        "monitor": (ground_parser(), ["monitor", "--swarm", swarm, "--prefix", prefix]),
        "emulate": (sim_parser(), ["emulate", "--agents", "2", "-o", "out", "--swarm", swarm, "--zenoh-prefix", prefix]),
    }


def _accepts(parser, argv, capsys) -> tuple[bool, str]:
    try:
        parser.parse_args(argv)
    except SystemExit as exc:
        assert exc.code == 2  # a usage error, never a traceback
        return False, capsys.readouterr().err
    return True, ""


@pytest.mark.parametrize("swarm, ok", [("alpha", True), ("a" * MAX_SWARM_NAME_BYTES, True), ("lab-2.blue_3", True),
                                      ("a" * 300, False), ("a" * (MAX_SWARM_NAME_BYTES + 1), False), ("a/b", False),
                                      ("*", False), ("al pha", False), ("\u00e9t\u00e9", False), ("", False),
                                      ("..", False), ("@x", False)])
def test_every_command_accepts_or_refuses_the_same_swarm_names(swarm, ok, capsys):
    """A 300-byte name was accepted by the agent and publish but refused by cmd: that fleet could
    never be held.  Now every command applies one rule."""
    results = {name: _accepts(parser, argv, capsys) for name, (parser, argv) in _argvs(swarm).items()}
    assert {name: r[0] for name, r in results.items()} == {name: ok for name in results}
    if not ok:
        assert all("swarm name" in r[1] for r in results.values()), results


@pytest.mark.parametrize("prefix, ok", [("fisc", True), ("lab/fisc", True), ("a/b/c", True), ("/fisc", False),
                                        ("fisc/", False), ("a//b", False), ("fi*sc", False), ("fisc/**", False),
                                        ("f$c", False), ("@/fisc", False), ("x" * 200, False)])
def test_every_command_applies_one_prefix_rule(prefix, ok, capsys):
    results = {name: _accepts(parser, argv, capsys) for name, (parser, argv) in _argvs("alpha", prefix).items()}
    assert {name: r[0] for name, r in results.items()} == {name: ok for name in results}
    if not ok:
        assert all("prefix" in r[1] for r in results.values()), results


def test_a_bad_prefix_is_a_usage_error_not_a_zenoh_traceback(capsys):
    """Bad --prefix values ended in a raw zenoh.ZError traceback with exit 1."""
    with pytest.raises(SystemExit) as exc:
        ground_main(["status", "--swarm", "alpha", "--prefix", "a//b", "--wait", "0"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "empty chunk" in err and "Traceback" not in err


def test_every_accepted_name_is_a_valid_zenoh_key_and_fits_a_fleet_command(net, sessions, ground_key):
    """The rule is not stricter than needed and not looser than Zenoh and the command wire format."""
    import zenoh

    hub, _ = net
    s = sessions(hub)
    for swarm, prefix in (("a" * MAX_SWARM_NAME_BYTES, "lab/fisc"), ("x.y-z_0", "p"), ("A", "a.b/c-d/e_f")):
        keys = Keys(check_prefix(prefix), check_swarm_name(swarm))
        for key in (keys.map, keys.cmd, keys.telemetry(4294967294), keys.all_telemetry):
            zenoh.KeyExpr(key)  # raises on an invalid key expression
        pub = s.declare_publisher(keys.telemetry(7))
        pub.undeclare()
        cmd = make_command("hold", swarm)
        assert decode_command(encode_command(cmd, ground_key[0]), [ground_key[1]]).swarm == swarm
    for bad in ("a" * 300, "a/b", "x*"):
        with pytest.raises(KeyNameError):
            check_swarm_name(bad)


def test_status_json_is_strict_json_with_null_for_non_finite_values(net, sessions, capsys):
    """`status --json` printed NaN/Infinity, which is not JSON."""
    hub, member = net
    hub_session = sessions(hub)
    keys = Keys("fisc", "alpha")
    stop = threading.Event()
    msg = tc.encode(tc.Telemetry(agent_id=5, seq=0, time_s=1.0, position_m=(math.nan, 1.0, math.inf),
                                 velocity_m_s=(-math.inf, 0.0, 0.0), state="HOLD"))

    def talk():
        while not stop.wait(0.05):
            hub_session.put(keys.telemetry(5), msg)

    t = threading.Thread(target=talk, daemon=True)
    t.start()
    try:
        rc = ground_main(["status", "--swarm", "alpha", "--zenoh-config", str(member), "--json", "--wait", "1.5"])
    finally:
        stop.set()
        t.join()
    assert rc == 0
    out = capsys.readouterr().out

    def refuse(token):
        raise AssertionError(f"non-standard JSON token {token}")

    report = json.loads(out, parse_constant=refuse)
    agent = next(a for a in report["agents"] if a["id"] == 5)
    assert agent["position_m"] == [None, 1.0, None] and agent["velocity_m_s"] == [None, 0.0, 0.0]
    assert agent["state"] == "HOLD"
