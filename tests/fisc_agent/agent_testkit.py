"""Test helpers for the agent tests: a small synthetic tunnel map (imported by conftest and tests)."""

from __future__ import annotations

import numpy as np

from fisc_agent.flight.health import VehicleHealth
from fisc_agent.flight.integrity import IntegrityVerdict



def tunnel_arrays(length_m: float = 3.0, radius_m: float = 1.0, cell_m: float = 0.5, speed_m_s: float = 2.0,
                  n_max: int = 3, seed: int = 0) -> tuple[dict, dict]:
    """A cylindrical tunnel of CVs along +x (axis on cell faces), flow speeding up along x."""
    n_side = int(round(2 * radius_m / cell_m))
    nx = int(round(length_m / cell_m))
    origin = np.array([0.0, -radius_m, -radius_m])
    grid = -np.ones((nx, n_side, n_side), dtype=np.int32)
    idx, centers = [], []
    for i in range(nx):
        for j in range(n_side):
            for k in range(n_side):
                c = origin + (np.array([i, j, k]) + 0.5) * cell_m
                if np.hypot(c[1], c[2]) <= radius_m:
                    grid[i, j, k] = len(idx)
                    idx.append((i, j, k))
                    centers.append(c)
    n = len(idx)
    centers = np.array(centers)
    rng = np.random.default_rng(seed)
    mean = np.zeros((n, 3))
    mean[:, 0] = speed_m_s * (1.0 + 0.2 * centers[:, 0] / length_m)
    mean[:, 1] = -0.1 * centers[:, 1]
    mean[:, 2] = -0.1 * centers[:, 2]
    n_star = rng.integers(2, n_max + 1, size=n).astype(np.int32)
    fit = np.full((n, n_max, 3), np.nan)
    for j in range(n):
        dev = rng.normal(0.0, 0.3, size=(n_star[j], 3))
        dev -= dev.mean(axis=0)
        fit[j, :n_star[j]] = mean[j] + dev
    zeros = np.zeros(n)
    arrays = {
        "cv_center_m": centers, "cv_index": np.array(idx, dtype=np.int32), "grid_cv": grid, "n_star": n_star,
        "fit_velocity_m_s": fit, "fit_mean_velocity_m_s": mean, "fit_pressure": zeros, "fit_loss": zeros,
        "target_velocity_m_s": mean, "target_pressure_gauge_pa": zeros, "target_density_kg_m3": zeros + 1.2,
        "swarm_pressure_target": zeros, "node_count": np.ones(n, dtype=np.int32),
    }
    meta = {
        "map_version": 1, "n_cv": n, "grid": {"origin_m": origin.tolist(), "cell_size_m": cell_m,
                                               "shape": list(grid.shape)},
        "n_range": [2, n_max], "scale": 1.0, "kappa": 1.0, "agent_mass_kg": 1.0, "max_speed_m_s": 5.0,
    }
    return meta, arrays


def tunnel_map_bytes(signing_key: bytes | None = None, map_version: int = 1, **kw) -> bytes:
    from fisc_agent.map.codec import encode_map

    meta, arrays = tunnel_arrays(**kw)
    meta["map_version"] = map_version
    return encode_map(meta, arrays, signing_key)




class EmulatorProbe:
    """Records what the project's autopilot emulator (``sim.autopilot``) receives, and injects
    faults into it at run time; the emulator still handles every message itself.

    ``setpoints``: (emulator time [s], vx, vy, vz, type_mask, frame, source system) of every
    SET_POSITION_TARGET_LOCAL_NED; ``commands``: (emulator time [s], command, params, source
    system) of every COMMAND_LONG.  Replaces the hand-written fake autopilot of earlier tests
    (issue 12), whose PX4 rules had drifted from the emulator's (offboard loss 0.5 s vs 1.0 s).
    """

    def __init__(self, emulator) -> None:
        import threading

        self.em = emulator
        self.setpoints: list[tuple] = []
        self.commands: list[tuple] = []
        self._lock = threading.Lock()
        handlers = emulator._handlers  # the emulator's own dispatch table, wrapped, not replaced
        sp, cmd = handlers["SET_POSITION_TARGET_LOCAL_NED"], handlers["COMMAND_LONG"]

        def on_setpoint(msg, now):
            with self._lock:
                self.setpoints.append((now, msg.vx, msg.vy, msg.vz, msg.type_mask, msg.coordinate_frame,
                                       msg.get_srcSystem()))
            sp(msg, now)

        def on_command(msg, now):
            with self._lock:
                self.commands.append((now, msg.command, (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5,
                                                         msg.param6, msg.param7), msg.get_srcSystem()))
            cmd(msg, now)

        handlers["SET_POSITION_TARGET_LOCAL_NED"] = on_setpoint
        handlers["COMMAND_LONG"] = on_command

    def setpoints_since(self, t_s: float) -> list[tuple]:
        with self._lock:
            return [s for s in self.setpoints if s[0] >= t_s]

    def commands_since(self, t_s: float) -> list[tuple]:
        with self._lock:
            return [c for c in self.commands if c[0] >= t_s]

    def drop_position(self, on: bool = True) -> None:
        """Stop (or restart) the position estimate and its messages from now on (a GPS/EKF loss)."""
        from sim.autopilot.faults import FaultConfig, FaultInjector

        windows = ((self.em.time_s, 1e9),) if on else ()
        self.em.faults = FaultInjector(FaultConfig(position_dropouts=windows))

    def mute(self, on: bool = True) -> None:
        """Lose every message in both directions from now on (a radio link loss)."""
        from sim.autopilot.faults import FaultConfig, FaultInjector

        self.em.faults = FaultInjector(FaultConfig(loss_probability=1.0 if on else 0.0))


class RecordingVehicle:
    """``VehicleCommands`` that records the intents it is asked for."""

    def __init__(self):
        self.sent = []           # ("arm",), ("set_mode", ModeClass), ("takeoff", alt_m)
        self.health = VehicleHealth()          # settable: the autopilot's health as a link reports it
        self.integrity = IntegrityVerdict()    # settable: the link's position integrity verdict

    def arm(self):
        self.sent.append(("arm",))

    def set_mode(self, mode):
        self.sent.append(("set_mode", mode))

    def takeoff(self, alt_m):
        self.sent.append(("takeoff", alt_m))

    def hold(self):
        from fisc_agent.mavlink.adapters import ModeClass

        self.set_mode(ModeClass.HOLD)

    def land(self):
        from fisc_agent.mavlink.adapters import ModeClass

        self.set_mode(ModeClass.LAND)
