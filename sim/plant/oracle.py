"""The scalar test oracle of the plant step: one agent, plain Python floats, loops over axes.

Written directly from the paper's equations and the sub-step order of :func:`sim.plant.model.step_plant`,
independently of the vectorised code (:mod:`sim.plant.kernel`); the tests hold both the numpy
reference and the compiled kernel to it.
"""

from __future__ import annotations

import math

from sim.plant.model import substep_count
from sim.plant.params import PlantParams

__all__ = ["step_single_agent"]


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
