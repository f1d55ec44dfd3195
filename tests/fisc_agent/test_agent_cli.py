"""fisc-agent CLI: refusing invalid maps/options with exit code 2, clean SIGTERM, lean imports."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from agent_testkit import EmulatorProbe, tunnel_map_bytes
from sim.autopilot import server
from fisc_agent.cli import build_parser, config_from_args, main
from fisc_agent.flight.tracking import KineticAxes, TrackingConfig
from fisc_agent.config import AgentConfig

ROOT = Path(__file__).resolve().parents[2]


def test_help_lists_the_contract_options(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for opt in ("--map", "--mavlink", "--id", "--autopilot", "--mode", "--rate", "--origin", "--yaw",
                "--trusted-key", "--backend", "--geodetic-anchor", "--exit-policy", "--geofence", "--max-speed"):
        assert opt in out


def test_args_become_a_config():
    a = build_parser().parse_args(["--map", "m.fiscmap", "--mavlink", "udp://:14540", "--id", "7", "--origin",
                                   "1,2,-15", "--yaw", "30", "--mode", "slot", "--rate", "50", "--exit-policy", "loop"])
    cfg = config_from_args(a)
    assert cfg.agent_id == 7 and cfg.origin_ned_m == (1.0, 2.0, -15.0) and cfg.yaw_deg == 30.0
    assert cfg.mode == "slot" and cfg.rate_hz == 50.0 and cfg.exit_policy == "loop"
    assert cfg.transform.yaw_deg == 30.0
    a = build_parser().parse_args(["--map", "m.fiscmap", "--mavlink", "udp://:14540", "--id", "7",
                                   "--geodetic-anchor", "47.1,8.2,500,90"])
    cfg = config_from_args(a)
    assert cfg.geodetic_anchor.heading_deg == 90.0 and cfg.transform.origin_ned_m == (0.0, 0.0, 0.0)
    assert cfg.transform.yaw_deg == 90.0


def test_mode_and_lookahead_default_to_the_map_and_preset_paper_is_algorithm_1():
    base = ["--map", "m.fiscmap", "--mavlink", "udp://:14540", "--id", "7"]
    cfg = config_from_args(build_parser().parse_args(base))
    assert cfg.mode is None and cfg.lookahead_s is None  # the map's recommended settings ...
    assert cfg.lookahead_auto and cfg.tracking.gain_1_s > 0   # ... refined in flight, with streamline tracking
    cfg = config_from_args(build_parser().parse_args(base + ["--lookahead", "0.4", "--mode", "kinetic"]))
    assert cfg.lookahead_s == 0.4 and cfg.mode == "kinetic"
    cfg = config_from_args(build_parser().parse_args(base + ["--preset", "paper"]))
    assert cfg.mode == "mean" and cfg.lookahead_s == 0.0
    assert not cfg.lookahead_auto and cfg.tracking.gain_1_s == 0.0    # open loop: Algorithm 1


def test_the_feedforward_gain_is_1_by_default_a_number_or_auto(capsys):
    base = ["--map", "m.fiscmap", "--mavlink", "udp://:14540", "--id", "7"]
    t = config_from_args(build_parser().parse_args(base)).tracking
    assert (t.feedforward_gain, t.feedforward_auto) == (1.0, False) == (TrackingConfig.feedforward_gain,
                                                                         TrackingConfig.feedforward_auto)
    t = config_from_args(build_parser().parse_args(base + ["--feedforward-gain", "1.2"])).tracking
    assert (t.feedforward_gain, t.feedforward_auto) == (1.2, False)
    t = config_from_args(build_parser().parse_args(base + ["--feedforward-gain", "auto"])).tracking
    assert (t.feedforward_gain, t.feedforward_auto) == (1.0, True)
    t = config_from_args(build_parser().parse_args(base + ["--feedforward-gain", "auto", "--preset", "paper"])).tracking
    assert (t.feedforward_gain, t.feedforward_auto) == (1.0, False)          # Algorithm 1: open loop
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(base + ["--feedforward-gain", "more"])
    assert exc.value.code == 2 and "--feedforward-gain: expected gain or 'auto', got 'more'" in capsys.readouterr().err


def test_the_kinetic_axes_default_to_cross_stream_and_isotropic_is_an_option(capsys):
    base = ["--map", "m.fiscmap", "--mavlink", "udp://:14540", "--id", "7", "--mode", "kinetic"]
    t = config_from_args(build_parser().parse_args(base)).tracking
    assert t.kinetic_axes is KineticAxes.CROSS_STREAM is TrackingConfig.kinetic_axes
    t = config_from_args(build_parser().parse_args(base + ["--kinetic-axes", "isotropic"])).tracking
    assert t.kinetic_axes is KineticAxes.ISOTROPIC
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(base + ["--kinetic-axes", "radial"])
    assert exc.value.code == 2 and "--kinetic-axes: invalid choice: 'radial'" in capsys.readouterr().err


def test_the_wall_margin_defaults_to_the_config_and_off_reflects_at_the_staircase_only(capsys):
    base = ["--map", "m.fiscmap", "--mavlink", "udp://:14540", "--id", "7"]
    assert config_from_args(build_parser().parse_args(base)).wall_margin_m == AgentConfig.wall_margin_m == 0.8
    assert config_from_args(build_parser().parse_args(base + ["--wall-margin", "0.3"])).wall_margin_m == 0.3
    assert config_from_args(build_parser().parse_args(base + ["--wall-margin", "off"])).wall_margin_m is None
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(base + ["--wall-margin", "near"])
    assert exc.value.code == 2 and "--wall-margin: expected metres or 'off', got 'near'" in capsys.readouterr().err


@pytest.mark.parametrize("args, words", [
    (["--lookahead", "-0.5"], "lookahead_s"),
    (["--mavlink", "bogus://x:1"], "unknown scheme"),
    (["--origin", "1,2"], "--origin"),
    (["--rate", "1"], "rate"),
    (["--max-speed", "-1"], "max_speed"),
    (["--wall-margin", "-0.1"], "wall_margin_m"),
])
def test_invalid_options_exit_2_naming_the_problem(tmp_path, caplog, args, words):
    base = {"--map": str(tmp_path / "m.fiscmap"), "--mavlink": "udpin:127.0.0.1:0", "--id": "1"}
    for k, v in zip(args[::2], args[1::2]):
        base[k] = v
    argv = [x for kv in base.items() for x in kv]
    assert main(argv) == 2
    assert words in caplog.text


def _corrupt(data: bytes) -> bytes:
    b = bytearray(data)
    b[200] ^= 0xFF
    return bytes(b)


@pytest.mark.parametrize("mutate, check", [
    (_corrupt, "sha256"),
    (lambda d: d[:100], "truncated"),
    (lambda d: b"NOTAMAP!" + d[8:], "magic"),
])
def test_invalid_map_refused_with_exit_2_and_the_failed_check(tmp_path, caplog, mutate, check):
    p = tmp_path / "bad.fiscmap"
    p.write_bytes(mutate(tunnel_map_bytes()))
    assert main(["--map", str(p), "--mavlink", "udpin:127.0.0.1:0", "--id", "1"]) == 2
    assert "invalid map" in caplog.text and check in caplog.text


def test_trusted_key_requires_a_signature_by_that_key(tmp_path, caplog):
    from nacl.signing import SigningKey

    key = SigningKey.generate()
    pub = tmp_path / "ground.pub"
    pub.write_text(key.verify_key.encode().hex())
    unsigned = tmp_path / "unsigned.fiscmap"
    unsigned.write_bytes(tunnel_map_bytes())
    assert main(["--map", str(unsigned), "--mavlink", "udpin:127.0.0.1:0", "--id", "1", "--trusted-key", str(pub)]) == 2
    assert "signature" in caplog.text
    other = tmp_path / "other.fiscmap"
    other.write_bytes(tunnel_map_bytes(signing_key=bytes(SigningKey.generate())))
    assert main(["--map", str(other), "--mavlink", "udpin:127.0.0.1:0", "--id", "1", "--trusted-key", str(pub)]) == 2
    assert "not trusted" in caplog.text


@pytest.mark.slow
def test_sigterm_holds_the_vehicle_and_exits_cleanly(tmp_path, udp_port):
    mp = tmp_path / "tunnel.fiscmap"
    mp.write_bytes(tunnel_map_bytes())
    emu = server.AutopilotEmulator(f"udpout:127.0.0.1:{udp_port}", personality="px4", start_ned=(-3.0, 0.0, 0.0)).start()
    probe = EmulatorProbe(emu)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "fisc_agent.cli", "--go", "--map", str(mp), "--mavlink",
                             f"udpin:127.0.0.1:{udp_port}", "--id", "2", "--origin", "0,0,-4", "--takeoff-alt", "1"],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        end = time.monotonic() + 15
        while time.monotonic() < end and not (emu.state.mode.value == "offboard" and len(probe.setpoints) > 30):
            time.sleep(0.05)
        assert emu.state.mode.value == "offboard", "agent never took the vehicle into OFFBOARD"
        t_term = emu.time_s
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=10)
        assert proc.returncode == 0, out
        assert probe.setpoints[-1][1:4] == (0.0, 0.0, 0.0)
        # the agent itself asked for Hold (AUTO.LOITER) on its way out, before the emulator's
        # offboard-loss failsafe (COM_OF_LOSS_T = 1.0 s) could have acted
        holds = [c for c in probe.commands_since(t_term) if c[1] == 176 and (c[2][1], c[2][2]) == (4.0, 3.0)]
        assert holds and holds[0][0] - probe.setpoints[-1][0] < 1.0, (holds, probe.setpoints[-1])
        assert emu.state.mode.value == "loiter" and emu.state.armed
        assert "SIGTERM" in out
    finally:
        if proc.poll() is None:
            proc.kill()
        emu.stop()


def test_origin_and_geodetic_anchor_are_exclusive(caplog):
    assert main(["--map", "m.fiscmap", "--mavlink", "udpin:127.0.0.1:0", "--id", "1", "--origin", "1,2,-5",
                 "--geodetic-anchor", "47,8,500,0"]) == 2
    assert "not both" in caplog.text
