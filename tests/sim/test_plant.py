"""Specification of the quadrotor velocity plant (paper section "Individual-Agent Velocity Plant").

The figure tests assert on the same ``sim.plant.checks`` functions that print the
"ours vs the paper" table of docs/plant.md.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.plant import checks as pc
from sim.plant.model import (
    PlantParams,
    VelocityPlant,
    constrain_thrust_accel,
    desired_thrust_accel,
    drag_accel,
    numba_available,
    plant_derivatives,
    step_plant,
    substep_count,
    thrust_accel_norm,
    tilt_deg,
    trim_thrust_accel,
)
from sim.plant.kernel import BLOCK
from sim.plant.oracle import step_single_agent
from ..optional import needs

BACKENDS = ["numpy", pytest.param("numba", marks=needs(numba_available(), "numba", extra="jit"))]
G = 9.81
TAN55 = math.tan(math.radians(55.0))


def random_state(n: int, seed: int = 0, params: PlantParams = PlantParams()):
    rng = np.random.default_rng(seed)
    vel = rng.normal(0.0, 6.0, (n, 3))
    thr = trim_thrust_accel(rng.normal(0.0, 6.0, (n, 3)), params)
    cmd = rng.normal(0.0, 12.0, (n, 3))
    wind = rng.normal(0.0, 4.0, (n, 3))
    return rng, vel, thr, cmd, wind


def hetero_params(n: int, seed: int = 3) -> PlantParams:
    rng = np.random.default_rng(seed)
    return PlantParams(
        mass_kg=rng.uniform(0.5, 3.0, n),
        tau_v_s=rng.uniform(0.2, 1.0, n),
        tau_thrust_s=rng.uniform(0.03, 0.15, n),
        thrust_to_weight=rng.uniform(1.3, 5.0, n),
        tilt_max_deg=rng.uniform(25.0, 65.0, n),
        drag_area_m2=rng.uniform(0.01, 0.05, (n, 3)),
        drag_coeff=rng.uniform(0.8, 1.4, (n, 3)),
        drag_feedforward_gain=rng.uniform(0.0, 1.0, n),
    )


# --- parameters --------------------------------------------------------------------------------


def test_defaults_are_the_papers_nominal_quadrotor():
    p = PlantParams()
    assert (p.mass_kg, p.g, p.tau_v_s, p.tau_thrust_s) == (1.0, 9.81, 0.5, 0.08)
    assert (p.thrust_to_weight, p.tilt_max_deg, p.air_density_kg_m3) == (2.2, 55.0, 1.225)
    np.testing.assert_array_equal(p.drag_area_m2, [0.02, 0.02, 0.03])
    np.testing.assert_array_equal(p.drag_coeff, [1.0, 1.0, 1.2])
    assert p.drag_feedforward_gain == 0.8
    assert p.is_homogeneous and p.n_agents is None
    co = p.coefficients()
    np.testing.assert_allclose(co.drag_k[0], 0.5 * 1.225 * np.array([1.0 * 0.02, 1.0 * 0.02, 1.2 * 0.03]) / 1.0)
    np.testing.assert_allclose(co.accel_max, 2.2 * 9.81)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"mass_kg": -1.0}, "mass_kg"),
        ({"tilt_max_deg": 90.0}, "tilt_max_deg"),
        ({"drag_area_m2": (0.1, 0.2)}, "drag_area_m2"),
        ({"mass_kg": np.ones(3), "tau_v_s": np.ones(4)}, "tau_v_s"),
        ({"substeps": 0}, "substeps"),
        ({"max_substep_s": 0.0}, "max_substep_s"),
        ({"g": math.nan}, "g"),
    ],
)
def test_invalid_parameters_are_refused_naming_the_field(kwargs, message):
    with pytest.raises(ValueError, match=message):
        PlantParams(**kwargs)


def test_per_agent_parameter_count_must_match_the_fleet():
    with pytest.raises(ValueError, match="3 agents"):
        VelocityPlant(PlantParams(mass_kg=np.ones(3)), 4)


# --- equations and numerics ----------------------------------------------------------------------


def test_drag_opposes_airspeed_quadratically():
    k = PlantParams().coefficients().drag_k
    a = drag_accel(np.array([[2.0, -2.0, 4.0]]), k)[0]
    assert a[0] < 0 < a[1] and a[2] < 0
    np.testing.assert_allclose(a[:2], [-0.01225 * 4, 0.01225 * 4])
    np.testing.assert_allclose(drag_accel(np.array([[4.0, 0, 0]]), k)[0, 0], 4 * a[0])


def test_desired_thrust_compensates_gravity_and_feeds_forward_drag():
    p = PlantParams()
    a = desired_thrust_accel(np.array([[5.0, 0.0, 0.0]]), np.array([[5.0, 0.0, 0.0]]), p)[0]
    # at the commanded velocity: no shaping term, gravity compensation up, drag push forward
    np.testing.assert_allclose(a, [0.8 * 0.01225 * 25.0, 0.0, -G])
    a = desired_thrust_accel(np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0]]), p)[0]
    assert a[0] == pytest.approx(1.0 / 0.5 + 0.8 * 0.01225)


def test_constraint_keeps_feasible_thrust_and_bounds_the_rest():
    amax = 2.2 * G
    rng = np.random.default_rng(5)
    a = rng.normal(0.0, 30.0, (5000, 3))
    c = constrain_thrust_accel(a, amax, TAN55)
    assert np.all(tilt_deg(c) <= 55.0 + 1e-9)
    assert np.all(thrust_accel_norm(c) <= amax * (1 + 1e-12))
    assert np.all(c[:, 2] <= 0.0)  # rotor thrust never points down
    # horizontal direction preserved, only shortened
    h, hc = a[:, :2], c[:, :2]
    cross = h[:, 0] * hc[:, 1] - h[:, 1] * hc[:, 0]
    np.testing.assert_allclose(cross, 0.0, atol=1e-9)
    assert np.all(np.einsum("ij,ij->i", h, hc) >= -1e-12)
    assert np.all(np.linalg.norm(hc, axis=1) <= np.linalg.norm(h, axis=1) + 1e-12)
    # vertical priority: the clipped upward demand is kept exactly
    np.testing.assert_allclose(-c[:, 2], np.clip(-a[:, 2], 0.0, amax))
    feasible = np.array([[3.0, -2.0, -G], [0.0, 0.0, -G]])
    np.testing.assert_array_equal(constrain_thrust_accel(feasible, amax, TAN55), feasible)
    # thrust-limited: full vertical demand leaves only sqrt(amax^2 - up^2) horizontally
    c = constrain_thrust_accel(np.array([[100.0, 0.0, -20.0]]), amax, TAN55)[0]
    assert c[2] == -20.0 and c[0] == pytest.approx(math.sqrt(amax**2 - 400.0))


@pytest.mark.parametrize("backend", BACKENDS)
def test_vectorised_step_equals_the_single_agent_oracle(backend):
    p = PlantParams()
    rng, vel, thr, cmd, wind = random_state(40)
    wind_ff = rng.normal(0.0, 2.0, (40, 3))
    noise = rng.normal(0.0, 0.5, (40, 3))
    v, a = vel.copy(), thr.copy()
    ref = [(tuple(vel[i]), tuple(thr[i])) for i in range(40)]
    for _ in range(5):
        v, a = step_plant(v, a, cmd, 0.05, p, wind, wind_ff, noise, backend=backend)
        ref = [step_single_agent(ref[i][0], ref[i][1], cmd[i], 0.05, p, wind[i], wind_ff[i], noise[i]) for i in range(40)]
    np.testing.assert_allclose(v, [r[0] for r in ref], rtol=0, atol=1e-11)
    np.testing.assert_allclose(a, [r[1] for r in ref], rtol=0, atol=1e-11)


@pytest.mark.parametrize("backend", BACKENDS)
def test_heterogeneous_fleet_equals_each_agents_own_oracle(backend):
    n = 25
    p = hetero_params(n)
    _, vel, _, cmd, wind = random_state(n, seed=7)
    thr = trim_thrust_accel(vel, p)
    v, a = step_plant(vel, thr, cmd, 0.03, p, wind, backend=backend)
    v, a = step_plant(v, a, cmd, 0.03, p, wind, backend=backend)
    for i in range(n):
        pi = p.agent(i)
        r = step_single_agent(vel[i], thr[i], cmd[i], 0.03, pi, wind[i])
        r = step_single_agent(r[0], r[1], cmd[i], 0.03, pi, wind[i])
        np.testing.assert_allclose(v[i], r[0], atol=1e-11)
        np.testing.assert_allclose(a[i], r[1], atol=1e-11)


@needs(numba_available(), "numba", extra="jit")
def test_numba_and_numpy_kernels_agree():
    p = hetero_params(300)
    _, vel, thr, cmd, wind = random_state(300, seed=11, params=PlantParams())
    out_np = step_plant(vel, thr, cmd, 0.1, p, wind, backend="numpy")
    out_nb = step_plant(vel, thr, cmd, 0.1, p, wind, backend="numba")
    np.testing.assert_allclose(out_np[0], out_nb[0], atol=1e-12)
    np.testing.assert_allclose(out_np[1], out_nb[1], atol=1e-12)


@needs(numba_available(), "numba", extra="jit")
@pytest.mark.parametrize("n", [1, BLOCK - 1, BLOCK, 1000])
def test_compiled_kernel_reproduces_the_numpy_reference_bit_for_bit(n):
    """One kernel, the numpy path its reference: fleet-wide and per-agent rows, with and without
    wind/feed-forward/noise, per-agent and broadcast commands, whole and partial blocks of agents,
    the actuation limits active for part of the fleet: the same numbers, to the last bit."""
    rng, vel, thr, cmd, wind = random_state(n, seed=12)
    cmd[::3] *= 4.0  # drive part of the fleet into the tilt / thrust limits
    wind_ff, noise = rng.normal(0.0, 2.0, (n, 3)), rng.normal(0.0, 0.5, (n, 3))
    for p in (PlantParams(), hetero_params(n)):
        for c in (cmd, cmd[0]):
            for extra in ((), (wind,), (wind, wind_ff, noise), (wind[0], None, noise[0])):
                ref = step_plant(vel, thr, c, 0.05, p, *extra, backend="numpy")
                got = step_plant(vel, thr, c, 0.05, p, *extra, backend="numba")
                np.testing.assert_array_equal(got[0], ref[0])
                np.testing.assert_array_equal(got[1], ref[1])
    v, a = vel.copy(), thr.copy()
    step_plant(v, a, cmd, 0.05, PlantParams(), out=(v, a), backend="numba")  # in place
    zero = np.zeros(3)
    np.testing.assert_array_equal(v, step_plant(vel, thr, cmd, 0.05, PlantParams(), zero, zero, zero, backend="numba")[0])
    i = n - 1
    r = step_single_agent(vel[i], thr[i], cmd[i], 0.05, PlantParams())
    np.testing.assert_allclose(v[i], r[0], atol=1e-11)
    np.testing.assert_allclose(a[i], r[1], atol=1e-11)


def test_small_step_follows_the_continuous_derivatives():
    p = PlantParams()
    _, vel, thr, cmd, wind = random_state(50, seed=2)
    dv, da = plant_derivatives(vel, thr, cmd, p, wind)
    h = 1e-6
    v1, a1 = step_plant(vel, thr, cmd, h, p, wind, backend="numpy")
    np.testing.assert_allclose((a1 - thr) / h, da, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose((v1 - vel) / h, dv, rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_order_hold_one_long_step_equals_many_short_ones(backend):
    p = PlantParams()
    _, vel, thr, cmd, wind = random_state(30, seed=4)
    v_long, a_long = step_plant(vel, thr, cmd, 0.1, p, wind, backend=backend)
    assert substep_count(0.1, p) == 10
    v, a = vel, thr
    for _ in range(10):
        v, a = step_plant(v, a, cmd, 0.01, p, wind, backend=backend)
    np.testing.assert_allclose(v_long, v, atol=1e-12)
    np.testing.assert_allclose(a_long, a, atol=1e-12)


def test_sub_stepping_converges():
    _, vel, thr, cmd, _ = random_state(20, seed=6)
    results = [step_plant(vel, thr, cmd, 0.2, PlantParams(max_substep_s=h))[0] for h in (0.04, 0.02, 0.01, 0.005)]
    diffs = [np.abs(results[i] - results[i + 1]).max() for i in range(3)]
    assert diffs[0] > diffs[1] > diffs[2]  # first-order convergence: errors roughly halve
    assert diffs[2] < 0.5 * diffs[1] * 1.3


def test_substep_count_rule():
    p = PlantParams(substeps=3, max_substep_s=0.01)
    assert substep_count(0.01, p) == 3
    assert substep_count(0.05, p) == 5
    assert substep_count(0.0501, p) == 6


def test_step_plant_is_pure_unless_out_aliases_the_state():
    p = PlantParams()
    _, vel, thr, cmd, wind = random_state(10)
    vel0, thr0 = vel.copy(), thr.copy()
    v, a = step_plant(vel, thr, cmd, 0.02, p, wind)
    np.testing.assert_array_equal(vel, vel0)
    np.testing.assert_array_equal(thr, thr0)
    step_plant(vel, thr, cmd, 0.02, p, wind, out=(vel, thr))
    np.testing.assert_array_equal(vel, v)
    np.testing.assert_array_equal(thr, a)


def test_broadcast_wind_and_command_equal_repeated_rows():
    p = PlantParams()
    _, vel, thr, _, _ = random_state(8)
    a = step_plant(vel, thr, np.array([3.0, -1.0, 0.5]), 0.05, p, np.array([-4.0, 1.0, 0.0]))
    b = step_plant(vel, thr, np.tile([3.0, -1.0, 0.5], (8, 1)), 0.05, p, np.tile([-4.0, 1.0, 0.0], (8, 1)))
    np.testing.assert_array_equal(a[0], b[0])


def test_bad_shapes_are_refused():
    p = PlantParams()
    with pytest.raises(ValueError, match="cmd_ned_m_s"):
        step_plant(np.zeros((4, 3)), np.zeros((4, 3)), np.zeros((3, 3)), 0.01, p)
    with pytest.raises(ValueError, match="dt_s"):
        step_plant(np.zeros((4, 3)), np.zeros((4, 3)), np.zeros(3), 0.0, p)
    with pytest.raises(ValueError, match="vel_ned_m_s"):
        step_plant(np.zeros((4, 2)), np.zeros((4, 2)), np.zeros(3), 0.01, p)


def test_tailwind_at_the_commanded_speed_leaves_no_drag():
    p = PlantParams(drag_feedforward_gain=0.0)
    plant = VelocityPlant(p, 1, velocity_ned_m_s=[4.0, 0.0, 0.0])
    for _ in range(500):
        plant.step([4.0, 0.0, 0.0], 0.01, wind_ned_m_s=[4.0, 0.0, 0.0])
    np.testing.assert_allclose(plant.velocity[0], [4.0, 0.0, 0.0], atol=1e-9)


# --- the stateful wrapper -----------------------------------------------------------------------


def test_velocity_plant_starts_in_hover_trim():
    plant = VelocityPlant(PlantParams(), 3)
    np.testing.assert_array_equal(plant.velocity, np.zeros((3, 3)))
    np.testing.assert_array_equal(plant.thrust_accel, np.tile([0.0, 0.0, -G], (3, 1)))
    np.testing.assert_allclose(plant.thrust_to_weight_used(), 1.0)
    np.testing.assert_array_equal(plant.tilt_deg(), 0.0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_append_and_keep_preserve_each_agents_trajectory(backend):
    p = PlantParams()
    rng = np.random.default_rng(9)
    cmd = rng.normal(0, 5, (6, 3))
    whole = VelocityPlant(p, 6, backend=backend)
    part = VelocityPlant(p, 4, backend=backend)
    for _ in range(30):
        whole.step(cmd, 0.02)
        part.step(cmd[:4], 0.02)
    part.append(whole.velocity[4:].copy(), whole.thrust_accel[4:].copy())
    assert part.n_agents == 6
    keep = np.array([True, False, True, True, False, True])
    whole.keep(keep)
    part.keep(keep)
    for _ in range(30):
        whole.step(cmd[keep], 0.02)
        part.step(cmd[keep], 0.02)
    np.testing.assert_allclose(part.velocity, whole.velocity, atol=1e-12)
    np.testing.assert_allclose(part.thrust_accel, whole.thrust_accel, atol=1e-12)


def test_append_enters_agents_at_trim_and_heterogeneous_fleets_need_their_params():
    plant = VelocityPlant(PlantParams(), 0)
    plant.append(np.array([[5.0, 0.0, 0.0]]))
    np.testing.assert_allclose(plant.thrust_accel[0], [0.01225 * 25, 0.0, -G])
    for _ in range(100):
        plant.step([5.0, 0.0, 0.0], 0.01, wind_ned_m_s=None)
    # in trim at the commanded velocity with k_ff = 0.8 the velocity barely moves
    assert abs(plant.velocity[0, 0] - 5.0) < 0.05
    het = VelocityPlant(PlantParams(mass_kg=np.array([1.0, 2.0])), 2)
    with pytest.raises(ValueError, match="per-agent"):
        het.append(np.zeros((1, 3)))
    het.append(np.zeros((2, 3)), params=PlantParams(mass_kg=4.0))
    np.testing.assert_allclose(het.coefficients.drag_k[:, 0], 0.01225 / np.array([1.0, 2.0, 4.0, 4.0]))
    het.keep(np.array([3, 0]))
    np.testing.assert_allclose(het.coefficients.drag_k[:, 0], 0.01225 / np.array([4.0, 1.0]))
    # a homogeneous fleet joined by different agents becomes per-agent
    hom = VelocityPlant(PlantParams(), 2)
    hom.append(np.zeros((1, 3)), params=PlantParams(thrust_to_weight=3.0))
    np.testing.assert_allclose(hom.coefficients.accel_max, [2.2 * G, 2.2 * G, 3.0 * G])


def test_empty_fleet_steps():
    plant = VelocityPlant(PlantParams(), 0)
    assert plant.step(np.zeros((0, 3)), 0.01).shape == (0, 3)


# --- the paper's plant tests ---------------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
def test_single_axis_step_settles_like_the_paper_without_overshoot(backend):
    r = pc.check_single_axis_step(backend=backend)
    for ts in r.settling_time_s:  # paper: about 1.67 s
        assert 1.4 <= ts <= 2.0
        assert ts == pytest.approx(1.67, abs=0.05)
    assert max(r.overshoot_frac) < 0.01  # paper: no overshoot
    assert max(r.steady_state_error_m_s) < 0.005
    assert max(r.max_off_axis_m_s) < 1e-12
    assert r.analytic_settling_time_s == pytest.approx(1.68, abs=0.01)


def test_large_steps_stay_overshoot_free_and_settle():
    r = pc.check_single_axis_step(step_m_s=5.0)
    assert max(r.overshoot_frac) < 0.01
    assert all(1.4 <= ts <= 2.0 for ts in r.settling_time_s)


@pytest.mark.parametrize("backend", BACKENDS)
def test_hover_is_stable(backend):
    r = pc.check_hover(backend=backend)
    assert r.max_speed_from_trim_m_s == 0.0
    assert r.final_speed_from_perturbed_m_s < 1e-6
    assert r.max_speed_late_from_perturbed_m_s < 1e-6


def test_thrust_to_weight_sweep_common_max_speed_and_tilt_limit():
    r = pc.check_thrust_to_weight_sweep()
    assert max(r.peak_tilt_deg) <= 55.0 + 1e-9
    assert max(r.peak_thrust_frac) <= 1.0 + 1e-12
    # common maximum speed across the sweep (paper: near 7.48 m/s)
    assert max(r.max_speed_m_s) - min(r.max_speed_m_s) < 0.01
    assert r.max_speed_m_s[0] == pytest.approx(7.48, abs=0.1)
    # attitude is the active constraint once T/W > 1/cos(55 deg) = 1.74
    assert r.active_constraint == ("thrust",) + ("tilt",) * 6
    assert all(t > 45.0 for t in r.peak_tilt_deg)


def test_terminal_speed_is_the_drag_limit_at_the_tilt_or_thrust_bound():
    r = pc.check_thrust_to_weight_sweep(thrust_to_weight=(1.5, 2.2, 6.0), cmd_speed_m_s=60.0, duration_s=40.0)
    k = 0.5 * 1.225 * 1.0 * 0.02
    assert r.tilt_limited_speed_m_s == pytest.approx(math.sqrt(G * TAN55 / k))
    assert r.max_speed_m_s[0] == pytest.approx(math.sqrt(G * math.sqrt(1.5**2 - 1) / k), rel=0.01)
    assert r.max_speed_m_s[1] == pytest.approx(r.tilt_limited_speed_m_s, rel=0.01)
    assert r.max_speed_m_s[2] == pytest.approx(r.tilt_limited_speed_m_s, rel=0.01)
    assert r.peak_tilt_deg[1] == pytest.approx(55.0, abs=0.05)
    assert max(r.peak_tilt_deg) <= 55.0 + 1e-9


@pytest.mark.parametrize("backend", BACKENDS)
def test_headwind_steady_state_error_with_feedforward(backend):
    r = pc.check_headwind(backend=backend)
    p = PlantParams()
    for w, e_still, e_aware, e_none in zip(
        r.headwind_m_s, r.error_still_air_ff_m_s, r.error_wind_aware_ff_m_s, r.error_no_ff_m_s
    ):
        assert e_still == pytest.approx(pc.steady_state_error_m_s(p, 5.0, -w, 0.0), abs=1e-3)
        assert e_aware == pytest.approx(pc.steady_state_error_m_s(p, 5.0, -w, -w), abs=1e-3)
        assert 0.0 < e_aware <= e_still < e_none
    assert np.all(np.diff(r.error_wind_aware_ff_m_s) > 0)
    # still air: inside the paper's 0.01..0.06 m/s band
    assert 0.01 <= r.error_still_air_ff_m_s[0] <= 0.06
    # wind-aware feed-forward k_ff = 0.8 leaves (1 - k_ff) of the drag at airspeed a = 13 m/s:
    # e ~ tau_v (1 - k_ff) k a^2 / (1 + 2 tau_v k a) to first order in e
    tv, k, air = 0.5, 0.01225, 13.0
    assert r.error_wind_aware_ff_m_s[-1] == pytest.approx(tv * 0.2 * k * air**2 / (1 + 2 * tv * k * air), rel=0.01)


def test_monte_carlo_noise_is_seeded_and_raises_rmse():
    kw = dict(noise_rms_m_s=(0.0, 0.25, 0.5), runs=6)
    a = pc.check_noise(kind="process", seed=3, **kw)
    assert a == pc.check_noise(kind="process", seed=3, **kw)
    assert a != pc.check_noise(kind="process", seed=4, **kw)
    assert a.rmse_lateral_m_s[0] == pc.check_noise(kind="measurement", seed=3, **kw).rmse_lateral_m_s[0]
    assert np.all(np.diff(a.rmse_lateral_m_s) > 0) and np.all(np.diff(a.rmse_vertical_m_s) > 0)
    # process noise of 0.5 m/s per 0.01 s adds about 2-4 m/s RMS (paper: +2.4 lateral, +2.0 vertical)
    added = math.sqrt(a.rmse_vertical_m_s[-1] ** 2 - a.rmse_vertical_m_s[0] ** 2)
    assert 1.5 < added < 4.0
    # measurement noise is low-pass filtered by the 0.38 Hz loop: almost no effect
    m = pc.check_noise(kind="measurement", seed=3, **kw)
    assert m.rmse_lateral_m_s[-1] < 1.02 * m.rmse_lateral_m_s[0]
    assert m.rmse_lateral_m_s[-1] > m.rmse_lateral_m_s[0]


def test_aggressive_manoeuvre_tracks_all_axes_and_feedforward_helps_cruise():
    r = pc.check_race(feedforward_gain=(0.0, 0.8, 1.0))
    assert r.cruise_error_m_s[0] > r.cruise_error_m_s[1] > r.cruise_error_m_s[2]
    assert r.cruise_error_m_s[2] < 0.02
    assert max(r.rmse_lateral_m_s) < 3.5 and max(r.rmse_vertical_m_s) < 1.2
    assert max(r.peak_tilt_deg) <= 55.0 + 1e-9 and max(r.peak_tilt_deg) > 54.0  # limit reached, not crossed
    assert max(r.peak_thrust_frac) <= 1.0 + 1e-12
    assert max(r.final_speed_m_s) < 0.05


@pytest.mark.parametrize("backend", BACKENDS)
def test_constraints_never_violated_under_random_commands(backend):
    r = pc.check_constraints(agents=300, steps=150, seed=21, backend=backend)
    assert r.max_tilt_excess_deg <= 1e-9
    assert r.max_thrust_excess_frac <= 1e-12
    assert r.max_tilt_deg > 60.0  # the random envelope did hit the (per-agent) limits


def test_cross_axis_coupling_is_small():
    r = pc.check_coupling()
    assert r.max_y_from_hover_m_s < 1e-12 and r.max_z_from_hover_m_s < 1e-12
    assert r.max_y_dev_while_cruising_m_s < 0.05


def test_frequency_response_matches_the_linearised_loop():
    r = pc.check_frequency_response()
    np.testing.assert_allclose(r.gain, r.model_gain, rtol=0.03)
    np.testing.assert_allclose(r.phase_deg, r.model_phase_deg, atol=3.0)
    assert r.bandwidth_hz == pytest.approx(r.model_bandwidth_hz, rel=0.05)
    # the thrust lag moves the closed-loop poles to -2.5 and -10 rad/s: bandwidth a bit above 1/(2 pi tau_v)
    assert r.first_order_bandwidth_hz < r.model_bandwidth_hz < 1.3 * r.first_order_bandwidth_hz


def test_heterogeneous_fleet_behaves_per_agent():
    p = PlantParams(tau_v_s=np.array([0.25, 0.5, 1.0]))
    n_t = 600
    run = pc.simulate(p, np.tile([1.0, 0.0, 0.0], (n_t, 3, 1)))
    ts = [pc.settling_time_s(run.t_s, run.vel_ned_m_s[:, i, 0], 1.0, 1.0) for i in range(3)]
    assert ts[0] < ts[1] < ts[2]
    assert ts[1] == pytest.approx(pc.second_order_settling_time_s(PlantParams()), abs=0.03)


def test_docs_table_is_what_the_checks_measure():
    """docs/plant.md carries the table ``python -m sim.plant.checks`` prints (regenerate it when
    the plant changes)."""
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[2] / "docs" / "plant.md").read_text(encoding="utf-8")
    for row in pc.report_markdown().splitlines():
        assert row in doc, f"docs/plant.md is stale; row not found: {row}"


# --- wind ------------------------------------------------------------------------------------------


def test_gusts_have_the_requested_rms_and_correlation():
    from sim.wind import GustWind, WindParams

    wp = WindParams(mean_wind_ned_m_s=(-3.0, 1.0, 0.0), turbulence_rms_m_s=(1.0, 0.5, 0.2), correlation_time_s=1.0)
    wind = GustWind(wp, 4000, np.random.default_rng(0))
    w0 = wind.wind_ned_m_s.copy()
    w1 = wind.step(0.5)
    np.testing.assert_allclose(w1.mean(axis=0), [-3.0, 1.0, 0.0], atol=0.05)
    np.testing.assert_allclose(w1.std(axis=0), [1.0, 0.5, 0.2], rtol=0.05)
    g0, g1 = w0 - wp.mean_wind_ned_m_s, w1 - wp.mean_wind_ned_m_s
    corr = (g0 * g1).mean(axis=0) / (g0.std(axis=0) * g1.std(axis=0))
    np.testing.assert_allclose(corr, math.exp(-0.5), atol=0.04)
    wind.append(10)
    wind.keep(np.arange(4010) % 2 == 0)
    assert wind.wind_ned_m_s.shape == (2005, 3)
    a = GustWind(wp, 5, np.random.default_rng(7)).step(0.1)
    np.testing.assert_array_equal(a, GustWind(wp, 5, np.random.default_rng(7)).step(0.1))
    with pytest.raises(ValueError, match="correlation_time_s"):
        WindParams(correlation_time_s=0.0)


def test_plant_flies_through_gusts_within_its_limits():
    from sim.wind import GustWind, WindParams

    wind = GustWind(WindParams((-4.0, 0.0, 0.0), (2.0, 2.0, 1.0), 0.5), 200, np.random.default_rng(1))
    plant = VelocityPlant(PlantParams(), 200)
    errs = []
    for _ in range(1000):
        plant.step([5.0, 0.0, 0.0], 0.01, wind.step(0.01))
        assert plant.tilt_deg().max() <= 55.0 + 1e-9
        errs.append(np.abs(plant.velocity - [5.0, 0.0, 0.0]).mean())
    assert np.mean(errs[500:]) < 0.3
