"""Stock PX4's multicopter velocity loop on PX4 SIH's quadrotor: the emulator's ``px4-sih-loop`` vehicle.

The paper's :class:`~sim.plant.model.VelocityPlant` shapes velocity proportionally against quadratic drag; the
``px4-sih`` preset fits it to stock PX4 flights without the agent's drag feed-forward.  With the feed-forward
the difference shows: PX4 holds its speed with an integrator, SIH's drag is linear (``SIH_KDV``), and the agent
feeds forward a linear ``c v_sp``.  On the quadratic plant that term is three times the drag at the inlet's
0.45 m/s and 0.84 of it at the throat's 1.8, and the emulated eight-vehicle loop scored density r 0.57-0.66
against the real fleet's 0.87-0.94 (2026-12-07).  This model is the loop itself
(``tools/px4_loop_model.py`` is its offline one-axis twin, which reproduced SIH's measured speed ratios):

- velocity PID per axis (PX4's ``PositionControl::_velocityControl``): ``a_sp = P e + I int(e) - D dv/dt + a_ff``
  with stock ``MPC_XY_VEL_P/I/D_ACC`` 1.8 / 0.4 / 0.2 and ``MPC_Z_VEL_P/I_ACC`` 4 / 2, the integrator bounded;
- the thrust ``a_sp - g`` (hover thrust holds the weight), horizontal part limited to ``MPC_TILTMAX_AIR``;
- a first-order thrust lag, then ``dv/dt = a_T + g - c v`` with SIH's linear drag ``c`` (1 N s/m on 1 kg).

Its interface is the part of :class:`~sim.plant.model.VelocityPlant` the emulated vehicle uses (one vehicle:
``velocity``, ``thrust_accel``, ``reset``, ``step``, ``fixed_step``), plus ``accel_ff_ned_m_s2``, the
setpoint's acceleration the vehicle sets before each step (the VelocityPlant takes it as more velocity
command instead).  Plain floats: for one vehicle numpy's per-call cost would dominate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["PX4_LOOP_PLANT", "Px4LoopParams", "Px4LoopPlant"]

PX4_LOOP_PLANT = "px4-sih-loop"
"""The emulator's name for this vehicle model (``fisc-sim emulate --plant``; PX4 personality only)."""


@dataclass(frozen=True)
class Px4LoopParams:
    """Stock PX4 velocity-loop gains and PX4 SIH's quadrotor (the defaults are both's stock values)."""

    p_xy_1_s: float = 1.8
    """``MPC_XY_VEL_P_ACC``: horizontal proportional gain [1/s]."""
    i_xy_1_s2: float = 0.4
    """``MPC_XY_VEL_I_ACC``: horizontal integral gain [1/s^2]."""
    d_xy: float = 0.2
    """``MPC_XY_VEL_D_ACC``: horizontal derivative gain, on the vehicle's acceleration [-]."""
    p_z_1_s: float = 4.0
    """``MPC_Z_VEL_P_ACC``: vertical proportional gain [1/s]."""
    i_z_1_s2: float = 2.0
    """``MPC_Z_VEL_I_ACC``: vertical integral gain [1/s^2]."""
    integrator_limit_m_s2: float = 9.81
    """Bound of each axis's integrator [m/s^2] (PX4 bounds it by the thrust it can still give)."""
    tilt_max_deg: float = 45.0
    """``MPC_TILTMAX_AIR``: the thrust's largest tilt from vertical [deg]."""
    drag_1_s: float = 1.0
    """SIH's linear drag over its mass, ``SIH_KDV / SIH_MASS`` [1/s] (stock 1 N s/m on 1 kg)."""
    tau_thrust_s: float = 0.05
    """First-order lag of the thrust behind its setpoint [s] (attitude loop and motors)."""
    g_m_s2: float = 9.81
    """Gravitational acceleration [m/s^2], +down in NED."""
    max_substep_s: float = 0.005
    """Longest integration sub-step [s] (the PID runs on each)."""

    def __post_init__(self) -> None:
        for name in ("p_xy_1_s", "p_z_1_s", "integrator_limit_m_s2", "tau_thrust_s", "g_m_s2", "max_substep_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"px4 loop: {name} must be finite and > 0, is {v!r}")
        for name in ("i_xy_1_s2", "d_xy", "i_z_1_s2", "drag_1_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"px4 loop: {name} must be finite and >= 0, is {v!r}")
        if not 0 < self.tilt_max_deg < 90:
            raise ValueError(f"px4 loop: tilt_max_deg must be in (0, 90), is {self.tilt_max_deg!r}")


class Px4LoopPlant:
    """One vehicle flying stock PX4's velocity loop (module docstring); starts hovering."""

    def __init__(self, params: Px4LoopParams = Px4LoopParams()) -> None:
        self.params = params
        self.velocity = np.zeros((1, 3))
        """Velocity [m/s] NED, (1, 3) as VelocityPlant's (the vehicle writes its vertical part on the ground)."""
        self.thrust_accel = np.zeros((1, 3))
        """Realised thrust acceleration [m/s^2] NED, (1, 3)."""
        self.accel_ff_ned_m_s2 = (0.0, 0.0, 0.0)
        """The setpoint's acceleration, added to the PID's output (PX4's ``_acc_sp``); set before each step."""
        self._integ = [0.0, 0.0, 0.0]
        self._dv = [0.0, 0.0, 0.0]
        self._gains = ((params.p_xy_1_s, params.i_xy_1_s2, params.d_xy), (params.p_xy_1_s, params.i_xy_1_s2, params.d_xy),
                       (params.p_z_1_s, params.i_z_1_s2, 0.0))  # (P, I, D) of north, east, down
        self._tan_tilt = math.tan(math.radians(params.tilt_max_deg))
        self.reset()

    def reset(self, velocity_ned_m_s: np.ndarray | None = None, thrust_accel_ned_m_s2: np.ndarray | None = None) -> None:
        """Hover (or fly at ``velocity_ned_m_s``) with the thrust that holds it and the integrator at rest."""
        v = [0.0, 0.0, 0.0] if velocity_ned_m_s is None else [float(x) for x in np.ravel(velocity_ned_m_s)[:3]]
        c, g = self.params.drag_1_s, self.params.g_m_s2
        trim = [c * v[0], c * v[1], c * v[2] - g]
        thr = trim if thrust_accel_ned_m_s2 is None else [float(x) for x in np.ravel(thrust_accel_ned_m_s2)[:3]]
        self.velocity[0] = v
        self.thrust_accel[0] = thr
        self._integ = [trim[0], trim[1], trim[2] + g]
        self._dv = [0.0, 0.0, 0.0]

    def step(self, v_cmd_ned_m_s: np.ndarray, dt_s: float) -> np.ndarray:
        """Advance by ``dt_s`` holding the velocity setpoint ``v_cmd_ned_m_s`` ((1, 3) or (3,)); returns the
        (1, 3) velocity."""
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be > 0 and finite, got {dt_s!r}")
        p = self.params
        sp = [float(x) for x in np.ravel(v_cmd_ned_m_s)[:3]]
        ff = self.accel_ff_ned_m_s2
        nsub = max(1, math.ceil(dt_s / p.max_substep_s - 1e-9))
        h = dt_s / nsub
        beta = h / (p.tau_thrust_s + h)
        gains, tan_tilt = self._gains, self._tan_tilt
        lim, c, g = p.integrator_limit_m_s2, p.drag_1_s, p.g_m_s2
        v, a, integ, dv = self.velocity[0].tolist(), self.thrust_accel[0].tolist(), self._integ, self._dv
        for _ in range(nsub):
            acc = [0.0, 0.0, 0.0]
            for k, (kp, ki, kd) in enumerate(gains):
                e = sp[k] - v[k]
                integ[k] = min(max(integ[k] + ki * e * h, -lim), lim)
                acc[k] = kp * e + integ[k] - kd * dv[k] + ff[k]
            up = max(g - acc[2], 0.0)  # the thrust's upward part holds the weight and the climb
            hor = math.hypot(acc[0], acc[1])
            if hor > up * tan_tilt:
                s = up * tan_tilt / hor
                acc[0] *= s
                acc[1] *= s
            want = (acc[0], acc[1], -up)
            for k in range(3):
                a[k] += (want[k] - a[k]) * beta
                dv[k] = a[k] + (g if k == 2 else 0.0) - c * v[k]
                v[k] += dv[k] * h
        self.velocity[0] = v
        self.thrust_accel[0] = a
        return self.velocity

    def fixed_step(self, dt_s: float) -> Callable[[np.ndarray], np.ndarray]:
        """``f(v_cmd)`` doing ``self.step(v_cmd, dt_s)`` (VelocityPlant's interface)."""
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be > 0 and finite, got {dt_s!r}")
        return lambda v_cmd_ned_m_s: self.step(v_cmd_ned_m_s, dt_s)
