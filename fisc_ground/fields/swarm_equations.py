"""The paper's swarm-gas equations, one function each (arrays of per-CV moments in, per-CV
fields out): swarm velocity, density, pressure, internal and dispersion pressure, temperatures,
inter-agent spacing, control energy and sound speed, with the gas parameters they need.
``fisc_ground.fields.swarm_fields`` reduces agent samples to the moments and composes these."""

from __future__ import annotations

from dataclasses import dataclass

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
