"""Real autopilots for the tests: PX4 SITL (SIH physics) and ArduCopter SITL from ``../shared/sitl``.

Everything here runs the autopilots the way their READMEs say (``start.sh N``, ``stop.sh``,
API link on udp 14540+i, ground-station link on 14550), with the run state in a temporary folder:

- ``Px4Sitl`` / ``ArduPilotSitl``: context managers that start N vehicles, wait until they are
  ready (PX4: "Ready for takeoff" in each console log; ArduPilot: its pre-arm checks pass),
  and stop them, leaving their flight logs (ULog / DataFlash) in ``run_dir``; they hold
  ``MachineLock`` meanwhile (one set of vehicles per machine: fixed ports and sockets).
- The shared PX4 folder is read-only and its ``bin/px4-<module>`` command links arrive as plain
  files that name their target (``px4``); PX4's startup scripts call those commands, so
  ``px4_install`` lays a shadow install in the run folder: a copy of the ``px4`` binary, real
  symlinks for the module commands, and the read-only ``etc`` (ROMFS) linked in.
- ``ulog_*`` / ``dataflash_*``: the truth from the autopilots' own logs (pyulog, pymavlink DFReader).
- ``Track``: an agent's flight log (``fisc-agent --flight-log``), positions in the map frame.
"""

from __future__ import annotations

import fcntl
import glob
import os
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fisc_agent.flight.flightlog import read_flight_log
from fisc_agent.map.codec import CommandMap, load_map
from fisc_ground.fields.flight_score import track_from_rows

from .conftest import cli, free_tcp_port, run_cli, write_zenoh_config

HOME_LAT_DEG, HOME_LON_DEG, HOME_ALT_M = 47.397742, 8.545594, 489.4
"""The SITL folders' default home (both autopilots)."""

MAP_ANCHOR = f"{HOME_LAT_DEG},{HOME_LON_DEG},{HOME_ALT_M + 10.0},0"
"""``--geodetic-anchor`` of the map origin: 10 m above the shared SITL home, x axis north."""

MACHINE_LOCK = Path("/tmp/fisc-sitl.lock")
"""One set of SITL vehicles per machine at a time: both autopilots' instances use fixed ports
(udp 14540+i, 14550, PX4's 18570+i and 4560+i) and PX4 its command sockets ``/tmp/px4-sock-<i>``,
so a second test session (a second CI clone, a developer's run) would otherwise talk to the first
one's vehicles.  Held from start to stop; a second session waits for it."""


class MachineLock:
    """Exclusive ``flock`` on ``path`` (``MACHINE_LOCK``), waited for up to ``timeout_s``; the error names
    the holder's pid."""

    def __init__(self, timeout_s: float = 300.0, path: Path = MACHINE_LOCK) -> None:
        self.timeout_s, self.path = timeout_s, path
        self._fd: int | None = None

    def acquire(self) -> None:
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        end = time.monotonic() + self.timeout_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > end:
                    holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "unknown"
                    os.close(fd)
                    raise RuntimeError(f"SITL vehicles of another test session (pid {holder}) still hold "
                                       f"{self.path} after {self.timeout_s:.0f} s: stop that session first") from None
                time.sleep(1.0)
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)   # closing drops the flock
            self._fd = None


def ensure_ports_quiet(ports: list[int], listen_s: float = 1.0) -> None:
    """Fail clearly if something (a stray SITL instance from an earlier run) already sends to the
    autopilot ports: an agent would lock onto the wrong vehicle."""
    import socket

    socks = []
    try:
        for port in ports:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(("127.0.0.1", port))
            except OSError as exc:
                s.close()
                raise RuntimeError(f"udp port {port} is in use ({exc}): stop whatever holds it first") from None
            s.setblocking(False)
            socks.append((port, s))
        end = time.monotonic() + listen_s
        while time.monotonic() < end:
            for port, s in socks:
                try:
                    s.recv(4096)
                except BlockingIOError:
                    continue
                raise RuntimeError(f"something already sends MAVLink to udp {port} (a stray SITL instance?): "
                                   "stop it before starting the test's autopilots")
            time.sleep(0.05)
    finally:
        for _, s in socks:
            s.close()


def _wait(pred, timeout_s: float, period_s: float = 0.25):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        value = pred()
        if value:
            return value
        time.sleep(period_s)
    return None


def px4_install(shared_px4: Path, dest: Path) -> Path:
    """A runnable PX4 SITL folder at ``dest`` built from the read-only shared one."""
    dest.mkdir(parents=True, exist_ok=True)
    bin_dir = dest / "bin"
    bin_dir.mkdir(exist_ok=True)
    shutil.copy2(shared_px4 / "bin" / "px4", bin_dir / "px4")
    os.chmod(bin_dir / "px4", 0o755)
    for f in (shared_px4 / "bin").iterdir():
        target = bin_dir / f.name
        if f.name == "px4" or target.exists() or target.is_symlink():
            continue
        if f.name.startswith("px4-") and f.stat().st_size < 64 and f.read_text(errors="replace").strip() == "px4":
            target.symlink_to("px4")
        else:
            shutil.copy2(f, target)
    if not (dest / "etc").exists():
        (dest / "etc").symlink_to(shared_px4 / "etc")
    for script in ("start.sh", "stop.sh"):
        shutil.copy2(shared_px4 / script, dest / script)
        os.chmod(dest / script, 0o755)
    return dest


@dataclass
class SitlRun:
    """What a started SITL left: its run folder and how many vehicles."""

    run_dir: Path
    n: int


class _SitlSet:
    """A set of SITL vehicles as a context manager: ``_start`` under ``MachineLock``, ``_stop`` on
    exit or on any failure while starting, then the lock let go."""

    _lock: MachineLock

    def _start(self) -> SitlRun:
        raise NotImplementedError

    def _stop(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> SitlRun:
        self._lock.acquire()
        try:
            return self._start()
        except BaseException:
            self.__exit__(None, None, None)
            raise

    def __exit__(self, *exc) -> None:
        try:
            self._stop()
        finally:
            self._lock.release()


MAX_EXCURSION_M = 0.3
"""Bound on a vehicle flown by its agent beyond the duct's wall [m] (issue 37: < 0.3 m outside)."""
PX4_SIH_ESTIMATE_ERROR_M = 1.25
"""Largest distance between stock PX4 SIH's position estimate (what the agent steers on) and SIH's ground truth
in a pass [m].  EKF2 takes its height from GNSS (``EKF2_HGT_REF`` 1) and SIH's receiver wanders: over eleven
three-vehicle flights of ``tests/faults/test_px4_kills.py`` (2026-12-06) up to 0.73 m horizontally and 1.22 m
vertically (vertical RMS 0.21-0.59 m per pass), swinging by about 1 m within 10 s.  No agent sees it: the
estimate is its only position.  A lab sizes the airspace around the duct by its own positioning's error
(docs/deployment.md, "Position error and the airspace")."""
TRUTH_EXCURSION_M = MAX_EXCURSION_M + PX4_SIH_ESTIMATE_ERROR_M
"""Bound by SIH's ground truth on a vehicle flown by its agent beyond the duct's wall [m]: the agent's own bound
on the estimate (``MAX_EXCURSION_M``, checked beside it by ``view_excursion_m``) plus the estimator's error.
It catches what the view cannot: a wrong frame or anchor, a clock or latency error, a vehicle the estimate lost.
Until 2026-12-06 it was 0.45 m; two of four flights then went 0.46 and 0.48 m beyond the wall by the truth while
0.57 m inside by PX4's estimate, which was 1.22 m low there."""
FAILSAFE_EXCURSION_M = 0.45
"""After the agent is killed, PX4 alone: it flies the last setpoint for COM_OF_LOSS_T (0.5 s), then its
Hold brakes.  That is PX4's own stopping distance, not the agent's flight: 0.16 m inside to 0.03 m
outside (2 runs, 2026-12-01), 0.342 m (tuned gains, 2026-12-04), 0.344 m (stock gains, 2026-12-05) beyond
the wall.  A lab sizes its airspace for it (docs/deployment.md, COM_OF_LOSS_T)."""
FAILSAFE_STOP_S = 5.0
"""PX4's failsafe has stopped a killed agent's vehicle this long after the kill (measured: it comes to rest
2-3 s after; COM_OF_LOSS_T 0.5 s, then Hold's braking) [s].  ``FAILSAFE_EXCURSION_M`` judges this window
only: after it the vehicle is agent-less in PX4's Hold, whose wander in SIH is PX4's (reported, not judged)."""
PX4_SIH_AIRFRAMES = {"quadx": (10040, "sihsim_quadx"), "hex": (10044, "sihsim_hex")}
"""PX4's SIH multicopters in the shared build (``etc/init.d-posix/airframes``): name -> (SYS_AUTOSTART,
PX4_SIM_MODEL).  start.sh flies the quadcopter; the hexacopter is another airframe with its own stock
parameters (mass, inertia, rotor geometry), for the agent's adaptation (issue 37)."""


class Px4Sitl(_SitlSet):
    """``with Px4Sitl(shared/sitl/px4, tmp, n) as run:`` N PX4 SIH vehicles, ready to arm."""

    def __init__(self, shared_px4: Path, work: Path, n: int = 1, spacing_m: float | None = None,
                 params: dict[str, float] | None = None, ready_timeout_s: float = 60.0,
                 airframe: str = "quadx") -> None:
        if airframe not in PX4_SIH_AIRFRAMES:
            raise ValueError(f"airframe {airframe!r}: one of {sorted(PX4_SIH_AIRFRAMES)}")
        self.install = px4_install(shared_px4, work / "px4-install")
        self.run_dir = work / "px4-run"
        self.n, self.spacing_m, self.params, self.airframe = n, spacing_m, dict(params or {}), airframe
        self.ready_timeout_s = ready_timeout_s
        self._lock = MachineLock()

    def _env(self) -> dict[str, str]:
        env = dict(os.environ, PX4_SITL_RUN=str(self.run_dir))
        if self.spacing_m is not None:
            env["SITL_SPACING_M"] = str(self.spacing_m)
        extra = [f"PX4_PARAM_{k}={v}" for k, v in self.params.items()]
        if self.airframe != "quadx":  # start.sh passes these on after its own (10040, sihsim_quadx): they win
            autostart, model = PX4_SIH_AIRFRAMES[self.airframe]
            extra = [f"PX4_SYS_AUTOSTART={autostart}", f"PX4_SIM_MODEL={model}", *extra]
        if extra:
            env["SITL_EXTRA_PARAMS"] = " ".join(extra)
        return env

    def console(self, i: int) -> str:
        p = self.run_dir / "logs" / f"px4_{i}.log"
        return p.read_text(errors="replace") if p.exists() else ""

    def _start(self) -> SitlRun:
        ensure_ports_quiet([14540 + i for i in range(self.n)] + [14550])
        out = subprocess.run([str(self.install / "start.sh"), str(self.n)], env=self._env(), capture_output=True,
                             text=True, timeout=60)
        if out.returncode != 0:
            raise RuntimeError(f"PX4 SITL did not start: {out.stdout}{out.stderr}\n{self.console(0)[-2000:]}")
        ready = _wait(lambda: all("Ready for takeoff" in self.console(i) for i in range(self.n)),
                      self.ready_timeout_s)
        if not ready:
            logs = "\n".join(self.console(i)[-1500:] for i in range(self.n))
            raise RuntimeError(f"PX4 SITL not ready for takeoff within {self.ready_timeout_s:.0f} s:\n{logs}")
        return SitlRun(self.run_dir, self.n)

    def _stop(self) -> None:
        subprocess.run([str(self.install / "stop.sh")], env=self._env(), capture_output=True, timeout=60)


class ArduPilotSitl(_SitlSet):
    """``with ArduPilotSitl(shared/sitl/ardupilot, tmp, n) as run:`` N ArduCopters whose pre-arm checks pass;
    ``params`` are set at boot on every instance (start.sh's ``SITL_EXTRA_PARAMS``)."""

    def __init__(self, shared_ap: Path, work: Path, n: int = 1, spacing_m: float | None = None,
                 ready_timeout_s: float = 90.0, params: dict[str, float] | None = None) -> None:
        self.shared = shared_ap
        self.run_dir = work / "ap-run"
        self.n, self.spacing_m, self.params = n, spacing_m, dict(params or {})
        self.ready_timeout_s = ready_timeout_s
        self._lock = MachineLock()

    def _env(self) -> dict[str, str]:
        env = dict(os.environ, AP_SITL_RUN=str(self.run_dir))
        if self.spacing_m is not None:
            env["SITL_SPACING_M"] = str(self.spacing_m)
        if self.params:  # start.sh: boot-time parameters of every instance (SIM_BATT_* only act at boot)
            env["SITL_EXTRA_PARAMS"] = " ".join(f"{k}={v}" for k, v in self.params.items())
        return env

    def _start(self) -> SitlRun:
        from pymavlink import mavutil

        ensure_ports_quiet([14540 + i for i in range(self.n)] + [14550])
        gcs = mavutil.mavlink_connection("udpin:127.0.0.1:14550", source_system=245)  # the GCS link
        try:
            out = subprocess.run([str(self.shared / "start.sh"), str(self.n)], env=self._env(), capture_output=True,
                                 text=True, timeout=60)
            if out.returncode != 0:
                raise RuntimeError(f"ArduPilot SITL did not start: {out.stdout}{out.stderr}")
            # ready = ArduPilot's own pre-arm checks pass (SYS_STATUS health bit MAV_SYS_STATUS_PREARM_CHECK,
            # streamed on request over the GCS link); its EKF is then using GPS (about 20-40 s after start)
            ready: set[int] = set()
            asked: dict[int, float] = {}
            end = time.monotonic() + self.ready_timeout_s
            while len(ready) < self.n and time.monotonic() < end:
                m = gcs.recv_match(type=["HEARTBEAT", "SYS_STATUS"], blocking=True, timeout=1.0)
                if m is None:
                    continue
                sysid = m.get_srcSystem()
                if m.get_type() == "HEARTBEAT" and time.monotonic() - asked.get(sysid, -10.0) > 2.0:
                    gcs.mav.command_long_send(sysid, 1, 511, 0, 1, 500_000, 0, 0, 0, 0, 0)  # SYS_STATUS at 2 Hz
                    asked[sysid] = time.monotonic()
                elif m.get_type() == "SYS_STATUS" and m.onboard_control_sensors_health & 0x10000000:
                    ready.add(sysid)
            if len(ready) < self.n:
                raise RuntimeError(f"ArduPilot pre-arm checks not passing within {self.ready_timeout_s:.0f} s "
                                   f"(ready: {sorted(ready)})")
        finally:
            gcs.close()
        return SitlRun(self.run_dir, self.n)

    def _stop(self) -> None:
        subprocess.run([str(self.shared / "stop.sh")], env=self._env(), capture_output=True, timeout=60)


def px4_pid(run: SitlRun, i: int) -> int:
    """pid of the running PX4 instance ``i`` (``start.sh``'s ``px4.pids``)."""
    for line in (run.run_dir / "px4.pids").read_text().splitlines():
        pid, inst = line.split()
        if int(inst) == i:
            return int(pid)
    raise LookupError(f"PX4 instance {i} is not in {run.run_dir / 'px4.pids'}")


# ---- the autopilots' own logs ------------------------------------------------------------
def px4_ulog(run: SitlRun, i: int) -> Path:
    """The newest ULog of PX4 instance ``i``."""
    files = sorted(glob.glob(str(run.run_dir / "logs" / f"ulog_{i}" / "*" / "*.ulg")), key=os.path.getmtime)
    if not files:
        raise FileNotFoundError(f"no ULog for PX4 instance {i} under {run.run_dir}")
    return Path(files[-1])


@dataclass(frozen=True)
class UlogSummary:
    """What a PX4 flight log says about a flight."""

    offboard_setpoint_hz: float
    """Median rate at which PX4 *logged* its offboard setpoint (trajectory_setpoint) while in
    OFFBOARD [Hz]: the default logger profile samples it at about 5 Hz, so this is a floor."""
    max_setpoint_gap_s: float
    """Longest gap between two logged offboard setpoints while in OFFBOARD [s]."""
    failsafe_seen: bool
    """vehicle_status.failsafe was set at some point."""
    gps_fused: bool
    """The estimator fused GNSS position (estimator_status_flags.cs_gnss_pos / cs_gps)."""
    nav_states: tuple[int, ...]
    """The sequence of vehicle_status.nav_state values (consecutive repeats removed)."""
    max_pos_error_m: float
    """Largest horizontal distance between PX4's position estimate and SIH's ground truth [m]."""


def ulog_summary(path: Path) -> UlogSummary:
    from pyulog import ULog

    u = ULog(str(path), ["vehicle_status", "trajectory_setpoint", "estimator_status_flags",
                         "vehicle_local_position", "vehicle_local_position_groundtruth"])

    def data(name):
        ds = [d for d in u.data_list if d.name == name]
        return ds[0].data if ds else None

    st = data("vehicle_status")
    nav = st["nav_state"].astype(int)
    states = tuple(int(s) for k, s in enumerate(nav) if k == 0 or s != nav[k - 1])
    NAV_OFFBOARD = 14
    t_st = st["timestamp"]
    off = nav == NAV_OFFBOARD
    ts = data("trajectory_setpoint")
    gaps: list[np.ndarray] = []
    if ts is not None and off.any():
        t_sp = ts["timestamp"]
        edges = np.flatnonzero(np.diff(np.r_[0, off.astype(int), 0]))  # OFFBOARD episodes [start, end)
        for a, b in zip(edges[::2], edges[1::2]):
            t0, t1 = t_st[a], (t_st[b] if b < len(t_st) else np.inf)
            sel = t_sp[(t_sp >= t0) & (t_sp < t1)] / 1e6
            if len(sel) > 2:
                gaps.append(np.diff(sel))
    d = np.concatenate(gaps) if gaps else np.array([])
    hz, gap = (1.0 / float(np.median(d)), float(d.max())) if len(d) else (0.0, float("inf"))
    flags = data("estimator_status_flags")
    key = "cs_gnss_pos" if flags is not None and "cs_gnss_pos" in flags else "cs_gps"
    gps = bool(flags is not None and np.any(flags[key]))
    lp, gt = data("vehicle_local_position"), data("vehicle_local_position_groundtruth")
    err = float("nan")
    if lp is not None and gt is not None:
        j = np.clip(np.searchsorted(gt["timestamp"], lp["timestamp"]), 0, len(gt["timestamp"]) - 1)
        err = float(np.max(np.hypot(lp["x"] - gt["x"][j], lp["y"] - gt["y"][j])))
    return UlogSummary(hz, gap, bool(np.any(st["failsafe"])), gps, states, err)


def truth_track(path: Path, map_above_start_m: float = 10.0, x_lo_m: float = 0.0, x_hi_m: float = 15.0,
                near_axis_m: float = 3.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """SIH's ground truth (``vehicle_local_position_groundtruth``) of the pass, in the map frame, as
    ``(t_s, pos_m, vel_m_s, states)`` for ``fisc_ground.fields.flight_score.score_track``.

    The vehicle's real motion, not PX4's estimate of it: EKF2's velocity estimate carries a bias
    that the agent's streamline tracking corrects for (measured: an estimate of 0.73-0.79 m/s
    where the vehicle truly flew 0.36-0.50 m/s near the outlet), so a score from the estimate
    counts the correction as an error.  The local frame's origin is the start point and the map
    origin ``map_above_start_m`` above it (the default deployment transform).  Samples from the
    first forward motion inside ``[x_lo_m, x_hi_m]`` within ``near_axis_m`` of the map's axis up to
    the first one past ``x_hi_m`` are the pass (state ``FLOW``); the rest are ``JOIN``.  (Without the
    axis bound a take-off that drifted forward past x = 0, 8-10 m below the map, began the pass: one
    MAVSDK flight in ten then scored a truth excursion of 8.4 m and velocity 0.121 while the agent's
    own pass began 14 s later at the inlet.)
    """
    from pyulog import ULog

    gt = ULog(str(path), ["vehicle_local_position_groundtruth"]).get_dataset(
        "vehicle_local_position_groundtruth").data
    pos = np.stack([gt["x"], gt["y"], -(gt["z"] + map_above_start_m)], axis=1).astype(float)
    vel = np.stack([gt["vx"], gt["vy"], -gt["vz"]], axis=1).astype(float)
    return gt["timestamp"] / 1e6, pos, vel, pass_states(pos, vel, x_lo_m, x_hi_m, near_axis_m)


CLOCK_WINDOW_S = 10.0
"""Span of PX4's clock over which ``truth_on_wall_clock`` fits one offset of the clock map [s] (its knots are half
of it apart)."""
CLOCK_DRIFT_S = 2.0
"""How far a knot's offset may stray from the affine map's [s]: lockstep SIH in the full suite drifted 1.96 s over
two minutes (2026-12-06).  Below 0.95 x CLOCK_WINDOW_S / 4, so the clock map never runs backwards."""


@dataclass(frozen=True)
class WallTruth:
    """SIH's ground truth of one vehicle in the map frame, on the agents' wall clock."""

    wall_s: np.ndarray
    """(n,) UNIX time of each sample [s]."""
    pos_m: np.ndarray
    """(n, 3) true position, map frame [m]."""
    px4_s: np.ndarray
    """(n,) the sample's time on PX4's own clock [s]."""
    clock_rate: float
    """Wall seconds per PX4 second over the flight: lockstep SIH runs a few per cent slower than the wall clock."""
    knots_px4_s: np.ndarray
    """(k,) PX4 times at which the clock map's offset is fitted [s]."""
    knots_offset_s: np.ndarray
    """(k,) the offset there: wall = clock_rate * px4 + offset, linear between knots, constant beyond [s]."""
    fit_rms_m: float
    """RMS distance between PX4's estimate and the agent's log once the clocks are matched [m]."""

    def to_wall(self, px4_s) -> np.ndarray:
        """Times on PX4's clock [s] (a ULog's timestamps / 1e6) on the wall clock [UNIX s]."""
        t = np.asarray(px4_s, dtype=float)
        return self.clock_rate * t + np.interp(t, self.knots_px4_s, self.knots_offset_s)


def _clock_map_cost(wall_s: np.ndarray, p_est: np.ndarray, track: "Track") -> float:
    """Mean squared distance between PX4's estimate put at ``wall_s`` and the agent's log there (inf: < 50 samples
    overlap)."""
    sel = np.flatnonzero((wall_s >= track.wall_s[0]) & (wall_s <= track.wall_s[-1]))
    if len(sel) < 50:
        return np.inf
    logged = np.column_stack([np.interp(wall_s[sel], track.wall_s, track.pos_m[:, k]) for k in range(3)])
    return float(np.mean(np.sum((logged - p_est[sel]) ** 2, axis=1)))


def truth_on_wall_clock(path: Path, track: "Track", anchor: str, ulog_end_wall_s: float | None = None) -> WallTruth:
    """SIH's true position (``vehicle_global_position_groundtruth``) of a vehicle flown with
    ``--geodetic-anchor anchor``, in the map frame and on the agent's wall clock.

    A ULog is stamped with PX4's (lockstep, simulated) clock, the agent's log with the UNIX clock.
    PX4's own position estimate (``vehicle_global_position``) is what the agent logged, so the clock map
    that best lays one on the other carries the truth onto the wall clock: first one affine map
    t_wall = a + b t_px4 (least squares over a grid of b in [0.95, 1.05] and a within 4 s of the logs' ends
    meeting), then, with b kept, an offset per ``CLOCK_WINDOW_S`` of PX4's clock (within ``CLOCK_DRIFT_S`` of a),
    linear between them.  Lockstep's rate follows the host's load: in the full suite on 2 cores one affine map
    left 0.21-0.46 m RMS, the offsets 0.046-0.051 m (2026-12-06; one affine map 0.02 m on a steady host, a pure
    offset 0.13-0.27 m).  The ULog ends at ``ulog_end_wall_s`` [UNIX s] (default: when the agent's log does;
    give it when PX4 flew on without its agent, which was killed).
    """
    from pyulog import ULog

    from fisc_agent.flight.frames import GeodeticAnchor

    geo = GeodeticAnchor.parse(anchor)
    tf = geo.transform()
    u = ULog(str(path), ["vehicle_global_position", "vehicle_global_position_groundtruth"])

    def in_map(name: str) -> tuple[np.ndarray, np.ndarray]:
        d = u.get_dataset(name).data
        ned = np.array([geo.geodetic_to_ned(a, b, c) for a, b, c in zip(d["lat"], d["lon"], d["alt"])])
        return d["timestamp"] / 1e6, tf.ned_to_map(ned)

    t_est, p_est = in_map("vehicle_global_position")
    t_gt, p_gt = in_map("vehicle_global_position_groundtruth")
    thin = slice(None, None, 10)
    best = (np.inf, 1.0, 0.0)
    for rate in np.arange(0.95, 1.05 + 1e-9, 0.0025):
        end = (track.wall_s[-1] if ulog_end_wall_s is None else ulog_end_wall_s) - rate * t_est[-1]
        for offset in np.arange(end - 4.0, end + 4.0, 0.05):
            cost = _clock_map_cost(rate * t_est[thin] + offset, p_est[thin], track)
            if cost < best[0]:
                best = (cost, float(rate), float(offset))
    if not np.isfinite(best[0]):
        raise ValueError(f"{path}: PX4's estimate and the agent's log {track.wall_s[0]:.0f}-{track.wall_s[-1]:.0f} "
                         "do not overlap")
    _, rate, offset = best
    knots = np.arange(t_est[0], t_est[-1] + CLOCK_WINDOW_S / 2, CLOCK_WINDOW_S / 2)
    offsets = np.full(knots.size, offset)
    for k, knot in enumerate(knots):
        near = np.flatnonzero(np.abs(t_est - knot) <= CLOCK_WINDOW_S / 2)[::2]
        costs = [(_clock_map_cost(rate * t_est[near] + o, p_est[near], track), o)
                 for o in np.arange(offset - CLOCK_DRIFT_S, offset + CLOCK_DRIFT_S + 1e-9, 0.01)]
        cost_k, o_k = min(costs)
        if np.isfinite(cost_k):
            offsets[k] = o_k
    wall_est = rate * t_est + np.interp(t_est, knots, offsets)
    rms = _clock_map_cost(wall_est, p_est, track) ** 0.5
    return WallTruth(rate * t_gt + np.interp(t_gt, knots, offsets), p_gt, t_gt, rate, knots, offsets, rms)


def truth_pass(truth: WallTruth, x_lo_m: float = 0.0, x_hi_m: float = 15.0,
               near_axis_m: float = 3.0, track: "Track | None" = None) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                               np.ndarray]:
    """``(t_s, pos_m, vel_m_s, states)`` of a fleet vehicle's ground truth (``truth_on_wall_clock``)
    for ``score_track``, as ``truth_track`` gives them for a lone vehicle: the velocity by central
    differences on PX4's own clock (the wall clock runs about ``clock_rate`` faster), the pass by
    ``pass_states``; with the agent's ``track``, the pass starts only while its log says FLOW (a join
    that gave its window up climbs over the tunnel, near the axis and moving forward, without flowing)."""
    keep = np.concatenate([[True], (np.diff(truth.wall_s) > 0) & (np.diff(truth.px4_s) > 0)])
    t, pos = truth.wall_s[keep], truth.pos_m[keep]
    vel = np.gradient(pos, truth.px4_s[keep], axis=0)
    flowing = None if track is None else flowing_at(track, t)
    return t, pos, vel, pass_states(pos, vel, x_lo_m, x_hi_m, near_axis_m, flowing)


def flowing_at(track: "Track", wall_s: np.ndarray) -> np.ndarray:
    """(n,) bool: does the agent's log say FLOW at the wall times ``wall_s`` (the state of the log row at or
    after each time, the last row beyond it)?"""
    idx = np.clip(np.searchsorted(track.wall_s, wall_s), 0, len(track.wall_s) - 1)
    return track.states[idx] == "FLOW"


def pass_states(pos_m: np.ndarray, vel_m_s: np.ndarray, x_lo_m: float, x_hi_m: float,
                near_axis_m: float, flowing: np.ndarray | None = None) -> np.ndarray:
    """(n,) ``FLOW`` from the first forward motion inside ``[x_lo_m, x_hi_m]`` within ``near_axis_m`` of
    the map's axis (map frame; where ``flowing`` is given, only where it is True) up to the first sample
    past ``x_hi_m``, ``JOIN`` elsewhere."""
    x = pos_m[:, 0]
    states = np.full(len(x), "JOIN", dtype=object)
    near = np.hypot(pos_m[:, 1], pos_m[:, 2]) <= near_axis_m
    if flowing is not None:
        near = near & flowing
    start = np.flatnonzero((x >= x_lo_m) & (x <= x_hi_m) & (vel_m_s[:, 0] > 0.2) & near)
    if start.size:
        past = np.flatnonzero((x > x_hi_m) & (np.arange(len(x)) > start[0]))
        states[start[0]:(past[0] + 1 if past.size else len(x))] = "FLOW"
    return states.astype(str)


def dataflash_log(run: SitlRun, i: int) -> Path:
    files = sorted(glob.glob(str(run.run_dir / "instances" / str(i) / "logs" / "*.BIN")), key=os.path.getmtime)
    if not files:
        raise FileNotFoundError(f"no DataFlash log for ArduPilot instance {i} under {run.run_dir}")
    return Path(files[-1])


def dataflash_modes_and_texts(path: Path) -> tuple[list[int], list[str]]:
    """(flight mode numbers in order, STATUSTEXT messages) from an ArduPilot DataFlash log."""
    from pymavlink import DFReader

    log = DFReader.DFReader_binary(str(path))
    modes, texts = [], []
    while True:
        m = log.recv_match(type=["MODE", "MSG"])
        if m is None:
            break
        if m.get_type() == "MODE":
            if not modes or modes[-1] != m.Mode:
                modes.append(int(m.Mode))
        else:
            texts.append(str(m.Message))
    return modes, texts


# ---- the agent's own flight log ------------------------------------------------------------
@dataclass
class Track:
    """One agent's flight log as arrays (map frame)."""

    rows: list[dict[str, str]]
    t_s: np.ndarray
    pos_m: np.ndarray
    vel_m_s: np.ndarray
    states: np.ndarray
    wall_s: np.ndarray

    @classmethod
    def read(cls, path: Path) -> "Track":
        rows = read_flight_log(path)
        t, pos, vel, states = track_from_rows(rows)
        wall = np.array([float(r["wall_time_s"]) for r in rows if r["x_m"] != "" and r["vx_m_s"] != ""])
        return cls(rows, t, pos, vel, states, wall)

    def hold_altitude_range_m(self, min_duration_s: float = 5.0) -> tuple[float, float]:
        """(largest |z - z at the hold's start| during the last HOLD, its duration [s])."""
        hold = np.flatnonzero(self.states == "HOLD")
        if not hold.size:
            return float("nan"), 0.0
        start = hold[0]
        for k in range(len(hold) - 1, 0, -1):  # the last contiguous HOLD episode
            if hold[k] - hold[k - 1] > 1:
                start = hold[k]
                break
        seg = hold[hold >= start]
        z = self.pos_m[seg, 2]
        return float(np.max(np.abs(z - z[0]))), float(self.t_s[seg[-1]] - self.t_s[seg[0]])


def view_excursion_m(track: Track, ref, scale: float, wall) -> float:
    """Largest distance beyond ``wall`` in the agent's own view (its flight log's FLOW rows: PX4's
    estimate, what it steers on) [m]; nan when it never flowed."""
    from fisc_ground.fields.flight_score import score_track

    return score_track(track.t_s, track.pos_m, track.vel_m_s, track.states, ref, scale, wall=wall).max_excursion_m


# ---- the ground side of a fleet test ----------------------------------------------------------
def ground(*args) -> list[str]:
    """argv of ``fisc-ground ARGS``."""
    return cli("fisc-ground") + [str(a) for a in args]


def ok(out) -> str:
    """stdout of a finished command; its output in the failure message otherwise."""
    assert out.returncode == 0, f"{out.args}: exit {out.returncode}\n{out.stdout}\n{out.stderr}"
    return out.stdout


def latest_states(logs: list[Path]) -> list[str]:
    """The newest mission state in each agent's flight log ("" for a log not written yet)."""
    out = []
    for p in logs:
        try:
            rows = read_flight_log(p)
        except (OSError, KeyError):
            rows = []
        out.append(rows[-1]["state"] if rows else "")
    return out


def mission_story(logs: list[Path]) -> str:
    """Each agent's mission as its flight log tells it, one line per agent: the states it went
    through with their reasons (for the end of an assertion message, where a CI's tail shows it)."""
    lines = []
    for i, p in enumerate(logs):
        try:
            rows = read_flight_log(p)
        except (OSError, KeyError) as e:
            lines.append(f"agent {i}: no flight log ({e})")
            continue
        steps = [f"{r['state']} ({r['reason']})" for k, r in enumerate(rows)
                 if k == 0 or (r["state"], r["reason"]) != (rows[k - 1]["state"], rows[k - 1]["reason"])]
        lines.append(f"agent {i}: " + " > ".join(steps))
    return "\n".join(lines)


@dataclass(frozen=True)
class SignedMapOnZenoh:
    """A ground key, the embedded default map fitted and signed with it, and Zenoh configs on loopback."""

    served: Path
    """The map file ``fisc-ground publish`` serves."""
    good: CommandMap
    """That map, verified against the ground key."""
    ground_key: Path
    ground_pub: Path
    hub: Path
    """Zenoh config of the publisher (listens)."""
    member: Path
    """Zenoh config of everyone else (connects to the hub)."""


def signed_map_on_zenoh(d: Path) -> SignedMapOnZenoh:
    ok(run_cli(ground("keygen", "-o", d / "ground")))
    served = d / "served.fiscmap"
    ok(run_cli(ground("fit", "cd_nozzle_inviscid", "-o", served, "--sign", d / "ground.key")))
    port = free_tcp_port()
    hub = write_zenoh_config(d / "hub.json5", [f"tcp/127.0.0.1:{port}"], [])
    member = write_zenoh_config(d / "member.json5", ["tcp/127.0.0.1:0"], [f"tcp/127.0.0.1:{port}"])
    return SignedMapOnZenoh(served, load_map(served, d / "ground.pub"), d / "ground.key", d / "ground.pub", hub, member)


# ---- a ground station and PX4 log topics for the authority tests ------------------------------
from .ground_station import GroundStation  # noqa: E402,F401 (the tests import it from the kit)


def ulog_topic(path: Path, name: str) -> dict[str, np.ndarray] | None:
    """One topic of a ULog as arrays (``timestamp`` in microseconds of PX4's clock), None if not logged."""
    from pyulog import ULog

    ds = [d for d in ULog(str(path), [name]).data_list if d.name == name]
    return ds[0].data if ds else None


def dedup(seq) -> list:
    """``seq`` with consecutive repeats removed."""
    out: list = []
    for v in seq:
        if not out or out[-1] != v:
            out.append(v)
    return out


class LinkCut:
    """A UDP relay between an autopilot's API port and an agent, that can cut the link both ways.

    ``with LinkCut(14540) as cut:`` binds udp ``autopilot_port`` (where the SITL sends its API link) and
    relays every datagram to the agent at ``127.0.0.1:cut.agent_port`` (run the agent with ``--mavlink
    udpin:0.0.0.0:<agent_port>``) and the agent's back to the autopilot's address.  ``cut.down = True``
    drops everything in both directions (the radio or cable gone), ``False`` relays again: the agent and
    the autopilot both keep running, unlike a frozen process."""

    def __init__(self, autopilot_port: int = 14540) -> None:
        import socket
        import threading

        from .conftest import free_udp_port

        self.agent_port = free_udp_port()
        self.down = False
        self.dropped = 0
        self._ap = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._ap.bind(("0.0.0.0", autopilot_port))
        self._ag = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._ag.bind(("127.0.0.1", 0))
        self._ap_addr: tuple[str, int] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="link-cut", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import select

        while not self._stop.is_set():
            ready, _, _ = select.select([self._ap, self._ag], [], [], 0.1)
            for s in ready:
                data, addr = s.recvfrom(65535)
                if self.down:
                    self.dropped += 1
                    continue
                if s is self._ap:
                    self._ap_addr = addr
                    self._ag.sendto(data, ("127.0.0.1", self.agent_port))
                elif self._ap_addr is not None:
                    self._ap.sendto(data, self._ap_addr)

    def __enter__(self) -> "LinkCut":
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._ap.close()
        self._ag.close()
