"""``fisc-agent``: fly one vehicle through a FISC command map over MAVLink.

Exit codes: 0 mission finished (or stopped by SIGINT/SIGTERM), 1 mission failed (e.g. could
not arm), 2 invalid map, configuration or endpoint (the message names the failed check).
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import threading

from fisc_agent.common.cli_common import (ExitCode, add_logging_args, console_exit, number_or, positive_number,
                                         setup_logging)
from fisc_agent.config import AUTOPILOTS, BACKENDS, EXIT_POLICIES, GEOFENCE_POLICIES, AgentConfig
from fisc_agent.mavlink.endpoints import EndpointError, parse_endpoint
from fisc_agent.flight.frames import GeodeticAnchor, parse_floats
from fisc_agent.map.lookup import COMMAND_MODES
from fisc_agent.map.codec import MapError, load_map
from fisc_agent.common.names import prefix_arg, swarm_name_arg
from fisc_agent.flight.drag import DragConfig
from fisc_agent.flight.safety_net import SafetyNetConfig
from fisc_agent.flight.tracking import KineticAxes, TrackingConfig

log = logging.getLogger("fisc_agent")


def _entry_stagger(text: str) -> float | None:
    """``--entry-stagger``: seconds >= 0, ``auto`` (None: the map's admission period) or ``off`` (0)."""
    if text == "auto":
        return None
    if text == "off":
        return 0.0
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, 'auto' or 'off', got {text!r}") from None
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"expected a finite number of seconds >= 0, 'auto' or 'off', got {text!r}")
    return value


def _entry_slots(text: str) -> int | None:
    """``--entry-slots``: an integer >= 1 or ``auto`` (None)."""
    if text == "auto":
        return None
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1 or 'auto', got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1 or 'auto', got {text!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The ``fisc-agent`` argument parser."""
    p = argparse.ArgumentParser(
        prog="fisc-agent", description=__doc__.split("\n\n")[0],
        epilog="Exit codes: 0 mission done or stopped by SIGINT/SIGTERM (vehicle left holding), 1 mission "
               "failed, 2 invalid map, option or endpoint. Deployment guide: docs/deployment.md.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--map", dest="map_path", help="command map file (.fiscmap); omit with --swarm to receive it over Zenoh")
    p.add_argument("--mavlink", required=True,
                   help="autopilot endpoint: udpin:0.0.0.0:14540, udpout:HOST:PORT, tcp:HOST:PORT, udp://:14540, "
                        "serial:///dev/ttyUSB0:921600, /dev/ttyACM0:57600")
    p.add_argument("--id", dest="agent_id", type=int, required=True, help="agent id N (slot and entry point)")
    a = p.add_argument_group("authority and health (docs/deployment.md, 'Authority')")
    a.add_argument("--go", action="store_true",
                   help="permission to arm and fly one flight now (a bench or SITL flight); without it the agent "
                        "waits disarmed for a signed fleet go / start-at (fisc-ground cmd go). An armed vehicle "
                        "is never taken over, with or without --go")
    a.add_argument("--target-system", type=int, default=None, metavar="SYSID",
                   help="MAVLink system id of the one autopilot to fly (default: the first one heard, then pinned)")
    a.add_argument("--min-battery", type=number_or("off", None, "percent"), default=AgentConfig.min_battery_pct,
                   metavar="PCT|off", help="below this battery %% finish the pass, then --low-battery-action; never "
                                           "arm or start a pass below it")
    a.add_argument("--low-battery-action", choices=("land", "hold"), default=AgentConfig.low_battery_action.value,
                   help="after the last pass on a low battery: land or hold at the exit point")
    a.add_argument("--takeoff-timeout", type=float, default=AgentConfig.takeoff_timeout_s,
                   help="land when the take-off has not reached its height after this long [s]")
    a.add_argument("--max-start-distance", type=float, default=AgentConfig.max_start_distance_m,
                   help="do not arm when the start point is farther than this from the map [m]")
    a.add_argument("--state-file", default=AgentConfig.state_file, metavar="PATH|auto|off",
                   help="where a restarted agent finds its hands-off, fleet hold, laps and fleet-command sequence; "
                        "auto: $XDG_STATE_HOME/fisc/agent-<swarm>-<id>.json (~/.local/state without XDG_STATE_HOME)")
    p.add_argument("--autopilot", choices=AUTOPILOTS, default=AgentConfig.autopilot,
                   help="autopilot flavour; auto: from the HEARTBEAT's autopilot field")
    p.add_argument("--backend", choices=BACKENDS, default=AgentConfig.backend,
                   help="MAVLink client library (mavsdk needs the mavsdk package)")
    p.add_argument("--mode", choices=COMMAND_MODES, default=None,
                   help="command mode (default: the map's recommended mode; mean for a schema-1 map; with "
                        "streamline tracking kinetic flies the staggered field with its deviations on the tracking "
                        "parcel, turned within --wall-margin of the map's real wall; a map without that wall flies "
                        "a recommended kinetic as staggered)")
    p.add_argument("--preset", choices=("paper",), default=None,
                   help="paper: the paper's Algorithm 1 (mean commands, open loop, no look-ahead) whatever the map "
                        "recommends")
    t = p.add_argument_group("streamline tracking (fisc_agent.flight.tracking; docs/deployment.md)")
    t.add_argument("--track-gain", type=float, default=TrackingConfig.gain_1_s,
                   help="cross-stream feedback towards the agent's own streamline [1/s]; 0: fly the simulator's "
                        "command function open loop")
    t.add_argument("--track-integral-gain", type=float, default=TrackingConfig.integral_gain_1_s2,
                   help="cross-stream integral gain: learns a steady velocity bias [1/s^2]")
    t.add_argument("--track-max-correction", type=float, default=TrackingConfig.max_correction_m_s,
                   help="largest feedback velocity added to the map's command [m/s]")
    t.add_argument("--lookahead", type=number_or("auto", "auto", "seconds"), default="auto",
                   help="evaluate the field this far ahead, compensating the vehicle's velocity lag [s]; auto: "
                        "identify the lag (and the feed-forward gain) in flight during take-off and join, the "
                        "map's recommended look-ahead until then")
    t.add_argument("--feedforward-gain", type=number_or("auto", "auto", "gain"), default=TrackingConfig.feedforward_gain,
                   metavar="G|auto",
                   help="multiplies the map's command (inverse of the vehicle's steady velocity gain; default 1); "
                        "auto (with --lookahead auto): the inverse of the gain identified in flight and learnt "
                        "again through the pass (stock PX4 flies better at 1: docs/deployment.md)")
    t.add_argument("--online-gain-time", type=number_or("off", 0.0, "seconds"), default=TrackingConfig.online_gain_time_s,
                   metavar="S|off",
                   help="with --feedforward-gain auto: learn the vehicle's steady velocity gain again through the "
                        "pass, forgetting over this time, and set the feed-forward gain from it [s]; off: keep the "
                        "gain identified before the pass")
    t.add_argument("--kinetic-axes", choices=[k.value for k in KineticAxes], default=TrackingConfig.kinetic_axes.value,
                   help="kinetic mode under tracking: fly the deviation across the stream only, at its full magnitude (the fitted "
                        "velocity spread without slowing a vehicle along the stream), or isotropic as fisc-sim run's "
                        "agents do (default %(default)s)")
    t.add_argument("--drag-feedforward", choices=("on", "off"), default="on",
                   help="PX4: identify the vehicle's drag in flight from its attitude and send the thrust it takes "
                        "with each velocity setpoint as acceleration feed-forward, switched on once the vehicle is "
                        "slow (fisc_agent.flight.drag; docs/deployment.md); off: velocity-only setpoints")
    p.add_argument("--safety-net", choices=("on", "off"), default="on",
                   help="separation safety net: with --swarm, hear the neighbours' telemetry; closing too fast on "
                        "one, slow down, and inside the map's d_min of one, push apart (fisc_agent.flight.safety_net); "
                        "off: the paper's flow law alone")
    p.add_argument("--entry-stagger", type=_entry_stagger, default="auto", metavar="S|auto|off",
                   help="cross the inlet only in this agent's window of a cycle of --entry-slots windows of this "
                        "length on the shared clock (GNSS time; agent i: window i mod slots) [s]; auto: the map's "
                        "admission period (fisc-ground inspect: 'admit one vehicle every ... s'), none on a map "
                        "without one; 0 or off: no stagger")
    p.add_argument("--entry-slots", type=_entry_slots, default="auto", metavar="N|auto",
                   help="windows per entry-stagger cycle; auto: the map's budget of vehicles in the tunnel with the "
                        "map's admission period, else 8")
    p.add_argument("--entry-radius-fraction", type=float, default=AgentConfig.entry_radius_fraction, metavar="F",
                   help="entry points spread over this fraction of the inlet radius (1: every inlet CV)")
    p.add_argument("--flight-log", help="write one CSV row per control tick to this file (fisc_agent.flight.flightlog)")
    p.add_argument("--rate", type=float, default=AgentConfig.rate_hz, help="setpoint rate [Hz]")
    p.add_argument("--origin", default=",".join(f"{c:g}" for c in AgentConfig.origin_ned_m), help="local NED of the map origin N,E,D [m]")
    p.add_argument("--yaw", type=float, default=AgentConfig.yaw_deg, help="map x-axis direction, clockwise from North [deg]")
    p.add_argument("--geodetic-anchor", help="map origin LAT,LON,ALT_AMSL,HEADING (uses GLOBAL_POSITION_INT)")
    p.add_argument("--trusted-key", help="Ed25519 public key (.pub): maps and fleet commands must be signed by it")
    z = p.add_argument_group("Zenoh (map over the network, fleet commands, telemetry; see docs/zenoh.md)")
    z.add_argument("--swarm", type=swarm_name_arg, help="swarm name: receive the map on <prefix>/SWARM/map (wait on the ground until then)")
    z.add_argument("--zenoh-config", help="standard Zenoh JSON5 config (omitted: the lab default, peer mode on loopback: connect to tcp/127.0.0.1:7447, hold it while free; docs/zenoh.md)")
    z.add_argument("--zenoh-prefix", type=prefix_arg, default="fisc", help="key expression prefix")
    z.add_argument("--telemetry-rate", type=float, default=5.0, help="telemetry rate [Hz]")
    z.add_argument("--allow-unsigned", action="store_true", help="LAB ONLY: accept unsigned maps and commands")
    p.add_argument("--max-speed", type=float, default=AgentConfig.max_speed_m_s, help="speed clamp [m/s]")
    p.add_argument("--max-accel", type=float, default=AgentConfig.max_accel_m_s2, help="acceleration clamp [m/s^2]")
    p.add_argument("--join-speed", type=float, default=AgentConfig.join_speed_m_s, help="speed flying to the inlet [m/s]")
    p.add_argument("--return-speed", type=float, default=AgentConfig.return_speed_m_s, help="speed returning to the map [m/s]")
    p.add_argument("--climb-speed", type=float, default=AgentConfig.climb_speed_m_s, help="climb rate of a setpoint takeoff (PX4, or an interrupted ArduPilot takeoff) [m/s]")
    p.add_argument("--takeoff-alt", type=float, default=AgentConfig.takeoff_alt_m, help="takeoff height above start [m]")
    p.add_argument("--exit-policy", choices=EXIT_POLICIES, default=AgentConfig.exit_policy,
                   help="after the outlet: hold position, land, or loop back to the inlet")
    p.add_argument("--laps", type=int, default=AgentConfig.laps, help="with --exit-policy loop: passes before holding (0: no limit)")
    p.add_argument("--exit-clearance", type=positive_number("metres"), default=AgentConfig.exit_clearance_m,
                   metavar="M", help="with --exit-policy hold/land: the first row of hold spots this far past the outlet [m]")
    p.add_argument("--exit-spacing", type=positive_number("metres"), default=AgentConfig.exit_spacing_m,
                   metavar="M", help="with --exit-policy hold/land: least horizontal distance between two hold "
                                     "(and landing) spots [m]")
    p.add_argument("--wall-margin", type=number_or("off", None, "metres"), default=AgentConfig.wall_margin_m,
                   metavar="M|off",
                   help="--mode kinetic under tracking: keep the deviation this far inside the duct's real wall "
                        "where the map carries it (duct_wall_m) [m]; off: reflect at the CV staircase only, as "
                        f"fisc-sim run's agents do (default {AgentConfig.wall_margin_m})")
    p.add_argument("--geofence", choices=GEOFENCE_POLICIES, default=AgentConfig.geofence, help="outside the map while flowing: hold, or return (near the map rejoin the nearest CV's flow with an "
                   "inward pull, as fisc-sim run's agents do; farther fly straight back to it)")
    p.add_argument("--stale-timeout", type=float, default=AgentConfig.stale_timeout_s, help="position age that triggers a hold [s]")
    p.add_argument("--hold-grace", type=float, default=AgentConfig.hold_grace_s, help="zero-velocity hold before hold mode [s]")
    p.add_argument("--link-timeout", type=float, default=AgentConfig.link_timeout_s, help="HEARTBEAT age that means link lost [s]")
    p.add_argument("--source-system", type=int, default=AgentConfig.source_system, help="our MAVLink system id (omitted: the vehicle's)", metavar="ID")
    add_logging_args(p)  # -v/-q/--log-level (state transitions are logged at INFO)
    p.add_argument("--max-duration", type=float, default=None, help="stop after this many seconds")
    return p


def config_from_args(a: argparse.Namespace) -> AgentConfig:
    """Build and validate the config (``ValueError``/``EndpointError`` name the bad option)."""
    parse_endpoint(a.mavlink)
    anchor = GeodeticAnchor.parse(a.geodetic_anchor) if a.geodetic_anchor else None
    paper = a.preset == "paper"
    return AgentConfig(
        mavlink_url=a.mavlink, agent_id=a.agent_id, map_path=a.map_path, trusted_key=a.trusted_key,
        autopilot=a.autopilot, backend=a.backend, rate_hz=a.rate,
        mode="mean" if (paper and a.mode is None) else a.mode,
        lookahead_s=0.0 if paper else (None if a.lookahead == "auto" else a.lookahead),
        lookahead_auto=a.lookahead == "auto" and not paper,
        tracking=TrackingConfig(gain_1_s=0.0 if paper else a.track_gain, integral_gain_1_s2=a.track_integral_gain,
                                max_correction_m_s=a.track_max_correction,
                                feedforward_gain=1.0 if paper or a.feedforward_gain == "auto" else a.feedforward_gain,
                                feedforward_auto=a.feedforward_gain == "auto" and not paper,
                                online_gain_time_s=a.online_gain_time, kinetic_axes=a.kinetic_axes),
        origin_ned_m=parse_floats(a.origin, 3, "--origin N,E,D"), yaw_deg=a.yaw, geodetic_anchor=anchor,
        max_speed_m_s=a.max_speed, max_accel_m_s2=a.max_accel, join_speed_m_s=a.join_speed,
        return_speed_m_s=a.return_speed, climb_speed_m_s=a.climb_speed, takeoff_alt_m=a.takeoff_alt,
        exit_policy=a.exit_policy, laps=a.laps, exit_clearance_m=a.exit_clearance, exit_spacing_m=a.exit_spacing,
        entry_stagger_s=a.entry_stagger, entry_slots=a.entry_slots,
        entry_radius_fraction=a.entry_radius_fraction, geofence=a.geofence, stale_timeout_s=a.stale_timeout,
        wall_margin_m=a.wall_margin, drag=DragConfig(feedforward=a.drag_feedforward == "on" and not paper),
        safety_net=SafetyNetConfig() if a.safety_net == "on" else None,
        hold_grace_s=a.hold_grace, link_timeout_s=a.link_timeout, source_system=a.source_system, go=a.go,
        target_system=a.target_system, min_battery_pct=a.min_battery, low_battery_action=a.low_battery_action,
        takeoff_timeout_s=a.takeoff_timeout, max_start_distance_m=a.max_start_distance,
        state_file=None if a.state_file == "off" else a.state_file)


def make_link(cfg: AgentConfig):
    """Open the configured backend's link to the autopilot."""
    if cfg.backend == "mavsdk":
        from fisc_agent.mavlink.mavsdk_backend import MavsdkLink

        return MavsdkLink(cfg.mavlink_url, anchor=cfg.geodetic_anchor)
    from fisc_agent.mavlink.link import MavlinkLink
    from fisc_agent.flight.position_gate import PositionGateConfig

    return MavlinkLink(cfg.mavlink_url, source_system=cfg.source_system, source_component=cfg.source_component,
                       target_system=cfg.target_system,
                       anchor=cfg.geodetic_anchor, position_rate_hz=max(50.0, cfg.rate_hz),
                       position_gate=PositionGateConfig.for_speed_clamp(cfg.max_speed_m_s))


def run(cfg: AgentConfig, stop: threading.Event | None = None, max_duration_s: float | None = None,
        zenoh_args: argparse.Namespace | None = None, flight_log: str | None = None) -> int:
    """Load the map (or receive it over Zenoh when ``zenoh_args.swarm`` is set), connect, fly."""
    from fisc_agent.runner import Runner

    try:
        cmap = load_map(cfg.map_path, cfg.trusted_key) if cfg.map_path else None
    except MapError as exc:
        log.error("invalid map, refusing to start: %s", exc)
        return ExitCode.USAGE
    if cmap is not None and cmap.signed:
        log.info("map %s signed by %s", cfg.map_path, cmap.public_key)
    elif cmap is not None:
        log.warning("map %s is not signed; its integrity (sha256) is checked, its origin is not", cfg.map_path)
    from fisc_agent.flight.flightlog import FlightLog

    try:
        flog = FlightLog(flight_log) if flight_log else None
    except OSError as exc:
        log.error("cannot write the flight log: %s", exc)
        return ExitCode.USAGE
    link = make_link(cfg)
    try:
        runner = Runner(cfg, link, cmap, on_tick=flog.write if flog else None,
                        swarm=zenoh_args.swarm if zenoh_args is not None else None)
    except MapError as exc:
        link.close()
        if flog:
            flog.close()
        log.error("invalid map, refusing to start: %s", exc)
        return ExitCode.USAGE
    log.info("fisc-agent %d: %s, map %s, mode %s, %.0f Hz, %s", cfg.agent_id, cfg.mavlink_url,
             cmap.sha256[:12] if cmap else "(none yet)", cfg.mode, cfg.rate_hz,
             "go given (--go)" if cfg.go else "waiting for a fleet go (no --go)")
    zlink = None
    try:
        if zenoh_args is not None and zenoh_args.swarm:
            from fisc_agent.map.codec import read_public_key
            from fisc_agent.zenoh.runner import connect_runner

            try:
                keys = [read_public_key(cfg.trusted_key)] if cfg.trusted_key else None
                zlink = connect_runner(runner, zenoh_args.zenoh_config, zenoh_args.swarm, keys,
                                       zenoh_args.allow_unsigned, zenoh_args.telemetry_rate, zenoh_args.zenoh_prefix,
                                       clock=runner.unix_time, command_floors=runner.command_floors)
            except (MapError, ValueError, FileNotFoundError) as exc:
                log.error("cannot start the Zenoh link: %s", exc)
                return ExitCode.USAGE
        final = runner.run(stop, max_duration_s=max_duration_s)
    finally:
        runner.shutdown()  # the vehicle first: hold, then tear down Zenoh and the log
        if zlink is not None:
            zlink.close()
        if flog is not None:
            flog.close()
    if runner.mission.failed:
        log.error("mission failed: %s", runner.mission.reason)
        return ExitCode.FAILURE
    log.info("fisc-agent stopped in %s (%s)", final.value, runner.mission.reason)
    return ExitCode.OK


def main(argv: list[str] | None = None) -> int:
    """``fisc-agent`` entry point: parse, validate, fly; returns the exit code."""
    args = build_parser().parse_args(argv)
    setup_logging(args, fmt="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        if not args.map_path and not args.swarm:
            raise ValueError("give --map FILE, or --swarm NAME to receive the map over Zenoh")
        if args.swarm and not args.trusted_key and not args.allow_unsigned:
            raise ValueError("--swarm needs --trusted-key PUB (or --allow-unsigned in a lab)")
        cfg = config_from_args(args)
    except (ValueError, EndpointError, MapError) as exc:
        log.error("%s", exc)
        return ExitCode.USAGE
    stop = threading.Event()

    def _on_signal(signum, _frame):
        log.info("signal %s: stopping (hold, then exit)", signal.Signals(signum).name)
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _on_signal)
    return run(cfg, stop, args.max_duration, args, args.flight_log)


def console() -> None:
    """The ``fisc-agent`` console script (``pyproject.toml``): ``main()`` through ``console_exit``."""
    console_exit(main)


if __name__ == "__main__":
    console()
