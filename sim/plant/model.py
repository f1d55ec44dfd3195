"""Quadrotor velocity plant of the paper's section "Individual-Agent Velocity Plant", vectorised.

Every agent is a point mass in NED (x north/forward, y east/right, z down) with two state
vectors: its velocity ``v`` and its realised thrust acceleration ``a_T`` (thrust / mass, so a
hovering vehicle has ``a_T = [0, 0, -g]``).  The paper's equations:

* translational dynamics ``dv/dt = a_T + [0, 0, g] + F_d / m``        (:func:`plant_derivatives`)
* thrust lag            ``da_T/dt = (a_T,d - a_T) / tau_T``           (:func:`plant_derivatives`)
* desired thrust        ``a_T,d = (v_cmd - v) / tau_v - [0, 0, g] - k_ff F_d(v_cmd) / m``
  (proportional shaping, gravity compensation, drag feed-forward; :func:`desired_thrust_accel`)
* per-axis quadratic drag ``F_d / m = -(rho Cd A / 2m) |v_air| v_air``, ``v_air = v - wind``
  (:func:`drag_accel`)
* actuation limits: tilt cone ``theta <= theta_max`` and ``|a_T| <= T_max / m``, applied to
  ``a_T,d`` before actuation, vertical (gravity compensation) first (:func:`constrain_thrust_accel`)
* zero-order hold of ``v_cmd`` over each step, semi-implicit Euler with sub-stepping
  (:func:`step_plant`).

The state arrays can be owned by the caller (the swarm simulator keeps ``(N, 3)`` arrays and
calls the pure :func:`step_plant`), or by :class:`VelocityPlant`, which adds cheap
``append``/``keep`` for agents entering and leaving.  Parameters may differ per agent
(heterogeneous fleets): any :class:`PlantParams` field may be an ``(N,)`` (or ``(N, 3)`` for the
drag vectors) array (:mod:`sim.plant.params`).

The step itself is one kernel (:mod:`sim.plant.kernel`): the numpy path is its tested
reference, and an optional numba compilation of the same arithmetic (``backend="numba"``, used
by ``"auto"`` when numba is importable) is what runs.  :func:`sim.plant.oracle.step_single_agent`
is a plain-Python scalar implementation written independently from the equations, kept as the
test oracle of both.  :meth:`VelocityPlant.fixed_step` prepares repeated steps of one length
(the autopilot emulator's one-vehicle physics step).
"""

from __future__ import annotations

import math
from typing import Callable, Literal

import numpy as np

from sim.plant.kernel import kernel_args, numba_available, numba_kernel, step_numpy
from sim.plant.params import PlantCoefficients, PlantParams

__all__ = [
    "Backend", "PlantCoefficients", "PlantParams", "VelocityPlant", "constrain_thrust_accel", "desired_thrust_accel",
    "drag_accel", "numba_available", "plant_derivatives", "step_plant", "substep_count",
    "thrust_accel_norm", "tilt_deg", "trim_thrust_accel",
]

Backend = Literal["auto", "numpy", "numba"]

def _select_kernel(backend: Backend) -> Callable | None:
    """The compiled kernel for ``backend`` (None: the numpy path)."""
    if backend == "numpy":
        return None
    if backend == "numba":
        k = numba_kernel()
        if k is None:
            raise RuntimeError("backend='numba' requested but numba is not installed (pip install fisc[jit])")
        return k
    if backend == "auto":
        return numba_kernel()
    raise ValueError(f"backend must be 'auto', 'numpy' or 'numba', got {backend!r}")


def _coeffs(params: PlantParams | PlantCoefficients, n_agents: int) -> PlantCoefficients:
    co = params.coefficients(n_agents) if isinstance(params, PlantParams) else params
    if co.rows not in (1, n_agents):
        raise ValueError(f"plant coefficients have {co.rows} rows for {n_agents} agents")
    return co


def _as_state(a: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (N, 3), got {arr.shape}")
    return arr


def _as_rows(a: np.ndarray | None, n: int, name: str) -> np.ndarray | None:
    """An optional (3,) or (N, 3) input as a C-contiguous float64 (1, 3) or (N, 3) array."""
    if a is None:
        return None
    arr = np.asarray(a, dtype=np.float64)
    if arr.shape == (3,):
        arr = arr.reshape(1, 3)
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] not in (1, n):
        raise ValueError(f"{name}: expected shape (3,) or ({n}, 3), got {np.shape(a)}")
    return np.ascontiguousarray(arr)


# ---------------------------------------------------------------------------------------------
# The paper's equations, one function each (numpy, any leading shape (N, 3))
# ---------------------------------------------------------------------------------------------


def drag_accel(air_vel_m_s: np.ndarray, drag_k: np.ndarray) -> np.ndarray:
    """Per-axis quadratic drag acceleration ``F_d / m = -(rho Cd A / 2m) |v_air| v_air``.

    Paper: "aerodynamic drag force computed per axis using a quadratic airspeed model";
    ``air_vel_m_s`` is the airspeed vector ``v - wind`` (N, 3), ``drag_k`` (M, 3).
    """
    return -drag_k * np.abs(air_vel_m_s) * air_vel_m_s


def desired_thrust_accel(
    vel_ned_m_s: np.ndarray,
    cmd_ned_m_s: np.ndarray,
    params: PlantParams | PlantCoefficients,
    wind_ff_ned_m_s: np.ndarray | None = None,
    feedback_noise_ned_m_s: np.ndarray | None = None,
) -> np.ndarray:
    """Desired thrust acceleration ``a_T,d`` before the actuation limits (paper: "proportional
    shaping on velocity error, gravity compensation, and an optional feedforward term derived
    from estimated aerodynamic drag at the commanded velocity"):

    ``a_T,d = (v_cmd - v_meas) / tau_v - [0, 0, g] - k_ff F_d(v_cmd - w_ff) / m``

    with ``v_meas = v + feedback_noise`` (sensor noise, default none) and ``w_ff`` the wind the
    feed-forward assumes (default still air).  Gravity compensation points up (-z in NED); the
    feed-forward pushes against the drag the commanded velocity will meet.
    """
    vel = _as_state(vel_ned_m_s, "vel_ned_m_s")
    n = vel.shape[0]
    co = _coeffs(params, n)
    cmd = np.broadcast_to(np.asarray(cmd_ned_m_s, dtype=np.float64), vel.shape)
    air_c = cmd if wind_ff_ned_m_s is None else cmd - _as_rows(wind_ff_ned_m_s, n, "wind_ff_ned_m_s")
    meas = vel if feedback_noise_ned_m_s is None else vel + _as_rows(feedback_noise_ned_m_s, n, "feedback_noise_ned_m_s")
    a_d = (cmd - meas) * co.inv_tau_v[:, None] - co.ff_gain[:, None] * drag_accel(air_c, co.drag_k)
    a_d[:, 2] -= co.g
    return a_d


def constrain_thrust_accel(
    accel_ned_m_s2: np.ndarray, accel_max_m_s2: np.ndarray | float, tan_tilt: np.ndarray | float
) -> np.ndarray:
    """Actuation limits applied to a desired thrust acceleration (paper: "Actuation Limits and
    Constraint Handling": tilt cone of half-angle theta_max, |thrust| <= T_max).

    Vertical first: the upward component ``a_up = -a_z`` is clipped to ``[0, T_max/m]`` (rotor
    thrust cannot point down, so a command to descend faster than free fall gets zero thrust);
    then the horizontal component is scaled, direction preserved, to at most
    ``min(a_up tan(theta_max), sqrt((T_max/m)^2 - a_up^2))`` - the tilt cone and the remaining
    thrust magnitude.  Returns a new (N, 3) array.
    """
    a = np.array(accel_ned_m_s2, dtype=np.float64)
    amax = np.asarray(accel_max_m_s2, dtype=np.float64)
    up = np.clip(-a[:, 2], 0.0, amax)
    h_norm = np.hypot(a[:, 0], a[:, 1])
    h_max = np.minimum(up * tan_tilt, np.sqrt(np.maximum(amax * amax - up * up, 0.0)))
    over = h_norm > h_max
    scale = np.divide(h_max, h_norm, out=np.ones_like(h_norm), where=over)
    a[:, 0] *= scale
    a[:, 1] *= scale
    a[:, 2] = -up
    return a


def plant_derivatives(
    vel_ned_m_s: np.ndarray,
    thrust_accel_ned_m_s2: np.ndarray,
    cmd_ned_m_s: np.ndarray,
    params: PlantParams | PlantCoefficients,
    wind_ned_m_s: np.ndarray | None = None,
    wind_ff_ned_m_s: np.ndarray | None = None,
    feedback_noise_ned_m_s: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Continuous-time state derivatives (the paper's two plant equations):

    ``dv/dt = a_T + [0, 0, g] + F_d(v - wind) / m`` and ``da_T/dt = (sat(a_T,d) - a_T) / tau_T``

    where ``sat`` is :func:`constrain_thrust_accel`.  Returns ``(dv/dt, da_T/dt)``, each (N, 3).
    """
    vel = _as_state(vel_ned_m_s, "vel_ned_m_s")
    thr = _as_state(thrust_accel_ned_m_s2, "thrust_accel_ned_m_s2")
    n = vel.shape[0]
    co = _coeffs(params, n)
    a_d = desired_thrust_accel(vel, cmd_ned_m_s, co, wind_ff_ned_m_s, feedback_noise_ned_m_s)
    a_c = constrain_thrust_accel(a_d, co.accel_max, co.tan_tilt)
    air = vel if wind_ned_m_s is None else vel - _as_rows(wind_ned_m_s, n, "wind_ned_m_s")
    dv = thr + drag_accel(air, co.drag_k)
    dv[:, 2] += co.g
    da = (a_c - thr) / co.tau_thrust_s[:, None]
    return dv, da


def trim_thrust_accel(
    vel_ned_m_s: np.ndarray,
    params: PlantParams | PlantCoefficients,
    wind_ned_m_s: np.ndarray | None = None,
) -> np.ndarray:
    """Thrust acceleration that holds ``vel`` steady: ``-[0, 0, g] - F_d(v - wind)/m``, within
    the actuation limits.  The natural initial thrust state of an agent entering in flight."""
    vel = _as_state(vel_ned_m_s, "vel_ned_m_s")
    n = vel.shape[0]
    co = _coeffs(params, n)
    air = vel if wind_ned_m_s is None else vel - _as_rows(wind_ned_m_s, n, "wind_ned_m_s")
    a = -drag_accel(air, co.drag_k)
    a[:, 2] -= co.g
    return constrain_thrust_accel(a, co.accel_max, co.tan_tilt)


def tilt_deg(thrust_accel_ned_m_s2: np.ndarray) -> np.ndarray:
    """(N,) angle [deg] between the thrust vector and vertical-up (0 for zero thrust)."""
    a = np.asarray(thrust_accel_ned_m_s2, dtype=np.float64)
    return np.degrees(np.arctan2(np.hypot(a[..., 0], a[..., 1]), -a[..., 2]))


def thrust_accel_norm(thrust_accel_ned_m_s2: np.ndarray) -> np.ndarray:
    """(N,) thrust acceleration magnitude |a_T| = T / m [m/s^2]."""
    return np.linalg.norm(np.asarray(thrust_accel_ned_m_s2, dtype=np.float64), axis=-1)


def substep_count(dt_s: float, params: PlantParams | PlantCoefficients) -> int:
    """Sub-steps used for a step of ``dt_s``: ``max(substeps, ceil(dt / max_substep_s))``."""
    return max(params.substeps, math.ceil(dt_s / params.max_substep_s - 1e-9))


# ---------------------------------------------------------------------------------------------
# Time stepping
# ---------------------------------------------------------------------------------------------


def step_plant(
    vel_ned_m_s: np.ndarray,
    thrust_accel_ned_m_s2: np.ndarray,
    cmd_ned_m_s: np.ndarray,
    dt_s: float,
    params: PlantParams | PlantCoefficients,
    wind_ned_m_s: np.ndarray | None = None,
    wind_ff_ned_m_s: np.ndarray | None = None,
    feedback_noise_ned_m_s: np.ndarray | None = None,
    out: tuple[np.ndarray, np.ndarray] | None = None,
    backend: Backend = "auto",
) -> tuple[np.ndarray, np.ndarray]:
    """Advance every agent by ``dt_s``: zero-order hold of ``cmd`` (and of wind and noise),
    ``n = substep_count(dt_s)`` semi-implicit Euler sub-steps of length ``h = dt_s / n``
    (paper: "Numerical Integration").  One sub-step, in this order::

        a_c   = sat(a_T,d(v))                          desired thrust, then the limits
        a_T  += h / (tau_T + h) * (a_c - a_T)          thrust lag, implicit (backward Euler)
        v    += h * (a_T + [0, 0, g] + F_d(v_old)/m)   velocity with the *new* thrust

    The thrust update is a convex combination of the old thrust and a feasible one, so a
    feasible thrust state stays feasible (tilt and magnitude limits hold exactly) and the lag is
    stable for any ``h``.

    Arguments: ``vel``/``thrust_accel`` (N, 3) state, ``cmd`` (N, 3) or (3,) commanded velocity,
    ``wind``/``wind_ff``/``feedback_noise`` optional (3,) or (N, 3) (true wind; wind assumed by
    the feed-forward; velocity measurement error fed back).  Inputs are not modified unless they
    are passed as ``out=(vel_out, thrust_out)`` (which may alias them: in-place stepping).
    ``backend``: "numpy", "numba" (error if unavailable) or "auto" (numba when importable).
    Both compute the same arithmetic in the same order (:mod:`sim.plant.kernel`).  Returns
    ``(vel, thrust_accel)``.
    """
    vel = _as_state(vel_ned_m_s, "vel_ned_m_s")
    thr = _as_state(thrust_accel_ned_m_s2, "thrust_accel_ned_m_s2")
    n = vel.shape[0]
    if thr.shape != vel.shape:
        raise ValueError(f"thrust_accel_ned_m_s2 shape {thr.shape} != vel_ned_m_s shape {vel.shape}")
    if not (math.isfinite(dt_s) and dt_s > 0):
        raise ValueError(f"dt_s must be > 0 and finite, got {dt_s!r}")
    co = _coeffs(params, n)
    cmd = _as_rows(cmd_ned_m_s, n, "cmd_ned_m_s")
    wind = _as_rows(wind_ned_m_s, n, "wind_ned_m_s")
    wind_ff = _as_rows(wind_ff_ned_m_s, n, "wind_ff_ned_m_s")
    noise = _as_rows(feedback_noise_ned_m_s, n, "feedback_noise_ned_m_s")
    if out is None:
        vel_out, thr_out = vel.copy(), thr.copy()
    else:
        vel_out, thr_out = out
        for name, o in (("out[0]", vel_out), ("out[1]", thr_out)):
            if not (isinstance(o, np.ndarray) and o.shape == vel.shape and o.dtype == np.float64 and o.flags.c_contiguous):
                raise ValueError(f"{name}: expected a C-contiguous float64 array of shape {vel.shape}")
        if vel_out is not vel:
            vel_out[...] = vel
        if thr_out is not thr:
            thr_out[...] = thr
    if n == 0:
        return vel_out, thr_out
    nsub = substep_count(dt_s, co)
    h = dt_s / nsub
    kernel = _select_kernel(backend)
    if kernel is None:
        step_numpy(vel_out, thr_out, cmd, wind, wind_ff, noise, co, h, nsub)
    else:
        kernel(vel_out, thr_out, cmd, wind, wind_ff, noise, *kernel_args(co, h), h, nsub)
    return vel_out, thr_out


def plant_stepper(params: PlantParams | PlantCoefficients, dt_s: float,
                  backend: Backend = "auto") -> Callable[[np.ndarray, np.ndarray, np.ndarray], None]:
    """``step(vel, thrust, cmd)``: :func:`step_plant` of ``(vel, thrust)`` in place over ``dt_s``, without
    wind or noise, for the fleet-wide ``params`` (one coefficient row), with the sub-step, the
    coefficients and the kernel chosen once: the same arithmetic without the per-call checks (the
    caller owns C-contiguous float64 (N, 3) buffers).  For a loop stepping thousands of times."""
    co = params if isinstance(params, PlantCoefficients) else params.coefficients()
    if co.rows != 1:
        raise ValueError("plant_stepper needs fleet-wide (one-row) plant coefficients")
    if not (math.isfinite(dt_s) and dt_s > 0):
        raise ValueError(f"dt_s must be > 0 and finite, got {dt_s!r}")
    nsub = substep_count(dt_s, co)
    h = dt_s / nsub
    kernel = _select_kernel(backend)
    if kernel is None:
        return lambda v, a, cmd: step_numpy(v, a, cmd, None, None, None, co, h, nsub) if v.shape[0] else None
    rows, shared = kernel_args(co, h)
    return lambda v, a, cmd: kernel(v, a, cmd, None, None, None, rows, shared, h, nsub)


# ---------------------------------------------------------------------------------------------
# Stateful wrapper
# ---------------------------------------------------------------------------------------------


class VelocityPlant:
    """N quadrotor velocity plants stepped together (state held here, stepped in place).

    ``VelocityPlant(params, n_agents)`` starts every agent hovering (v = 0, a_T = [0, 0, -g]).
    ``step(v_cmd, dt_s, wind)`` returns the new velocities.  Agents enter with :meth:`append`
    and leave with :meth:`keep`; with per-agent parameters, entering agents bring theirs.
    """

    def __init__(
        self,
        params: PlantParams | None = None,
        n_agents: int | None = None,
        velocity_ned_m_s: np.ndarray | None = None,
        thrust_accel_ned_m_s2: np.ndarray | None = None,
        backend: Backend = "auto",
    ) -> None:
        self._params = PlantParams() if params is None else params
        if n_agents is None:
            n_agents = (
                self._params.n_agents if self._params.n_agents is not None
                else (0 if velocity_ned_m_s is None else np.shape(velocity_ned_m_s)[0])
            )  # fmt: skip
        if n_agents < 0:
            raise ValueError(f"n_agents must be >= 0, got {n_agents}")
        self._backend: Backend = backend
        _select_kernel(backend)  # fail early on an unavailable backend
        self._co = self._params.coefficients(n_agents)
        self._vel = np.zeros((n_agents, 3))
        self._thr = np.zeros((n_agents, 3))
        self.reset(velocity_ned_m_s, thrust_accel_ned_m_s2)

    # state -----------------------------------------------------------------------------------
    @property
    def n_agents(self) -> int:
        """Current number of agents N."""
        return self._vel.shape[0]

    @property
    def velocity(self) -> np.ndarray:
        """(N, 3) realised velocity [m/s] NED (the live state array; do not resize)."""
        return self._vel

    @property
    def thrust_accel(self) -> np.ndarray:
        """(N, 3) realised thrust acceleration a_T [m/s^2] NED (the live state array)."""
        return self._thr

    @property
    def params(self) -> PlantParams:
        """The parameters given at construction."""
        return self._params

    @property
    def coefficients(self) -> PlantCoefficients:
        """Current per-agent (or shared) coefficients."""
        return self._co

    def tilt_deg(self) -> np.ndarray:
        """(N,) current tilt of the realised thrust from vertical-up [deg]."""
        return tilt_deg(self._thr)

    def thrust_accel_norm(self) -> np.ndarray:
        """(N,) current |a_T| [m/s^2]."""
        return thrust_accel_norm(self._thr)

    def thrust_to_weight_used(self) -> np.ndarray:
        """(N,) current thrust over weight |a_T| / g [-]."""
        return self.thrust_accel_norm() / np.broadcast_to(self._co.g, (self.n_agents,))

    # evolution -------------------------------------------------------------------------------
    def reset(self, velocity_ned_m_s: np.ndarray | None = None, thrust_accel_ned_m_s2: np.ndarray | None = None) -> None:
        """Set the state: velocity (default 0) and thrust (default the trim of that velocity in
        still air, :func:`trim_thrust_accel`).  (3,) inputs apply to every agent."""
        n = self.n_agents
        vel = np.zeros((n, 3)) if velocity_ned_m_s is None else np.broadcast_to(_as_rows(velocity_ned_m_s, n, "velocity_ned_m_s"), (n, 3))
        thr = trim_thrust_accel(vel, self._co) if thrust_accel_ned_m_s2 is None else np.broadcast_to(
            _as_rows(thrust_accel_ned_m_s2, n, "thrust_accel_ned_m_s2"), (n, 3)
        )
        self._vel[...] = vel
        self._thr[...] = thr

    def step(
        self,
        v_cmd_ned_m_s: np.ndarray,
        dt_s: float,
        wind_ned_m_s: np.ndarray | None = None,
        wind_ff_ned_m_s: np.ndarray | None = None,
        feedback_noise_ned_m_s: np.ndarray | None = None,
    ) -> np.ndarray:
        """Advance by ``dt_s`` holding ``v_cmd`` ((N, 3) or (3,)); returns the (N, 3) velocity."""
        step_plant(
            self._vel, self._thr, v_cmd_ned_m_s, dt_s, self._co,
            wind_ned_m_s, wind_ff_ned_m_s, feedback_noise_ned_m_s,
            out=(self._vel, self._thr), backend=self._backend,
        )  # fmt: skip
        return self._vel

    def fixed_step(self, dt_s: float) -> Callable[[np.ndarray], np.ndarray]:
        """A stepper for many steps of one length: ``f(v_cmd)`` does exactly what
        ``self.step(v_cmd, dt_s)`` does (same kernel, same numbers) and returns the (N, 3) velocity.

        The argument checks, the sub-step count and the coefficient extraction are done once
        here instead of on every call (for one agent they cost ~10x the kernel).  The fast path
        takes a C-contiguous float64 (N, 3) or (1, 3) command on the compiled backend; anything
        else (or a plant whose agents changed since) goes through :meth:`step`, which checks
        its arguments."""
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be > 0 and finite, got {dt_s!r}")
        co = self._co
        kernel = _select_kernel(self._backend)
        if kernel is None:
            return lambda v_cmd_ned_m_s: self.step(v_cmd_ned_m_s, dt_s)
        nsub = substep_count(dt_s, co)
        h = dt_s / nsub
        args = (*kernel_args(co, h), h, nsub)

        def step(v_cmd_ned_m_s: np.ndarray) -> np.ndarray:
            cmd = v_cmd_ned_m_s
            if (self._co is not co or type(cmd) is not np.ndarray or cmd.dtype != np.float64 or cmd.ndim != 2
                    or cmd.shape[1] != 3 or cmd.shape[0] not in (1, self._vel.shape[0]) or not cmd.flags.c_contiguous):
                return self.step(cmd, dt_s)
            kernel(self._vel, self._thr, cmd, None, None, None, *args)
            return self._vel

        return step

    # population ------------------------------------------------------------------------------
    def append(
        self,
        velocity_ned_m_s: np.ndarray,
        thrust_accel_ned_m_s2: np.ndarray | None = None,
        params: PlantParams | None = None,
    ) -> None:
        """Add agents at the end: ``velocity`` (k, 3); thrust defaults to their still-air trim.

        ``params``: the new agents' parameters (scalar or per-agent for k agents); default the
        fleet's own, which must then be homogeneous."""
        vel = _as_state(velocity_ned_m_s, "velocity_ned_m_s")
        k = vel.shape[0]
        if params is None:
            if self._co.rows != 1:
                raise ValueError("append: the fleet has per-agent parameters; give params for the new agents")
            new_co = self._co
        else:
            new_co = params.coefficients(k)
        thr = trim_thrust_accel(vel, new_co) if thrust_accel_ned_m_s2 is None else _as_state(
            thrust_accel_ned_m_s2, "thrust_accel_ned_m_s2"
        )
        if thr.shape != vel.shape:
            raise ValueError(f"append: thrust shape {thr.shape} != velocity shape {vel.shape}")
        self._co = self._co.concat(new_co, self.n_agents, k)
        self._vel = np.concatenate([self._vel, vel])
        self._thr = np.concatenate([self._thr, thr])

    def keep(self, index: np.ndarray) -> None:
        """Keep only the agents selected by ``index`` (bool mask of length N, or integer indices,
        in the order given); the others leave."""
        idx = np.asarray(index)
        if idx.dtype == bool and idx.shape != (self.n_agents,):
            raise ValueError(f"keep: mask shape {idx.shape} != ({self.n_agents},)")
        self._vel = np.ascontiguousarray(self._vel[idx])
        self._thr = np.ascontiguousarray(self._thr[idx])
        self._co = self._co.take(idx)
