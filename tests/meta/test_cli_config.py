"""Every CLI flag maps to a documented config field, and the CLI's defaults are the config's.

For each command with a config dataclass the table below maps every option to the dataclass
field(s) it sets; the test checks that the table covers exactly the parser's options, that every
field exists and has a docstring in its class, and that the config the CLI builds from its defaults
equals the dataclass's own defaults (so the dataclass is the one source).  Options that set no
config field are listed with the reason; so are the commands that have no config dataclass.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import textwrap

import pytest

COMMON = {"-h": "argparse help", "-v": "logging (fisc_agent.common.cli_common)", "-q": "logging and progress (fisc_agent.common.cli_common)",
          "--log-level": "logging (fisc_agent.common.cli_common)"}

AGENT = {
    "--map": "AgentConfig.map_path", "--mavlink": "AgentConfig.mavlink_url", "--id": "AgentConfig.agent_id",
    "--autopilot": "AgentConfig.autopilot", "--backend": "AgentConfig.backend", "--mode": "AgentConfig.mode",
    "--preset": "AgentConfig.mode AgentConfig.lookahead_s AgentConfig.lookahead_auto AgentConfig.tracking",
    "--track-gain": "TrackingConfig.gain_1_s", "--track-integral-gain": "TrackingConfig.integral_gain_1_s2",
    "--track-max-correction": "TrackingConfig.max_correction_m_s",
    "--lookahead": "AgentConfig.lookahead_s AgentConfig.lookahead_auto",
    "--feedforward-gain": "TrackingConfig.feedforward_gain TrackingConfig.feedforward_auto", "--online-gain-time": "TrackingConfig.online_gain_time_s", "--kinetic-axes": "TrackingConfig.kinetic_axes", "--entry-stagger": "AgentConfig.entry_stagger_s",
    "--entry-slots": "AgentConfig.entry_slots", "--rate": "AgentConfig.rate_hz",
    "--entry-radius-fraction": "AgentConfig.entry_radius_fraction",
    "--origin": "AgentConfig.origin_ned_m", "--yaw": "AgentConfig.yaw_deg",
    "--geodetic-anchor": "AgentConfig.geodetic_anchor", "--trusted-key": "AgentConfig.trusted_key",
    "--max-speed": "AgentConfig.max_speed_m_s", "--max-accel": "AgentConfig.max_accel_m_s2",
    "--join-speed": "AgentConfig.join_speed_m_s", "--return-speed": "AgentConfig.return_speed_m_s",
    "--climb-speed": "AgentConfig.climb_speed_m_s", "--takeoff-alt": "AgentConfig.takeoff_alt_m",
    "--exit-policy": "AgentConfig.exit_policy", "--laps": "AgentConfig.laps",
    "--exit-clearance": "AgentConfig.exit_clearance_m", "--exit-spacing": "AgentConfig.exit_spacing_m", "--geofence": "AgentConfig.geofence",
    "--wall-margin": "AgentConfig.wall_margin_m", "--drag-feedforward": "DragConfig.feedforward",
    "--stale-timeout": "AgentConfig.stale_timeout_s", "--hold-grace": "AgentConfig.hold_grace_s",
    "--link-timeout": "AgentConfig.link_timeout_s", "--source-system": "AgentConfig.source_system",
    "--go": "AgentConfig.go", "--target-system": "AgentConfig.target_system",
    "--min-battery": "AgentConfig.min_battery_pct", "--low-battery-action": "AgentConfig.low_battery_action",
    "--takeoff-timeout": "AgentConfig.takeoff_timeout_s", "--max-start-distance": "AgentConfig.max_start_distance_m",
    "--state-file": "AgentConfig.state_file", "--safety-net": "AgentConfig.safety_net",
}
AGENT_NO_FIELD = {
    "--flight-log": "an output file of the process (fisc_agent.cli.run's flight_log), not a flight setting",
    "--max-duration": "lifetime of the process (Runner.run's max_duration_s), not a flight setting",
    "--swarm": "Zenoh link option passed to fisc_agent.zenoh.runner.connect_runner (the Zenoh link's "
               "arguments; the flight settings live in AgentConfig)",
    "--zenoh-config": "Zenoh link option (as --swarm)", "--zenoh-prefix": "Zenoh link option (as --swarm)",
    "--telemetry-rate": "Zenoh link option (as --swarm)", "--allow-unsigned": "Zenoh link option (as --swarm)",
}

RUN = {
    "--mcap": "RunConfig.mcap",
    "--map": "RunConfig.map", "--scenario": "RunConfig.scenario", "--agents": "RunConfig.agents",
    "--duration": "RunConfig.duration_s", "--average-window": "RunConfig.average_window_s",
    "--plant": "RunConfig.plant", "--preset": "RunConfig.preset", "--mode": "RunConfig.mode",
    "--collisions": "RunConfig.collisions",
    "--safety-net": "RunConfig.safety_net",
    "--staggered-admission": "RunConfig.staggered_admission", "--seed": "RunConfig.seed", "--scale": "RunConfig.scale",
    "--max-speed": "RunConfig.max_speed_m_s", "--lookahead": "RunConfig.lookahead_s",
    "--x-axial": "RunConfig.x_axial_m", "--no-figures": "RunConfig.figures", "-o": "RunConfig.out_dir",
}

EMULATE = {
    "--mcap": "EmulateConfig.mcap",
    "--flight-logs": "EmulateConfig.flight_logs",
    "--map": "EmulateConfig.map", "--agents": "EmulateConfig.agents", "--duration": "EmulateConfig.duration_s",
    "--mode": "EmulateConfig.mode", "--lookahead": "EmulateConfig.lookahead_s", "--preset": "EmulateConfig.preset",
    "--autopilot": "EmulateConfig.personality", "--plant": "EmulateConfig.plant",
    "--exit-policy": "EmulateConfig.exit_policy", "--geofence": "EmulateConfig.geofence", "--rate": "EmulateConfig.rate_hz",
    "--open-loop": "EmulateConfig.tracking", "--safety-net": "EmulateConfig.safety_net", "--entry-radius-fraction": "EmulateConfig.entry_radius_fraction",
    "--staggered-admission": "EmulateConfig.staggered_admission", "--fleet-mode": "EmulateConfig.fleet_mode", "--estimate-error": "EmulateConfig.estimate_error", "--start-spacing": "EmulateConfig.start_spacing_m",
    "--reference-seeds": "EmulateConfig.reference_seeds",
    "--average-window": "EmulateConfig.average_window_s", "--telemetry": "EmulateConfig.telemetry",
    "--physics-rate": "EmulateConfig.physics_rate_hz", "--physics-dt": "EmulateConfig.physics_dt_s",
    "--workers": "EmulateConfig.emulator_workers EmulateConfig.agent_workers", "--no-compare": "EmulateConfig.compare",
    "--no-figures": "EmulateConfig.figures", "--seed": "EmulateConfig.seed", "--swarm": "EmulateConfig.swarm",
    "--zenoh-config": "EmulateConfig.zenoh_config", "--zenoh-prefix": "EmulateConfig.zenoh_prefix",
    "--telemetry-rate": "EmulateConfig.telemetry_rate_hz", "--trusted-key": "EmulateConfig.trusted_key",
    "-o": "EmulateConfig.out_dir",
}

FIT = {
    "--cell-size": "FitConfig.cell_size_m", "--n-range": "FitConfig.n_min FitConfig.n_max", "--scale": "FitConfig.scale",
    "--max-speed": "FitConfig.max_speed_m_s", "--kappa": "FitConfig.kappa", "--agent-mass": "FitConfig.agent_mass_kg",
    "--min-nodes": "FitConfig.min_nodes", "--seed": "FitConfig.seed", "--preset": "FitConfig.staggered",
    "--continuity-weight": "FitConfig.continuity_weight", "--density-amplitude": "FitConfig.density_amplitude",
    "--dispersion-ratio": "FitConfig.dispersion_ratio", "--staircase-contrast": "FitConfig.staircase_contrast",
    "--vehicle-radius": "FitConfig.vehicle_radius_m", "--position-sigma": "FitConfig.position_sigma_m",
    "--length-scale": "FitConfig.length_scale",
}
FIT_NO_FIELD = {
    "-o": "the map file written (run_fit's output), not a fit setting",
    "--sign": "the signing key file (fisc_ground.maps.write.write_map's signing_key), not a fit setting",
    "--pressure-kind": "an importer option of the reference file (fisc_ground.reference.load.load_reference)",
}

#: Commands whose options are the arguments of one function call, with no config dataclass.
NO_CONFIG_DATACLASS = {
    ("fisc-ground", "inspect"): "prints a map summary; options are output format and trust key",
    ("fisc-ground", "keygen"): "one option: the key file stem",
    ("fisc-ground", "plot"): "options are the map, output folder and trust key",
    ("fisc-ground", "score-flight"): "scoring arguments of fisc_ground.fields.flight_score.score_track",
    ("fisc-ground", "publish"): "Zenoh map-server options (MapServer arguments)",
    ("fisc-ground", "router"): "a Zenoh router: its configuration is a standard Zenoh config file (--config) or endpoints",
    ("fisc-ground", "cmd"): "one signed fleet command's fields",
    ("fisc-ground", "status"): "a listening window",
    ("fisc-ground", "monitor"): "monitor options: swarm, map, trust, recording and Foxglove port (arguments of run_monitor)",
    ("fisc-ground", "replay"): "arguments of fisc_ground.monitor.recording.replay (the MCAP file and the output folder)",
    ("fisc-sim", "bench"): "benchmark sizes and switches (sim.bench.run_bench arguments)",
    ("fisc-sim", "sweep"): "the spec file is the configuration (checked against RunConfig/FitConfig by sim.sweep.spec)",
    ("fisc-sim", "autopilot"): "keyword arguments of sim.autopilot.server.AutopilotEmulator; its defaults are "
                               "checked against that signature below",
}


def _options(parser: argparse.ArgumentParser) -> set[str]:
    """The first option string of every optional action (the flag as documented)."""
    return {a.option_strings[0] for a in parser._actions if a.option_strings}


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            return dict(a.choices)
    return {}


def documented_fields(cls) -> set[str]:
    """Fields of dataclass ``cls`` followed by an attribute docstring in its source."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body
    out = set()
    for node, nxt in zip(body, body[1:]):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(nxt, ast.Expr) \
                and isinstance(nxt.value, ast.Constant) and isinstance(nxt.value.value, str):
            out.add(node.target.id)
    return out


def _classes():
    from fisc_agent.config import AgentConfig
    from fisc_agent.flight.drag import DragConfig
    from fisc_agent.flight.tracking import TrackingConfig
    from fisc_ground.maps.build import FitConfig
    from sim.emulate import EmulateConfig
    from sim.run import RunConfig

    return {c.__name__: c for c in (AgentConfig, TrackingConfig, DragConfig, FitConfig, EmulateConfig, RunConfig)}


def _parsers():
    from fisc_agent.cli import build_parser as agent
    from fisc_ground.cli import build_parser as ground
    from sim.cli import build_parser as simcli

    g, s = _subparsers(ground()), _subparsers(simcli())
    return agent(), g, s


CASES = [
    ("fisc-agent", lambda a, g, s: a, AGENT, AGENT_NO_FIELD),
    ("fisc-sim run", lambda a, g, s: s["run"], RUN, {}),
    ("fisc-sim emulate", lambda a, g, s: s["emulate"], EMULATE, {}),
    ("fisc-ground fit", lambda a, g, s: g["fit"], FIT, FIT_NO_FIELD),
]


@pytest.mark.parametrize("name, get, table, no_field", CASES, ids=[c[0] for c in CASES])
def test_every_flag_maps_to_a_documented_config_field(name, get, table, no_field):
    parser = get(*_parsers())
    options = _options(parser) - set(COMMON)
    unmapped = options - set(table) - set(no_field)
    stale = (set(table) | set(no_field)) - options
    assert not unmapped, f"{name}: options with no config field and no listed reason: {sorted(unmapped)}"
    assert not stale, f"{name}: table lists options the parser does not have: {sorted(stale)}"
    classes = _classes()
    for flag, fields in table.items():
        for ref in fields.split():
            cls_name, field = ref.split(".")
            cls = classes[cls_name]
            assert field in {f.name for f in dataclasses.fields(cls)}, f"{name} {flag}: {ref} is not a field"
            assert field in documented_fields(cls), f"{name} {flag}: {ref} has no docstring"


def test_every_command_is_covered():
    _, g, s = _parsers()
    covered = {("fisc-sim", "run"), ("fisc-sim", "emulate"), ("fisc-ground", "fit")} | set(NO_CONFIG_DATACLASS)
    present = {("fisc-ground", k) for k in g} | {("fisc-sim", k) for k in s}
    assert not present - covered, f"commands with neither a config table nor a listed reason: {sorted(present - covered)}"


def test_documented_fields_sees_a_missing_docstring():
    @dataclasses.dataclass(frozen=True)
    class C:
        a: int = 1
        """Documented."""
        b: int = 2

    assert documented_fields(C) == {"a"}


def test_defaults_are_the_config_defaults():
    """The config each CLI builds from its defaults equals the dataclass's defaults."""
    from fisc_agent.cli import config_from_args as agent_config
    from fisc_ground.cli import fit_config_from_args
    from sim.cli import run_config_from_args
    from sim.emulate.cli import config_from_args as emulate_config

    classes = _classes()
    a, g, s = _parsers()
    url = "udpin:0.0.0.0:14540"
    assert agent_config(a.parse_args(["--mavlink", url, "--id", "1"])) == classes["AgentConfig"](mavlink_url=url, agent_id=1)
    assert run_config_from_args(s["run"].parse_args([])) == classes["RunConfig"]()
    emu = classes["EmulateConfig"]()
    assert emulate_config(s["emulate"].parse_args(["--agents", str(emu.agents), "-o", emu.out_dir])) == emu
    assert fit_config_from_args(g["fit"].parse_args(["cd_nozzle", "-o", "m.fiscmap"])) == classes["FitConfig"]()
    # a changed flag does reach its field (the comparison can fail)
    assert agent_config(a.parse_args(["--mavlink", url, "--id", "1", "--rate", "25"])).rate_hz == 25.0


def test_autopilot_defaults_are_the_emulator_defaults():
    from sim.autopilot.server import AutopilotEmulator

    _, _, s = _parsers()
    args = s["autopilot"].parse_args(["--mavlink", "udpin:127.0.0.1:0"])
    sig = inspect.signature(AutopilotEmulator.__init__).parameters
    pairs = {"personality": "personality", "sysid": "sysid", "home_lla": "home", "rate_position_hz": "rate_position",
             "rate_attitude_hz": "rate_attitude", "loss": "loss", "latency_s": "latency", "seed": "seed"}
    checked = 0
    for param, dest in pairs.items():
        if param in sig and sig[param].default is not inspect.Parameter.empty:
            want, got = sig[param].default, getattr(args, dest)
            assert (tuple(got) if isinstance(want, tuple) else got) == want, (param, got, want)
            checked += 1
    assert checked >= 6, "the emulator's signature changed: update the pairs"
