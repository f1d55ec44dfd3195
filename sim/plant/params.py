"""Parameters of the quadrotor velocity plant and the per-agent coefficients its step kernels use.

:class:`PlantParams` (frozen; the paper's nominal small quadrotor by default, any physical field
fleet-wide or per agent) and :class:`PlantCoefficients` (the derived rows the kernels read, with
``take``/``concat`` for agents leaving and entering).  See :mod:`sim.plant.model` for the equations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["PlantCoefficients", "PlantParams"]

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
