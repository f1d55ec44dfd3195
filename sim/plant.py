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
drag vectors) array.  :func:`step_single_agent` is a plain-Python scalar implementation kept as
the test oracle.  An optional numba kernel (``backend="numba"``, used by ``"auto"`` when numba is
importable) fuses the sub-step loop, with a faster specialisation for fleet-wide parameters
without wind or noise (the swarm simulator's case); the numpy path computes the same numbers.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass
from typing import Callable, Literal

import numpy as np

_log = logging.getLogger(__name__)

Backend = Literal["auto", "numpy", "numba"]

_SCALAR_FIELDS = (
    "mass_kg",
    "g",
    "tau_v_s",
    "tau_thrust_s",
    "thrust_to_weight",
    "tilt_max_deg",
    "air_density_kg_m3",
    "drag_feedforward_gain",
)
_VECTOR_FIELDS = ("drag_area_m2", "drag_coeff")


@dataclass(frozen=True, eq=False)
class PlantParams:
    """Parameters of the velocity plant; defaults are the paper's nominal small quadrotor.

    Every physical field may be a scalar (the whole fleet) or a per-agent array: ``(N,)`` for
    the scalar fields, ``(N, 3)`` for ``drag_area_m2`` and ``drag_coeff``.  All per-agent
    fields of one instance must agree on N.  ``substeps`` and ``max_substep_s`` are numerical
    settings shared by the fleet.
    """

    mass_kg: float | np.ndarray = 1.0
    """Vehicle mass m_i [kg] (paper: 1 kg)."""
    g: float | np.ndarray = 9.81
    """Gravitational acceleration [m/s^2], acting along +z (down) in NED."""
    tau_v_s: float | np.ndarray = 0.5
    """Velocity shaping time constant tau_v [s]: desired acceleration (v_cmd - v) / tau_v."""
    tau_thrust_s: float | np.ndarray = 0.08
    """First-order thrust (inner attitude/motor loop) lag tau_T [s] (paper: 0.08 s)."""
    thrust_to_weight: float | np.ndarray = 2.2
    """Maximum thrust over weight T_max / (m g) (paper: 2.2); bounds |a_T| <= T_max / m."""
    tilt_max_deg: float | np.ndarray = 55.0
    """Tilt cone half-angle theta_max [deg] between the thrust vector and vertical-up (paper: 55)."""
    air_density_kg_m3: float | np.ndarray = 1.225
    """Air density rho [kg/m^3] (paper: 1.225)."""
    drag_area_m2: tuple[float, float, float] | np.ndarray = (0.02, 0.02, 0.03)
    """Per-axis drag reference areas S = [S_x, S_y, S_z] [m^2] (paper: [0.02, 0.02, 0.03])."""
    drag_coeff: tuple[float, float, float] | np.ndarray = (1.0, 1.0, 1.2)
    """Per-axis drag coefficients Cd = [Cd_x, Cd_y, Cd_z] [-] (paper: [1.0, 1.0, 1.2])."""
    drag_feedforward_gain: float | np.ndarray = 0.8
    """Gain k_ff of the drag feed-forward, the estimated drag at the commanded velocity [-].

    0 disables it, 1 cancels the modelled drag exactly in steady flight.  Default 0.8, the
    value of the paper's headwind test: it removes 80 % of the drag-induced steady-state
    error while leaving margin for an over-estimated drag model (over-compensation makes the
    response overshoot)."""
    substeps: int = 1
    """Minimum number of semi-implicit Euler sub-steps per :func:`step_plant` call."""
    max_substep_s: float = 0.01
    """Longest sub-step [s]; a call with ``dt`` uses ``max(substeps, ceil(dt / max_substep_s))``
    sub-steps (0.01 s = tau_T / 8 keeps the discrete response within ~1 % of the continuous one)."""

    def __post_init__(self) -> None:
        n_agents: int | None = None
        for name in _SCALAR_FIELDS + _VECTOR_FIELDS:
            raw = getattr(self, name)
            try:
                arr = np.array(raw, dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"PlantParams.{name}: not numeric ({raw!r})") from exc
            want_vec = name in _VECTOR_FIELDS
            if (want_vec and arr.shape == (3,)) or (not want_vec and arr.ndim == 0):
                value: float | np.ndarray = float(arr) if arr.ndim == 0 else _readonly(arr)
            elif (want_vec and arr.ndim == 2 and arr.shape[1] == 3) or (not want_vec and arr.ndim == 1):
                if n_agents is not None and arr.shape[0] != n_agents:
                    raise ValueError(
                        f"PlantParams.{name}: per-agent length {arr.shape[0]} differs from "
                        f"{n_agents} of the other per-agent fields"
                    )
                n_agents = arr.shape[0]
                value = _readonly(arr)
            else:
                expect = "(3,) or (N, 3)" if want_vec else "a scalar or (N,)"
                raise ValueError(f"PlantParams.{name}: shape {arr.shape}, expected {expect}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"PlantParams.{name}: non-finite value")
            object.__setattr__(self, name, value)
        checks = (
            ("mass_kg", lambda a: a > 0, "> 0"),
            ("g", lambda a: a >= 0, ">= 0"),
            ("tau_v_s", lambda a: a > 0, "> 0"),
            ("tau_thrust_s", lambda a: a > 0, "> 0"),
            ("thrust_to_weight", lambda a: a > 0, "> 0"),
            ("tilt_max_deg", lambda a: (a > 0) & (a < 90), "in (0, 90)"),
            ("air_density_kg_m3", lambda a: a >= 0, ">= 0"),
            ("drag_area_m2", lambda a: a >= 0, ">= 0"),
            ("drag_coeff", lambda a: a >= 0, ">= 0"),
            ("drag_feedforward_gain", lambda a: a >= 0, ">= 0"),
        )
        for name, ok, text in checks:
            if not np.all(ok(np.asarray(getattr(self, name)))):
                raise ValueError(f"PlantParams.{name}: every value must be {text}")
        if isinstance(self.substeps, bool) or int(self.substeps) != self.substeps or self.substeps < 1:
            raise ValueError(f"PlantParams.substeps: must be an integer >= 1, got {self.substeps!r}")
        object.__setattr__(self, "substeps", int(self.substeps))
        if not (math.isfinite(float(self.max_substep_s)) and float(self.max_substep_s) > 0):
            raise ValueError(f"PlantParams.max_substep_s: must be > 0, got {self.max_substep_s!r}")
        object.__setattr__(self, "max_substep_s", float(self.max_substep_s))
        object.__setattr__(self, "_n_agents", n_agents)

    @property
    def n_agents(self) -> int | None:
        """N of the per-agent fields, or None when every field is fleet-wide (homogeneous)."""
        return self._n_agents  # type: ignore[attr-defined]

    @property
    def is_homogeneous(self) -> bool:
        """True when no field is per-agent."""
        return self.n_agents is None

    def agent(self, i: int) -> "PlantParams":
        """The scalar parameters of agent ``i`` (for the single-agent oracle)."""
        kw = {}
        for name in _SCALAR_FIELDS + _VECTOR_FIELDS:
            val = getattr(self, name)
            if isinstance(val, np.ndarray) and (val.ndim == 1 if name in _SCALAR_FIELDS else val.ndim == 2):
                val = val[i]
            kw[name] = val
        return PlantParams(**kw, substeps=self.substeps, max_substep_s=self.max_substep_s)

    def coefficients(self, n_agents: int | None = None) -> "PlantCoefficients":
        """The derived per-agent coefficient arrays the step kernels use (see PlantCoefficients)."""
        if n_agents is not None and self.n_agents is not None and n_agents != self.n_agents:
            raise ValueError(f"PlantParams has per-agent fields for {self.n_agents} agents, not {n_agents}")
        m = 1 if self.n_agents is None else self.n_agents

        def s(name: str) -> np.ndarray:
            return np.broadcast_to(np.asarray(getattr(self, name), dtype=np.float64), (m,))

        def v(name: str) -> np.ndarray:
            return np.broadcast_to(np.asarray(getattr(self, name), dtype=np.float64), (m, 3))

        mass, g = s("mass_kg"), s("g")
        drag_k = 0.5 * s("air_density_kg_m3")[:, None] * v("drag_coeff") * v("drag_area_m2") / mass[:, None]
        return PlantCoefficients(
            inv_tau_v=1.0 / s("tau_v_s"),
            tau_thrust_s=s("tau_thrust_s").copy(),
            g=g.copy(),
            drag_k=np.ascontiguousarray(drag_k),
            ff_gain=s("drag_feedforward_gain").copy(),
            accel_max=s("thrust_to_weight") * g,
            tan_tilt=np.tan(np.deg2rad(s("tilt_max_deg"))),
            substeps=self.substeps,
            max_substep_s=self.max_substep_s,
        )


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64)
    a.flags.writeable = False
    return a


_PER_AGENT = ("inv_tau_v", "tau_thrust_s", "g", "drag_k", "ff_gain", "accel_max", "tan_tilt")


@dataclass(frozen=True, eq=False)
class PlantCoefficients:
    """Derived coefficients, one row per agent (M = N) or one shared row (M = 1).

    The swarm simulator may hold these next to its state arrays and slice/concatenate them
    with :meth:`take` / :meth:`concat` when agents leave or enter.
    """

    inv_tau_v: np.ndarray
    """(M,) 1 / tau_v [1/s]."""
    tau_thrust_s: np.ndarray
    """(M,) thrust lag tau_T [s]."""
    g: np.ndarray
    """(M,) gravity [m/s^2]."""
    drag_k: np.ndarray
    """(M, 3) rho Cd A / (2 m) per axis [1/m]: drag acceleration = -drag_k |v_air| v_air."""
    ff_gain: np.ndarray
    """(M,) drag feed-forward gain k_ff [-]."""
    accel_max: np.ndarray
    """(M,) T_max / m = thrust_to_weight * g [m/s^2]."""
    tan_tilt: np.ndarray
    """(M,) tan(theta_max) [-]."""
    substeps: int
    """Minimum sub-steps per step."""
    max_substep_s: float
    """Longest sub-step [s]."""

    @property
    def rows(self) -> int:
        """M: 1 for a fleet-wide row, else the number of agents."""
        return int(self.inv_tau_v.shape[0])

    def expand(self, n_agents: int) -> "PlantCoefficients":
        """Per-agent copy with N rows (a shared row is repeated; N rows are kept as they are)."""
        if self.rows == n_agents:
            return self
        if self.rows != 1:
            raise ValueError(f"PlantCoefficients: cannot expand {self.rows} rows to {n_agents}")
        return self._map(lambda a: np.repeat(a, n_agents, axis=0))

    def take(self, index: np.ndarray) -> "PlantCoefficients":
        """Rows for the agents selected by ``index`` (bool mask or integer indices); shared rows stay."""
        if self.rows == 1:
            return self
        return self._map(lambda a: np.ascontiguousarray(a[index]))

    def concat(self, other: "PlantCoefficients", n_self: int, n_other: int) -> "PlantCoefficients":
        """Coefficients of ``n_self`` agents followed by ``n_other`` agents."""
        if self.rows == 1 and other.rows == 1 and all(
            np.array_equal(getattr(self, k), getattr(other, k)) for k in _PER_AGENT
        ):
            return self
        a, b = self.expand(n_self), other.expand(n_other)
        return PlantCoefficients(
            **{k: np.concatenate([getattr(a, k), getattr(b, k)], axis=0) for k in _PER_AGENT},
            substeps=self.substeps,
            max_substep_s=self.max_substep_s,
        )

    def _map(self, fn) -> "PlantCoefficients":
        return PlantCoefficients(
            **{k: fn(getattr(self, k)) for k in _PER_AGENT},
            substeps=self.substeps,
            max_substep_s=self.max_substep_s,
        )


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
    With numba, a fleet-wide coefficient row and no wind/wind_ff/noise, a specialised kernel
    (same arithmetic, vectorised across agents) is used.  Returns ``(vel, thrust_accel)``.
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
        _step_numpy(vel_out, thr_out, cmd, wind, wind_ff, noise, co, h, nsub)
    elif co.rows == 1 and wind is None and wind_ff is None and noise is None:
        fleet_kernel()(vel_out, thr_out, cmd, *_fleet_args(co, h, nsub))
    else:
        z = np.zeros((1, 3))
        kernel(
            vel_out, thr_out, cmd,
            z if wind is None else wind, z if wind_ff is None else wind_ff, z if noise is None else noise,
            np.ascontiguousarray(co.inv_tau_v), np.ascontiguousarray(co.tau_thrust_s),
            np.ascontiguousarray(co.g), np.ascontiguousarray(co.drag_k),
            np.ascontiguousarray(co.ff_gain), np.ascontiguousarray(co.accel_max),
            np.ascontiguousarray(co.tan_tilt), h, nsub,
        )  # fmt: skip
    return vel_out, thr_out


def _fleet_args(co: PlantCoefficients, h: float, nsub: int) -> tuple:
    """The scalar arguments of :func:`fleet_kernel` after the state and command arrays."""
    return (
        float(co.inv_tau_v[0]), float(h / (co.tau_thrust_s[0] + h)), float(co.g[0]),
        float(co.drag_k[0, 0]), float(co.drag_k[0, 1]), float(co.drag_k[0, 2]), float(co.ff_gain[0]),
        float(co.accel_max[0]), float(co.tan_tilt[0]), h, nsub,
    )  # fmt: skip


def _step_numpy(v, a, cmd, wind, wind_ff, noise, co: PlantCoefficients, h: float, nsub: int) -> None:
    """In-place numpy sub-stepping of (v, a); the reference for the numba kernel."""
    kd = co.drag_k
    g = co.g
    # Constant over the step (zero-order hold): feed-forward + gravity bias and shaping reference.
    air_c = cmd if wind_ff is None else cmd - wind_ff
    bias = np.abs(air_c) * air_c
    bias *= co.ff_gain[:, None] * kd
    bias = np.broadcast_to(bias, v.shape).copy()
    bias[:, 2] -= g
    ref = cmd if noise is None else cmd - noise
    itv = co.inv_tau_v[:, None]
    beta = (h / (co.tau_thrust_s + h))[:, None]
    amax = co.accel_max
    amax2 = amax * amax
    tan2 = co.tan_tilt * co.tan_tilt
    d = np.empty_like(v)
    x = np.empty_like(v)
    for _ in range(nsub):
        # desired thrust acceleration and actuation limits (in place in d)
        np.subtract(ref, v, out=d)
        d *= itv
        d += bias
        up = np.clip(-d[:, 2], 0.0, amax)
        up2 = up * up
        hn2 = d[:, 0] * d[:, 0]
        hn2 += d[:, 1] * d[:, 1]
        hmax2 = np.minimum(up2 * tan2, np.maximum(amax2 - up2, 0.0))
        over = hn2 > hmax2
        if over.any():
            scale = np.sqrt(np.divide(hmax2, hn2, out=np.ones_like(hn2), where=over))
            d[:, 0] *= scale
            d[:, 1] *= scale
        np.negative(up, out=d[:, 2])
        # thrust lag (backward Euler): a += beta (a_c - a)
        d -= a
        d *= beta
        a += d
        # velocity with the new thrust and the drag at the old velocity
        if wind is None:
            np.abs(v, out=x)
            x *= v
        else:
            np.subtract(v, wind, out=d)
            np.abs(d, out=x)
            x *= d
        x *= kd
        np.subtract(a, x, out=x)
        x[:, 2] += g
        x *= h
        v += x


@functools.lru_cache(maxsize=1)
def _numba_kernel():
    """The fused numba kernel, compiled on first use; None when numba is not importable."""
    try:
        import numba
    except ImportError:
        _log.info("numba not available; the plant uses its numpy path")
        return None

    @numba.njit(cache=True, nogil=True, error_model="numpy")
    def kernel(v, a, cmd, wind, wind_ff, noise, itv, tau_t, g, kd, ff, amax, tant, h, nsub):
        n = v.shape[0]
        per_agent = itv.shape[0] > 1
        for i in range(n):
            c = i if per_agent else 0
            ic = i if cmd.shape[0] > 1 else 0
            iw = i if wind.shape[0] > 1 else 0
            jf = i if wind_ff.shape[0] > 1 else 0
            jn = i if noise.shape[0] > 1 else 0
            kd0, kd1, kd2 = kd[c, 0], kd[c, 1], kd[c, 2]
            gi, itvi, am, tt, ffi = g[c], itv[c], amax[c], tant[c], ff[c]
            am2, tt2 = am * am, tt * tt
            beta = h / (tau_t[c] + h)
            c0, c1, c2 = cmd[ic, 0], cmd[ic, 1], cmd[ic, 2]
            x0, x1, x2 = c0 - wind_ff[jf, 0], c1 - wind_ff[jf, 1], c2 - wind_ff[jf, 2]
            b0 = abs(x0) * x0 * (ffi * kd0)
            b1 = abs(x1) * x1 * (ffi * kd1)
            b2 = abs(x2) * x2 * (ffi * kd2) - gi
            r0, r1, r2 = c0 - noise[jn, 0], c1 - noise[jn, 1], c2 - noise[jn, 2]
            w0, w1, w2 = wind[iw, 0], wind[iw, 1], wind[iw, 2]
            v0, v1, v2 = v[i, 0], v[i, 1], v[i, 2]
            a0, a1, a2 = a[i, 0], a[i, 1], a[i, 2]
            for _ in range(nsub):
                d0 = (r0 - v0) * itvi + b0
                d1 = (r1 - v1) * itvi + b1
                d2 = (r2 - v2) * itvi + b2
                up = min(max(-d2, 0.0), am)
                hn2 = d0 * d0 + d1 * d1
                hmax2 = min(up * up * tt2, max(am2 - up * up, 0.0))
                if hn2 > hmax2:
                    s = math.sqrt(hmax2 / hn2)
                    d0 *= s
                    d1 *= s
                a0 += (d0 - a0) * beta
                a1 += (d1 - a1) * beta
                a2 += (-up - a2) * beta
                y0, y1, y2 = v0 - w0, v1 - w1, v2 - w2
                v0 += (a0 - abs(y0) * y0 * kd0) * h
                v1 += (a1 - abs(y1) * y1 * kd1) * h
                v2 += (a2 - abs(y2) * y2 * kd2 + gi) * h
            v[i, 0], v[i, 1], v[i, 2] = v0, v1, v2
            a[i, 0], a[i, 1], a[i, 2] = a0, a1, a2

    return kernel


#: Agents per block of the fleet-wide kernel: the block's state (a few (B,) arrays) stays in L1
#: while the sub-steps loop over it, and the innermost loop over the block's agents vectorises.
_FLEET_BLOCK = 256


@functools.lru_cache(maxsize=1)
def fleet_kernel():
    """The fleet-wide specialisation of :func:`_numba_kernel`, compiled on first use; None
    without numba.

    Used when every agent shares one coefficient row and there is no wind, wind feed-forward or
    feedback noise (the swarm simulator's case).  Same arithmetic, in the same order, as the
    general kernel with zero wind/noise, but with scalar coefficients and the loops interchanged
    per block of agents (sub-steps outside, agents inside, branch-free limits), so that the
    compiler vectorises across agents instead of following one agent's dependency chain.
    """
    try:
        import numba
    except ImportError:
        return None

    @numba.njit(cache=True, nogil=True, error_model="numpy")
    def kernel(v, a, cmd, itvi, beta, gi, kd0, kd1, kd2, ffi, am, tt, h, nsub):
        n = v.shape[0]
        bs = _FLEET_BLOCK
        am2, tt2 = am * am, tt * tt
        fk0, fk1, fk2 = ffi * kd0, ffi * kd1, ffi * kd2
        bc = cmd.shape[0] > 1
        r0 = np.empty(bs)
        r1 = np.empty(bs)
        r2 = np.empty(bs)
        b0 = np.empty(bs)
        b1 = np.empty(bs)
        b2 = np.empty(bs)
        v0 = np.empty(bs)
        v1 = np.empty(bs)
        v2 = np.empty(bs)
        a0 = np.empty(bs)
        a1 = np.empty(bs)
        a2 = np.empty(bs)
        for start in range(0, n, bs):
            m = min(bs, n - start)
            for j in range(m):
                i = start + j
                ic = i if bc else 0
                c0, c1, c2 = cmd[ic, 0], cmd[ic, 1], cmd[ic, 2]
                r0[j], r1[j], r2[j] = c0, c1, c2
                b0[j] = abs(c0) * c0 * fk0
                b1[j] = abs(c1) * c1 * fk1
                b2[j] = abs(c2) * c2 * fk2 - gi
                v0[j], v1[j], v2[j] = v[i, 0], v[i, 1], v[i, 2]
                a0[j], a1[j], a2[j] = a[i, 0], a[i, 1], a[i, 2]
            for _ in range(nsub):
                for j in range(m):
                    x0, x1, x2 = v0[j], v1[j], v2[j]
                    d0 = (r0[j] - x0) * itvi + b0[j]
                    d1 = (r1[j] - x1) * itvi + b1[j]
                    d2 = (r2[j] - x2) * itvi + b2[j]
                    up = min(max(-d2, 0.0), am)
                    hn2 = d0 * d0 + d1 * d1
                    hmax2 = min(up * up * tt2, max(am2 - up * up, 0.0))
                    s = math.sqrt(hmax2 / hn2) if hn2 > hmax2 else 1.0
                    y0 = a0[j] + (d0 * s - a0[j]) * beta
                    y1 = a1[j] + (d1 * s - a1[j]) * beta
                    y2 = a2[j] + (-up - a2[j]) * beta
                    a0[j], a1[j], a2[j] = y0, y1, y2
                    v0[j] = x0 + (y0 - abs(x0) * x0 * kd0) * h
                    v1[j] = x1 + (y1 - abs(x1) * x1 * kd1) * h
                    v2[j] = x2 + (y2 - abs(x2) * x2 * kd2 + gi) * h
            for j in range(m):
                i = start + j
                v[i, 0], v[i, 1], v[i, 2] = v0[j], v1[j], v2[j]
                a[i, 0], a[i, 1], a[i, 2] = a0[j], a1[j], a2[j]

    return kernel


def numba_available() -> bool:
    """True when the optional numba kernel can be used."""
    return _numba_kernel() is not None


def _select_kernel(backend: Backend):
    if backend == "numpy":
        return None
    if backend == "numba":
        k = _numba_kernel()
        if k is None:
            raise RuntimeError("backend='numba' requested but numba is not installed (pip install fisc[jit])")
        return k
    if backend == "auto":
        return _numba_kernel()
    raise ValueError(f"backend must be 'auto', 'numpy' or 'numba', got {backend!r}")


def step_single_agent(
    vel_ned_m_s: tuple[float, float, float],
    thrust_accel_ned_m_s2: tuple[float, float, float],
    cmd_ned_m_s: tuple[float, float, float],
    dt_s: float,
    params: PlantParams,
    wind_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0),
    wind_ff_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0),
    feedback_noise_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """Scalar reference implementation for one agent (plain Python floats, loops over axes).

    Written directly from the paper's equations and the sub-step order of :func:`step_plant`,
    independently of the vectorised code; the test oracle.  ``params`` must be homogeneous.
    """
    if not params.is_homogeneous:
        raise ValueError("step_single_agent needs scalar PlantParams; use params.agent(i)")
    m, g = params.mass_kg, params.g
    k = [0.5 * params.air_density_kg_m3 * params.drag_coeff[j] * params.drag_area_m2[j] / m for j in range(3)]
    amax = params.thrust_to_weight * g
    tan_t = math.tan(math.radians(params.tilt_max_deg))
    n = substep_count(dt_s, params)
    h = dt_s / n
    v = [float(x) for x in vel_ned_m_s]
    a = [float(x) for x in thrust_accel_ned_m_s2]
    gvec = (0.0, 0.0, g)
    for _ in range(n):
        # desired thrust: shaping - gravity compensation - k_ff * drag(v_cmd - w_ff)/m
        ad = [0.0, 0.0, 0.0]
        for j in range(3):
            air_c = cmd_ned_m_s[j] - wind_ff_ned_m_s[j]
            drag_c = -k[j] * abs(air_c) * air_c
            meas = v[j] + feedback_noise_ned_m_s[j]
            ad[j] = (cmd_ned_m_s[j] - meas) / params.tau_v_s - gvec[j] - params.drag_feedforward_gain * drag_c
        # limits: vertical first, then the horizontal within cone and remaining thrust
        up = min(max(-ad[2], 0.0), amax)
        h_norm = math.sqrt(ad[0] ** 2 + ad[1] ** 2)
        h_max = min(up * tan_t, math.sqrt(max(amax**2 - up**2, 0.0)))
        s = h_max / h_norm if h_norm > h_max else 1.0
        ac = [ad[0] * s, ad[1] * s, -up]
        # semi-implicit Euler: thrust lag (backward Euler), then velocity with new thrust
        drag = [-k[j] * abs(v[j] - wind_ned_m_s[j]) * (v[j] - wind_ned_m_s[j]) for j in range(3)]
        for j in range(3):
            a[j] = (a[j] + h / params.tau_thrust_s * ac[j]) / (1.0 + h / params.tau_thrust_s)
        for j in range(3):
            v[j] = v[j] + h * (a[j] + gvec[j] + drag[j])
    return (v[0], v[1], v[2]), (a[0], a[1], a[2])


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
        takes a C-contiguous float64 (N, 3) or (1, 3) command of a plant with a fleet-wide
        coefficient row on a compiled backend; anything else (or a plant whose agents changed
        since) goes through :meth:`step`, which checks its arguments."""
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be > 0 and finite, got {dt_s!r}")
        co = self._co
        kernel = _select_kernel(self._backend)
        if kernel is None or co.rows != 1:
            return lambda v_cmd_ned_m_s: self.step(v_cmd_ned_m_s, dt_s)
        nsub = substep_count(dt_s, co)
        h = dt_s / nsub
        fleet = fleet_kernel()
        args = _fleet_args(co, h, nsub)

        def step(v_cmd_ned_m_s: np.ndarray) -> np.ndarray:
            cmd = v_cmd_ned_m_s
            if (self._co is not co or type(cmd) is not np.ndarray or cmd.dtype != np.float64 or cmd.ndim != 2
                    or cmd.shape[1] != 3 or cmd.shape[0] not in (1, self._vel.shape[0]) or not cmd.flags.c_contiguous):
                return self.step(cmd, dt_s)
            fleet(self._vel, self._thr, cmd, *args)
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
