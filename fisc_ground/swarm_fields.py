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
* one function per paper equation (``swarm_velocity``, ``swarm_density``, ``swarm_pressure``,
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

G_M_S2 = 9.81
"""Standard gravity used for the default a_max [m/s^2]."""

NOMINAL_THRUST_TO_WEIGHT = 2.2
"""The paper's nominal agent thrust-to-weight ratio T_max / (m g) (section "Individual-Agent
Velocity Plant")."""


@dataclass(frozen=True)
class SwarmGasParams:
    """Constitutive parameters of the swarm "gas" (paper section "Constitutive Parameters").

    The paper fixes none of these numerically; the defaults are documented choices:
    ``K_b,s = 1`` and ``c_v,s = 1`` so that temperatures are plain specific energies
    [m^2/s^2] (the paper's nomenclature gives T in m^2/s^2), ``gamma_s = 1.4`` (the value of
    the air the reference CFD solves, so the swarm analogue of the isentropic exponent matches
    the reference flow), ``lambda = 0.5`` (mid-range of 0 < lambda < 1), and
    ``a_max = (T/W - 1) g = (2.2 - 1) * 9.81 = 11.77 m/s^2``: the specific acceleration the
    nominal agent (T_max / (m g) = 2.2) still has after holding its weight, i.e. the authority
    available in the worst (climbing) direction.  ``omega = tau = 0`` gives the low-frequency
    sound speed c = sqrt(gamma_s R_s T_s).
    """

    k_b_s: float = 1.0
    """K_b,s: Boltzmann-analogue scale from velocity variance to swarm energy [-]."""
    c_v_s: float = 1.0
    """c_v,s: swarm specific heat at constant volume (e_s = c_v,s T_s) [-]."""
    gamma_s: float = 1.4
    """gamma_s = c_p,s / c_v,s: swarm specific-heat ratio (compressibility) [-]."""
    lambda_ctrl: float = 0.5
    """lambda: share of the control-energy budget used (0 < lambda < 1) [-]."""
    a_max_m_s2: float = (NOMINAL_THRUST_TO_WEIGHT - 1.0) * G_M_S2
    """a_max = F_max / m: maximum specific acceleration available for control [m/s^2]."""
    omega_rad_s: float = 0.0
    """omega: angular frequency of the disturbance in the sound-speed relation [rad/s]."""
    tau_s: float = 0.0
    """tau: reaction delay (actuation latency, filtering) in the sound-speed relation [s]."""

    def __post_init__(self) -> None:
        for name in ("k_b_s", "c_v_s", "a_max_m_s2"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"SwarmGasParams.{name} must be > 0, got {getattr(self, name)!r}")
        if not self.gamma_s >= 1.0:
            raise ValueError(f"SwarmGasParams.gamma_s must be >= 1, got {self.gamma_s!r}")
        if not 0.0 <= self.lambda_ctrl <= 1.0:
            raise ValueError(f"SwarmGasParams.lambda_ctrl must be in [0, 1], got {self.lambda_ctrl!r}")
        if self.omega_rad_s < 0.0 or self.tau_s < 0.0:
            raise ValueError("SwarmGasParams.omega_rad_s and tau_s must be >= 0")

    @property
    def c_p_s(self) -> float:
        """c_p,s = gamma_s c_v,s: swarm specific heat at constant pressure (h_s = c_p,s T_s)."""
        return self.gamma_s * self.c_v_s

    @property
    def r_s(self) -> float:
        """R_s = c_p,s - c_v,s: swarm gas constant (state relation P_s = rho_s R_s T_s)."""
        return self.c_p_s - self.c_v_s


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
    if np.any(~(norm > 1e-12)):
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


def _volume(cell_volume_m3: np.ndarray | float) -> np.ndarray | float:
    """A scalar volume as float, a per-CV volume array as float array (no checks)."""
    v = np.asarray(cell_volume_m3, dtype=float)
    return float(v) if v.ndim == 0 else v


def check_cell_volumes(cell_volume_m3: np.ndarray | float, n_cv: int) -> np.ndarray | float:
    """Validate a CV volume: a scalar > 0 (every CV l^3) or an (n_cv,) array of finite values > 0
    (per-CV effective volumes A_j dx_j).  Returns a float or a float64 array."""
    v = np.asarray(cell_volume_m3, dtype=float)
    if v.ndim == 0:
        if not float(v) > 0.0:
            raise ValueError(f"cell_volume_m3 must be > 0, got {cell_volume_m3!r}")
        return float(v)
    if v.shape != (n_cv,):
        raise ValueError(f"cell_volume_m3 must be a scalar or an ({n_cv},) array, got shape {v.shape}")
    if np.any(~(v > 0.0)) or not np.all(np.isfinite(v)):
        j = int(np.flatnonzero(~((v > 0.0) & np.isfinite(v)))[0])
        raise ValueError(f"cell_volume_m3[{j}] must be finite and > 0, got {float(v[j])!r}")
    return v.copy()


def _safe_div(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num / den where den > 0, NaN elsewhere (broadcasts a trailing axis for vectors)."""
    den = np.asarray(den, dtype=float)
    ok = den > 0.0
    shaped = ok if np.ndim(num) == ok.ndim else ok[:, None]
    d = den if np.ndim(num) == den.ndim else den[:, None]
    return np.where(shaped, num / np.where(shaped, d, 1.0), np.nan)


def mean_velocity(momentum_kg_m_s: np.ndarray, mass_kg: np.ndarray) -> np.ndarray:
    """U = sum m_i v_i / sum m_i, the local mass-weighted mean velocity (eq. temperature_random)."""
    return _safe_div(momentum_kg_m_s, mass_kg)


def swarm_velocity(momentum_kg_m_s: np.ndarray, mass_kg: np.ndarray,
                   drift_dir: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. swarm_velocity: u_s = (1/M) sum m_i (v_i . u_hat_d) u_hat_d.

    Since the projection is linear, (1/M) sum m_i (v_i . d) = U . d.  Returns the axial scalar
    u_s . u_hat_d (n_cv,) and the vector u_s (n_cv, 3); NaN in empty CVs.
    ``drift_dir``: (n_cv, 3) unit vectors (see ``drift_directions``).
    """
    u_axial = np.einsum("ij,ij->i", mean_velocity(momentum_kg_m_s, mass_kg), drift_dir)
    return u_axial, u_axial[:, None] * drift_dir


def swarm_density(mass_kg: np.ndarray, cell_volume_m3: np.ndarray | float) -> np.ndarray:
    """Eq. swarm_density: rho_s = m N_j / (A_j dx_j).

    ``cell_volume_m3`` is the CV's *effective* volume A_j dx_j: l^3 for a full cubic CV, or a
    per-CV (n_cv,) array such as ``l^3 * cv_open_fraction`` for CVs that lie partly outside
    the tunnel (A_j the effective cross-section).  Written with the CV's total mass
    M_j = sum m_i, which is m N_j for identical agents and the mass-weighted generalisation
    for heterogeneous fleets.
    """
    return np.asarray(mass_kg, dtype=float) / _volume(cell_volume_m3)


def swarm_pressure(m_v2_kg_m2_s2: np.ndarray, cell_volume_m3: np.ndarray | float) -> np.ndarray:
    """Eq. swarm_pressure: P_s = 2/(3 dV) sum_i m_i ||v_i||^2 (trace of the momentum-exchange tensor).

    ``cell_volume_m3``: scalar or per-CV (n_cv,) effective volume dV_j (see ``swarm_density``)."""
    return 2.0 * np.asarray(m_v2_kg_m2_s2, dtype=float) / (3.0 * _volume(cell_volume_m3))


def pressure_density(rho_s_kg_m3: np.ndarray, mean_square_speed_m2_s2: np.ndarray) -> np.ndarray:
    """Eq. pressure_density: P_s = 2/3 rho_s <||v_i||^2> (mass-weighted mean square speed)."""
    return 2.0 / 3.0 * np.asarray(rho_s_kg_m3) * np.asarray(mean_square_speed_m2_s2)


def internal_pressure(rho_s_kg_m3: np.ndarray, m_v2_kg_m2_s2: np.ndarray, mass_kg: np.ndarray,
                      u_s_m_s: np.ndarray, momentum_kg_m_s: np.ndarray) -> np.ndarray:
    """Eq. internal_pressure: P_s,internal = 2/3 rho_s <||v_i - u_s||^2>.

    The mass-weighted mean <||v - u_s||^2> = sum m||v||^2 / M - 2 u_s . (sum m v)/M + ||u_s||^2
    is formed from moments (clipped at 0 against round-off).  Empty CVs give 0 (no agents, no
    pressure).
    """
    mean_v2 = _safe_div(m_v2_kg_m2_s2, mass_kg)
    u_dot_U = np.einsum("ij,ij->i", u_s_m_s, mean_velocity(momentum_kg_m_s, mass_kg))
    var = np.maximum(mean_v2 - 2.0 * u_dot_U + np.einsum("ij,ij->i", u_s_m_s, u_s_m_s), 0.0)
    return np.where(np.asarray(mass_kg) > 0.0, pressure_density(rho_s_kg_m3, var), 0.0)


def dispersion_pressure(m_dev2_kg_m2_s2: np.ndarray, cell_volume_m3: np.ndarray | float) -> np.ndarray:
    """Eq. pressure_constraint: P = 2 m / (3 dV) sum_i ||v_i - v_target,j||^2.

    The pressure the paper compares with the CFD in its simulations ("computed from the mean
    squared difference of the target and actual velocities"), written with each agent's own
    mass m_i.  Input: the moment sum m_i ||v_i - v_ref,j||^2 (``cv_moments``); ``cell_volume_m3``
    scalar or per-CV (n_cv,) effective volume dV_j (see ``swarm_density``).
    """
    return 2.0 * np.asarray(m_dev2_kg_m2_s2, dtype=float) / (3.0 * _volume(cell_volume_m3))


def temperature_random(m_v2_kg_m2_s2: np.ndarray, momentum_kg_m_s: np.ndarray, mass_kg: np.ndarray,
                       k_b_s: float = 1.0) -> np.ndarray:
    """Eq. temperature_random: T_s,rand = K_b,s sum m_i ||v_i - U||^2 / (2 sum m_i).

    With U = sum m v / M, sum m ||v - U||^2 / M = sum m ||v||^2 / M - ||U||^2 (clipped at 0).
    NaN in empty CVs.
    """
    U = mean_velocity(momentum_kg_m_s, mass_kg)
    var = np.maximum(_safe_div(m_v2_kg_m2_s2, mass_kg) - np.einsum("ij,ij->i", U, U), 0.0)
    return 0.5 * float(k_b_s) * var


def interagent_spacing(number_density_per_m3: np.ndarray) -> np.ndarray:
    """L_c ~ rho_s^(-1/3) (section "Swarm Density"), evaluated with the agent *number* density.

    The paper writes L_c ~ rho_s^(-1/3); a length needs a number density, so
    L_c = n^(-1/3) with n = N / dV (identical to the paper's form for unit-mass agents, the
    paper's nominal m = 1 kg).  NaN where the CV is empty.
    """
    n = np.asarray(number_density_per_m3, dtype=float)
    return np.where(n > 0.0, np.where(n > 0.0, n, 1.0) ** (-1.0 / 3.0), np.nan)


def control_energy(spacing_m: np.ndarray, a_max_m_s2: float) -> np.ndarray:
    """e_ctrl = a_max L_c, the available control energy per unit mass (eq. swarm_temperature)."""
    return float(a_max_m_s2) * np.asarray(spacing_m, dtype=float)


def swarm_temperature(t_rand_m2_s2: np.ndarray, e_ctrl_m2_s2: np.ndarray,
                      params: SwarmGasParams) -> tuple[np.ndarray, np.ndarray]:
    """Eq. swarm_temperature: T_s = T_s,rand + T_s,ctrl = (e_rand + lambda e_ctrl) / c_v,s.

    T_s,rand comes from eq. temperature_random (scaled by K_b,s; with the default
    K_b,s = c_v,s = 1 both readings of the paper coincide); T_s,ctrl = lambda e_ctrl / c_v,s.
    Returns (T_ctrl, T_s).
    """
    t_ctrl = params.lambda_ctrl * np.asarray(e_ctrl_m2_s2, dtype=float) / params.c_v_s
    return t_ctrl, np.asarray(t_rand_m2_s2, dtype=float) + t_ctrl


def sound_speed(t_s_m2_s2: np.ndarray, params: SwarmGasParams) -> np.ndarray:
    """Eq. sound_speed: c^2 = gamma_s R_s T_s / (1 + omega^2 tau^2)."""
    c2 = params.gamma_s * params.r_s * np.asarray(t_s_m2_s2, dtype=float)
    return np.sqrt(c2 / (1.0 + (params.omega_rad_s * params.tau_s) ** 2))


# --------------------------------------------------------------------------------------------
# Composition


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
        mom = cv_moments(cv_ids, velocities_m_s, masses_kg, self.n_cv, reference_velocity_m_s)
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
