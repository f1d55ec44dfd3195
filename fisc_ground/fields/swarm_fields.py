"""The paper's swarm quartet Q = {u_s, rho_s, P_s, T_s} per control volume, from agent samples.

Shared by the simulator (time-averaged fields of a run) and the ground-station monitor (live
fields from telemetry).  Everything is vectorised over agents and CVs (``np.bincount``); there
is no per-agent or per-CV Python loop.

Two layers:

* ``cv_moments`` reduces agent samples ``(cv_id, velocity, mass)`` to additive per-CV
  *moments*: agent count, mass M = sum m_i, momentum sum m_i v_i, second moment
  sum m_i ||v_i||^2 and, when a per-CV reference (target) velocity is given,
  sum m_i ||v_i - v_ref,j||^2.  Moments of several time samples simply add up, which is what
  makes time averaging (``FieldAccumulator``) and replay/merging exact.
* one function per paper equation, in ``fisc_ground.fields.swarm_equations`` (``swarm_velocity``, ``swarm_density``, ``swarm_pressure``,
  ``pressure_density``, ``internal_pressure``, ``dispersion_pressure``, ``temperature_random``,
  ``control_energy``, ``swarm_temperature``, ``sound_speed``) working on those per-CV
  moments, and ``fields_from_moments`` that composes them into a ``SwarmFields``.

Time averaging.  With K time samples, the time-averaged moments are the summed moments
divided by K.  Quantities that are *sums over the CV* (density, P_s, the dispersion pressure)
are then exactly the time means of their instantaneous values (e.g. rho = total mass /
(K dV)).  Quantities that are *means over the agents* (u_s, U, T_rand, P_internal's velocity
variance) use the pooled mass-weighted moments over all samples, i.e. the variance about the
time-averaged local velocity (it includes temporal fluctuation, as a time-averaged
temperature should).

Conventions for CVs without agents: sums are 0 (count, mass, rho_s, P_s, P_internal,
P_dispersion) and means are NaN (u_s, U, T_rand, T_ctrl, T_s, L_c, sound speed).
"""

from __future__ import annotations

from dataclasses import dataclass, fields as dc_fields

import numpy as np

from fisc_ground.fields.swarm_equations import (SwarmGasParams, check_cell_volumes, control_energy, dispersion_pressure,
                                         interagent_spacing, internal_pressure, mean_velocity, sound_speed,
                                         swarm_density, swarm_pressure, swarm_temperature, swarm_velocity,
                                         temperature_random)


@dataclass(frozen=True)
class CVMoments:
    """Additive per-CV moments of agent samples (sums over agents, divided by ``n_time_samples``
    when they describe a time average).  All arrays have ``n_cv`` rows."""

    count: np.ndarray
    """(n_cv,) agents per CV (per time sample) [-]."""
    mass_kg: np.ndarray
    """(n_cv,) M = sum m_i [kg]."""
    momentum_kg_m_s: np.ndarray
    """(n_cv, 3) sum m_i v_i [kg m/s]."""
    m_v2_kg_m2_s2: np.ndarray
    """(n_cv,) sum m_i ||v_i||^2 [kg m^2/s^2]."""
    m_dev2_kg_m2_s2: np.ndarray | None
    """(n_cv,) sum m_i ||v_i - v_ref,j||^2 [kg m^2/s^2], or None without a reference."""


@dataclass(frozen=True)
class SwarmFields:
    """The swarm quartet Q and derived quantities per CV (instantaneous or time-averaged)."""

    n_time_samples: int
    """Number of time samples averaged (1 for instantaneous fields)."""
    samples: np.ndarray
    """(n_cv,) int: agent samples that fell in the CV over all time samples."""
    count: np.ndarray
    """(n_cv,) mean number of agents in the CV per time sample, N_j [-]."""
    mass_kg: np.ndarray
    """(n_cv,) mean agent mass in the CV per time sample, M_j [kg]."""
    drift_dir: np.ndarray
    """(n_cv, 3) unit drift direction u_hat_d used for the projection."""
    mean_velocity_m_s: np.ndarray
    """(n_cv, 3) mass-weighted mean velocity U (NaN where empty) [m/s]."""
    u_axial_m_s: np.ndarray
    """(n_cv,) swarm velocity along the drift direction, u_s . u_hat_d (eq. swarm_velocity) [m/s]."""
    u_s_m_s: np.ndarray
    """(n_cv, 3) swarm velocity vector u_s = (u_s . u_hat_d) u_hat_d (eq. swarm_velocity) [m/s]."""
    rho_s_kg_m3: np.ndarray
    """(n_cv,) swarm density rho_s (eq. swarm_density) [kg/m^3]."""
    number_density_per_m3: np.ndarray
    """(n_cv,) agent number density n = N / dV [1/m^3]."""
    p_s_pa: np.ndarray
    """(n_cv,) swarm pressure P_s = 2/(3 dV) sum m ||v||^2 (eqs. swarm_pressure, pressure_density) [Pa]."""
    p_internal_pa: np.ndarray
    """(n_cv,) internal pressure 2/3 rho_s <||v - u_s||^2> (eq. internal_pressure) [Pa]."""
    p_dispersion_pa: np.ndarray
    """(n_cv,) 2/(3 dV) sum m ||v - v_ref,j||^2 (eq. pressure_constraint); NaN without reference [Pa]."""
    t_rand_m2_s2: np.ndarray
    """(n_cv,) random temperature T_s,rand (eq. temperature_random) [m^2/s^2]."""
    t_ctrl_m2_s2: np.ndarray
    """(n_cv,) control temperature T_s,ctrl = lambda a_max L_c / c_v,s (eq. swarm_temperature) [m^2/s^2]."""
    t_s_m2_s2: np.ndarray
    """(n_cv,) swarm temperature T_s = T_rand + T_ctrl (eq. swarm_temperature) [m^2/s^2]."""
    spacing_m: np.ndarray
    """(n_cv,) characteristic inter-agent spacing L_c = n^(-1/3) [m]."""
    sound_speed_m_s: np.ndarray
    """(n_cv,) swarm speed of sound c (eq. sound_speed) [m/s]."""

    @property
    def n_cv(self) -> int:
        """Number of control volumes."""
        return int(self.count.shape[0])

    def as_arrays(self) -> dict[str, np.ndarray]:
        """All fields as a name -> array dict (e.g. for ``np.savez``)."""
        return {f.name: np.asarray(getattr(self, f.name)) for f in dc_fields(self)}


# --------------------------------------------------------------------------------------------
# Aggregation


def _as_cv_ids(cv_ids: np.ndarray, n_cv: int) -> np.ndarray:
    ids = np.asarray(cv_ids)
    if ids.ndim != 1:
        raise ValueError(f"cv_ids must be a 1-D array, got shape {ids.shape}")
    if ids.size and not np.issubdtype(ids.dtype, np.integer):
        raise ValueError(f"cv_ids must be integers, got dtype {ids.dtype}")
    ids = ids.astype(np.int64, copy=False)
    if ids.size and ids.max() >= n_cv:
        raise ValueError(f"cv_ids contains {int(ids.max())}, but n_cv is {n_cv}")
    if ids.size and ids.min() < -1:
        raise ValueError(f"cv_ids contains {int(ids.min())}; only -1 (outside the map) may be negative")
    return ids


def _as_masses(masses: np.ndarray | float, n: int) -> np.ndarray:
    m = np.asarray(masses, dtype=float)
    if m.ndim == 0:
        m = np.full(n, float(m))
    if m.shape != (n,):
        raise ValueError(f"masses must be a scalar or an ({n},) array, got shape {m.shape}")
    if np.any(~(m > 0.0)):
        raise ValueError("masses must be finite and > 0")
    return m


def drift_directions(drift_dir: np.ndarray | None, n_cv: int) -> np.ndarray:
    """(n_cv, 3) unit drift directions from None (+x), a (3,) vector or an (n_cv, 3) array."""
    d = np.array([1.0, 0.0, 0.0]) if drift_dir is None else np.asarray(drift_dir, dtype=float)
    if d.shape == (3,):
        d = np.broadcast_to(d, (n_cv, 3))
    if d.shape != (n_cv, 3):
        raise ValueError(f"drift_dir must be (3,) or ({n_cv}, 3), got shape {d.shape}")
    norm = np.linalg.norm(d, axis=1)
    if np.any(~(np.isfinite(norm) & (norm > 1e-12))):  # an infinite component made NaN directions
        raise ValueError("drift_dir contains a zero or non-finite direction")
    return d / norm[:, None]


def cv_moments(cv_ids: np.ndarray, velocities_m_s: np.ndarray, masses_kg: np.ndarray | float,
               n_cv: int, reference_velocity_m_s: np.ndarray | None = None) -> CVMoments:
    """Per-CV additive moments of one set of agent samples (agents with ``cv_id == -1`` ignored).

    ``reference_velocity_m_s``: (n_cv, 3) per-CV reference (target) velocity v_ref,j; when given
    the moment sum m_i ||v_i - v_ref,j||^2 for the dispersion pressure is formed.
    """
    ids = _as_cv_ids(cv_ids, n_cv)
    v = np.asarray(velocities_m_s, dtype=float)
    if v.shape != (ids.shape[0], 3):
        raise ValueError(f"velocities must be ({ids.shape[0]}, 3), got shape {v.shape}")
    m = _as_masses(masses_kg, ids.shape[0])
    keep = ids >= 0
    ids, v, m = ids[keep], v[keep], m[keep]
    if not np.all(np.isfinite(v)):
        raise ValueError("velocities of agents inside the map must be finite")
    count = np.bincount(ids, minlength=n_cv).astype(float)
    mass = np.bincount(ids, weights=m, minlength=n_cv)
    mv = m[:, None] * v
    momentum = np.stack([np.bincount(ids, weights=mv[:, k], minlength=n_cv) for k in range(3)], axis=1)
    m_v2 = np.bincount(ids, weights=m * np.einsum("ij,ij->i", v, v), minlength=n_cv)
    m_dev2 = None
    if reference_velocity_m_s is not None:
        ref = np.asarray(reference_velocity_m_s, dtype=float)
        if ref.shape != (n_cv, 3):
            raise ValueError(f"reference_velocity must be ({n_cv}, 3) (one per CV), got shape {ref.shape}")
        dv = v - ref[ids]
        m_dev2 = np.bincount(ids, weights=m * np.einsum("ij,ij->i", dv, dv), minlength=n_cv)
    return CVMoments(count=count, mass_kg=mass, momentum_kg_m_s=momentum, m_v2_kg_m2_s2=m_v2,
                     m_dev2_kg_m2_s2=m_dev2)


# --------------------------------------------------------------------------------------------
# The paper's equations, on per-CV moments


def fields_from_moments(moments: CVMoments, cell_volume_m3: float, drift_dir: np.ndarray | None = None,
                        params: SwarmGasParams | None = None, n_time_samples: int = 1,
                        samples: np.ndarray | None = None) -> SwarmFields:
    """All of Q from per-CV moments that describe *one* (possibly time-averaged) sample.

    ``moments``: per-sample moments (summed moments divided by ``n_time_samples``).
    ``cell_volume_m3``: l^3 (scalar) or per-CV effective volumes (n_cv,) (eq. swarm_density).
    ``samples``: agent samples per CV (defaults to ``count``).
    """
    p = SwarmGasParams() if params is None else params
    n_cv = moments.count.shape[0]
    cell_volume_m3 = check_cell_volumes(cell_volume_m3, n_cv)
    d = drift_directions(drift_dir, n_cv)
    U = mean_velocity(moments.momentum_kg_m_s, moments.mass_kg)
    u_axial, u_vec = swarm_velocity(moments.momentum_kg_m_s, moments.mass_kg, d)
    rho = swarm_density(moments.mass_kg, cell_volume_m3)
    n_density = moments.count / cell_volume_m3
    p_s = swarm_pressure(moments.m_v2_kg_m2_s2, cell_volume_m3)
    p_int = internal_pressure(rho, moments.m_v2_kg_m2_s2, moments.mass_kg, u_vec, moments.momentum_kg_m_s)
    if moments.m_dev2_kg_m2_s2 is None:
        p_disp = np.full(n_cv, np.nan)
    else:
        p_disp = dispersion_pressure(moments.m_dev2_kg_m2_s2, cell_volume_m3)
    t_rand = temperature_random(moments.m_v2_kg_m2_s2, moments.momentum_kg_m_s, moments.mass_kg, p.k_b_s)
    spacing = interagent_spacing(n_density)
    t_ctrl, t_s = swarm_temperature(t_rand, control_energy(spacing, p.a_max_m_s2), p)
    samp = np.rint(moments.count).astype(np.int64) if samples is None else np.asarray(samples, dtype=np.int64)
    return SwarmFields(
        n_time_samples=int(n_time_samples), samples=samp, count=moments.count, mass_kg=moments.mass_kg,
        drift_dir=d, mean_velocity_m_s=U, u_axial_m_s=u_axial, u_s_m_s=u_vec, rho_s_kg_m3=rho,
        number_density_per_m3=n_density, p_s_pa=p_s, p_internal_pa=p_int, p_dispersion_pa=p_disp,
        t_rand_m2_s2=t_rand, t_ctrl_m2_s2=t_ctrl, t_s_m2_s2=t_s, spacing_m=spacing,
        sound_speed_m_s=sound_speed(t_s, p),
    )


def instantaneous_fields(cv_ids: np.ndarray, velocities_m_s: np.ndarray, masses_kg: np.ndarray | float,
                         n_cv: int, cell_volume_m3: np.ndarray | float, drift_dir: np.ndarray | None = None,
                         reference_velocity_m_s: np.ndarray | None = None,
                         params: SwarmGasParams | None = None) -> SwarmFields:
    """Q per CV at one instant from agent samples.

    ``cv_ids`` (N,) CV of each agent (-1 = outside the map, ignored); ``velocities_m_s``
    (N, 3); ``masses_kg`` scalar or (N,); ``cell_volume_m3`` l^3 or per-CV effective volumes
    (n_cv,) (eq. swarm_density); ``drift_dir`` None (+x), (3,) or (n_cv, 3);
    ``reference_velocity_m_s`` (n_cv, 3) per-CV target velocity for the dispersion pressure
    (eq. pressure_constraint), NaN fields without it.
    """
    mom = cv_moments(cv_ids, velocities_m_s, masses_kg, n_cv, reference_velocity_m_s)
    return fields_from_moments(mom, cell_volume_m3, drift_dir, params)


class FieldAccumulator:
    """Time-averaged swarm fields: accumulate agent samples, O(N) per ``add`` (bincount).

    The state is a handful of per-CV sums (``state()``/``from_state()`` give plain numpy arrays
    for saving or replay; ``merge`` adds another accumulator's sums).  ``result()`` returns
    the time-averaged ``SwarmFields``: density and pressures are the means over time samples of
    their instantaneous values (rho = total mass / (K dV)); velocities and variances are
    mass-weighted over all agent samples (see module docstring).  The dispersion pressure is
    averaged over the samples that carried a reference velocity.
    """

    _SUMS = ("count", "mass_kg", "momentum_kg_m_s", "m_v2_kg_m2_s2", "m_dev2_kg_m2_s2")

    def __init__(self, n_cv: int, cell_volume_m3: np.ndarray | float, drift_dir: np.ndarray | None = None,
                 params: SwarmGasParams | None = None) -> None:
        if int(n_cv) < 0:
            raise ValueError(f"n_cv must be >= 0, got {n_cv}")
        self.n_cv = int(n_cv)
        self.cell_volume_m3 = check_cell_volumes(cell_volume_m3, self.n_cv)
        """l^3 (float) or per-CV effective volumes (n_cv,) [m^3] (eq. swarm_density)."""
        self.drift_dir = drift_directions(drift_dir, self.n_cv)
        self.params = SwarmGasParams() if params is None else params
        self.count = np.zeros(self.n_cv)
        self.mass_kg = np.zeros(self.n_cv)
        self.momentum_kg_m_s = np.zeros((self.n_cv, 3))
        self.m_v2_kg_m2_s2 = np.zeros(self.n_cv)
        self.m_dev2_kg_m2_s2 = np.zeros(self.n_cv)
        self.n_time_samples = 0
        self.n_ref_samples = 0

    def add(self, cv_ids: np.ndarray, velocities_m_s: np.ndarray, masses_kg: np.ndarray | float,
            reference_velocity_m_s: np.ndarray | None = None) -> None:
        """Add one time sample of all agents (same arguments as ``instantaneous_fields``)."""
        self.add_moments(cv_moments(cv_ids, velocities_m_s, masses_kg, self.n_cv, reference_velocity_m_s))

    def add_moments(self, mom: CVMoments) -> None:
        """Add one time sample already reduced to per-CV moments (``cv_moments``), e.g. when the same
        sample also feeds a ``fisc_ground.fields.time_blocks.BlockAccumulator``."""
        if mom.count.shape != (self.n_cv,):
            raise ValueError(f"moments of {mom.count.shape[0]} CVs added to an accumulator of {self.n_cv}")
        self.count += mom.count
        self.mass_kg += mom.mass_kg
        self.momentum_kg_m_s += mom.momentum_kg_m_s
        self.m_v2_kg_m2_s2 += mom.m_v2_kg_m2_s2
        if mom.m_dev2_kg_m2_s2 is not None:
            self.m_dev2_kg_m2_s2 += mom.m_dev2_kg_m2_s2
            self.n_ref_samples += 1
        self.n_time_samples += 1

    def merge(self, other: "FieldAccumulator") -> None:
        """Add the sums of another accumulator over the same CVs (e.g. another time window)."""
        if other.n_cv != self.n_cv or not np.array_equal(np.asarray(other.cell_volume_m3),
                                                          np.asarray(self.cell_volume_m3)):
            raise ValueError("merge: accumulators differ in n_cv or cell volume")
        for name in self._SUMS:
            setattr(self, name, getattr(self, name) + getattr(other, name))
        self.n_time_samples += other.n_time_samples
        self.n_ref_samples += other.n_ref_samples

    def state(self) -> dict[str, np.ndarray]:
        """The complete state as numpy arrays (``np.savez``-able); see ``from_state``."""
        out = {name: getattr(self, name).copy() for name in self._SUMS}
        out.update(n_time_samples=np.array(self.n_time_samples), n_ref_samples=np.array(self.n_ref_samples),
                   cell_volume_m3=np.array(self.cell_volume_m3, dtype=float), drift_dir=self.drift_dir.copy())
        return out

    @classmethod
    def from_state(cls, state: dict[str, np.ndarray], params: SwarmGasParams | None = None) -> "FieldAccumulator":
        """Rebuild an accumulator from ``state()`` output."""
        try:
            acc = cls(int(np.asarray(state["count"]).shape[0]), np.asarray(state["cell_volume_m3"], dtype=float),
                      np.asarray(state["drift_dir"]), params)
            for name in cls._SUMS:
                arr = np.array(state[name], dtype=float)
                if arr.shape != getattr(acc, name).shape:
                    raise ValueError(f"state array {name!r} has shape {arr.shape}, expected {getattr(acc, name).shape}")
                setattr(acc, name, arr)
            acc.n_time_samples = int(state["n_time_samples"])
            acc.n_ref_samples = int(state["n_ref_samples"])
        except KeyError as exc:
            raise ValueError(f"accumulator state lacks {exc.args[0]!r}") from exc
        return acc

    def result(self) -> SwarmFields:
        """Time-averaged fields over all samples added so far (all-NaN/zero before any ``add``)."""
        k = max(self.n_time_samples, 1)
        m_dev2 = self.m_dev2_kg_m2_s2 / self.n_ref_samples if self.n_ref_samples else None
        mom = CVMoments(count=self.count / k, mass_kg=self.mass_kg / k, momentum_kg_m_s=self.momentum_kg_m_s / k,
                        m_v2_kg_m2_s2=self.m_v2_kg_m2_s2 / k, m_dev2_kg_m2_s2=m_dev2)
        return fields_from_moments(mom, self.cell_volume_m3, self.drift_dir, self.params,
                                   n_time_samples=self.n_time_samples,
                                   samples=np.rint(self.count).astype(np.int64))
