"""Specification of the swarm-field estimators Q (paper section "Swarm-Domain Primitive Variables").

The hand cases use cubic CVs of edge l = 0.5 m (dV = 0.125 m^3) and these agents:
  A: CV 0, v = (2, 0, 0)    B: CV 0, v = (4, 0, 2)    C: CV 1, v = (1, 1, 0)
  D: outside the map (cv -1), v = (100, 0, 0) -- must be ignored.
"""

import numpy as np
import pytest

from fisc_ground.fields.swarm_equations import SwarmGasParams, interagent_spacing, sound_speed
from fisc_ground.fields.swarm_fields import FieldAccumulator, cv_moments, instantaneous_fields

DV = 0.125
IDS = np.array([0, 0, 1, -1])
VEL = np.array([[2.0, 0, 0], [4.0, 0, 2.0], [1.0, 1.0, 0], [100.0, 0, 0]])
REF = np.array([[3.0, 0, 0], [1.0, 0, 0]])


def test_hand_case_velocity_density_pressures():
    f = instantaneous_fields(IDS, VEL, 1.0, n_cv=2, cell_volume_m3=DV, reference_velocity_m_s=REF)
    # counts and mass: D is ignored
    np.testing.assert_array_equal(f.count, [2, 1])
    np.testing.assert_array_equal(f.samples, [2, 1])
    np.testing.assert_allclose(f.mass_kg, [2, 1])
    # eq. swarm_velocity: CV0 momentum (6,0,2)/M=2 -> U=(3,0,1), projected on +x -> 3
    np.testing.assert_allclose(f.mean_velocity_m_s, [[3, 0, 1], [1, 1, 0]])
    np.testing.assert_allclose(f.u_axial_m_s, [3, 1])
    np.testing.assert_allclose(f.u_s_m_s, [[3, 0, 0], [1, 0, 0]])
    # eq. swarm_density: m N / dV = 2/0.125 = 16, 1/0.125 = 8
    np.testing.assert_allclose(f.rho_s_kg_m3, [16, 8])
    np.testing.assert_allclose(f.number_density_per_m3, [16, 8])
    # eq. swarm_pressure: 2/(3 dV) sum m|v|^2: CV0 sum = 4 + 20 = 24 -> 48/0.375 = 128; CV1 sum 2 -> 10.667
    np.testing.assert_allclose(f.p_s_pa, [128, 4 / 0.375])
    # eq. internal_pressure: |v - u_s|^2: A (-1,0,0)->1, B (1,0,2)->5, mean 3 -> 2/3*16*3 = 32;
    # CV1 (0,1,0) -> 1 -> 2/3*8 = 16/3
    np.testing.assert_allclose(f.p_internal_pa, [32, 16 / 3])
    # eq. pressure_constraint: CV0 |v - (3,0,0)|^2 = 1 + 5 = 6 -> 12/0.375 = 32; CV1 |(0,1,0)|^2 -> 2/0.375
    np.testing.assert_allclose(f.p_dispersion_pa, [32, 2 / 0.375])


def test_hand_case_temperature_and_sound_speed():
    p = SwarmGasParams(k_b_s=1.0, c_v_s=1.0, gamma_s=1.4, lambda_ctrl=0.5, a_max_m_s2=8.0)
    f = instantaneous_fields(IDS, VEL, 1.0, n_cv=2, cell_volume_m3=DV, params=p)
    # eq. temperature_random: U=(3,0,1); |A-U|^2 = 2, |B-U|^2 = 2 -> 4 / (2*2) = 1; single agent -> 0
    np.testing.assert_allclose(f.t_rand_m2_s2, [1.0, 0.0], atol=1e-12)
    # L_c = n^(-1/3) with n = 16 and 8 per m^3 -> 16^(-1/3), 0.5
    np.testing.assert_allclose(f.spacing_m, [16 ** (-1 / 3), 0.5])
    # T_ctrl = lambda a_max L_c / c_v = 0.5 * 8 * L_c
    np.testing.assert_allclose(f.t_ctrl_m2_s2, [4 * 16 ** (-1 / 3), 2.0])
    np.testing.assert_allclose(f.t_s_m2_s2, f.t_rand_m2_s2 + f.t_ctrl_m2_s2)
    # c^2 = gamma R T, R = c_p - c_v = 0.4
    np.testing.assert_allclose(f.sound_speed_m_s ** 2, 1.4 * 0.4 * f.t_s_m2_s2)
    assert np.isnan(f.p_dispersion_pa).all()  # no reference velocity given


def test_sound_speed_dispersion_term_and_constitutive_params():
    p = SwarmGasParams(gamma_s=1.4, c_v_s=2.0, omega_rad_s=10.0, tau_s=0.1)
    assert p.c_p_s == pytest.approx(2.8)
    assert p.r_s == pytest.approx(0.8)
    # 1 + (omega tau)^2 = 2
    np.testing.assert_allclose(sound_speed(np.array([5.0]), p) ** 2, 1.4 * 0.8 * 5.0 / 2.0)


def test_default_params_documented_values():
    p = SwarmGasParams()
    assert (p.k_b_s, p.c_v_s, p.gamma_s, p.lambda_ctrl) == (1.0, 1.0, 1.4, 0.5)
    assert p.a_max_m_s2 == pytest.approx(1.2 * 9.81)
    with pytest.raises(ValueError, match="lambda_ctrl"):
        SwarmGasParams(lambda_ctrl=1.5)


def test_heterogeneous_masses_are_mass_weighted():
    # A (m=1) and B (m=3) in CV0: momentum (2+12, 0, 6) / M=4 -> U = (3.5, 0, 1.5)
    f = instantaneous_fields(IDS, VEL, np.array([1.0, 3.0, 1.0, 1.0]), n_cv=2, cell_volume_m3=DV)
    np.testing.assert_allclose(f.u_axial_m_s, [3.5, 1.0])
    np.testing.assert_allclose(f.rho_s_kg_m3, [32.0, 8.0])
    np.testing.assert_allclose(f.count, [2, 1])
    # P_s with masses: (1*4 + 3*20) * 2/(3 dV) = 64/0.1875
    np.testing.assert_allclose(f.p_s_pa[0], 64 * 2 / (3 * DV))
    # L_c uses the number density (2 agents / dV), not the mass density
    np.testing.assert_allclose(f.spacing_m[0], 16 ** (-1 / 3))


def test_per_cv_drift_direction_is_normalised():
    dirs = np.array([[1.0, 0, 0], [0, 2.0, 0]])
    f = instantaneous_fields(IDS, VEL, 1.0, n_cv=2, cell_volume_m3=DV, drift_dir=dirs)
    np.testing.assert_allclose(f.u_axial_m_s, [3.0, 1.0])
    np.testing.assert_allclose(f.u_s_m_s[1], [0, 1, 0])
    with pytest.raises(ValueError, match="drift_dir"):
        instantaneous_fields(IDS, VEL, 1.0, n_cv=2, cell_volume_m3=DV, drift_dir=np.zeros(3))


def test_empty_cv_conventions():
    f = instantaneous_fields(np.array([0]), np.array([[1.0, 0, 0]]), 1.0, n_cv=2, cell_volume_m3=DV)
    assert f.count[1] == 0 and f.rho_s_kg_m3[1] == 0 and f.p_s_pa[1] == 0 and f.p_internal_pa[1] == 0
    assert np.isnan(f.u_axial_m_s[1]) and np.isnan(f.t_s_m2_s2[1]) and np.isnan(f.spacing_m[1])


def test_invalid_inputs_are_named():
    with pytest.raises(ValueError, match="cv_ids contains 5"):
        cv_moments(np.array([5]), np.zeros((1, 3)), 1.0, n_cv=2)
    with pytest.raises(ValueError, match="velocities"):
        cv_moments(np.array([0, 1]), np.zeros((3, 3)), 1.0, n_cv=2)
    with pytest.raises(ValueError, match="reference_velocity"):
        cv_moments(np.array([0]), np.zeros((1, 3)), 1.0, n_cv=2, reference_velocity_m_s=np.zeros((1, 3)))
    with pytest.raises(ValueError, match="masses"):
        cv_moments(np.array([0]), np.zeros((1, 3)), 0.0, n_cv=2)


def test_time_average_hand_case():
    # sample 1: A in CV0 at (2,0,0); sample 2: A (4,0,0) and B (0,0,0) in CV0; CV1 always empty
    acc = FieldAccumulator(2, DV)
    acc.add(np.array([0]), np.array([[2.0, 0, 0]]), 1.0)
    acc.add(np.array([0, 0]), np.array([[4.0, 0, 0], [0.0, 0, 0]]), 1.0)
    f = acc.result()
    assert f.n_time_samples == 2
    np.testing.assert_array_equal(f.samples, [3, 0])
    np.testing.assert_allclose(f.count, [1.5, 0])
    # density = mean of instantaneous (8, 16) = total mass 3 / (2 dV) = 12
    np.testing.assert_allclose(f.rho_s_kg_m3, [12, 0])
    # velocity mass-weighted over all samples: (2 + 4 + 0)/3 = 2
    np.testing.assert_allclose(f.u_axial_m_s[0], 2.0)
    assert np.isnan(f.u_axial_m_s[1])
    # P_s = mean of instantaneous (4, 16) * 2/(3 dV) = 10 * 2/0.375
    np.testing.assert_allclose(f.p_s_pa[0], 10 * 2 / (3 * DV))
    # pooled T_rand about U = 2: (0 + 4 + 4) / (2 * 3) = 4/3
    np.testing.assert_allclose(f.t_rand_m2_s2[0], 4 / 3)


def test_dispersion_pressure_averaged_over_referenced_samples():
    acc = FieldAccumulator(2, DV)
    acc.add(np.array([0]), np.array([[2.0, 0, 0]]), 1.0, reference_velocity_m_s=REF)  # |(-1,0,0)|^2 = 1
    acc.add(np.array([0]), np.array([[5.0, 0, 0]]), 1.0, reference_velocity_m_s=REF)  # |(2,0,0)|^2 = 4
    np.testing.assert_allclose(acc.result().p_dispersion_pa, [2.5 * 2 / (3 * DV), 0.0])


def _naive_fields(ids, vel, m, n_cv, dv):
    """Loop reference implementation (the paper's sums written out literally)."""
    out = {k: np.full(n_cv, np.nan) for k in ("u", "rho", "ps", "pint", "trand")}
    for j in range(n_cv):
        sel = ids == j
        if not sel.any():
            continue
        mj, vj = m[sel], vel[sel]
        M = mj.sum()
        u = (mj * vj[:, 0]).sum() / M
        U = (mj[:, None] * vj).sum(0) / M
        rho = M / dv
        out["u"][j] = u
        out["rho"][j] = rho
        out["ps"][j] = 2 / (3 * dv) * (mj * (vj ** 2).sum(1)).sum()
        us = np.array([u, 0, 0])
        out["pint"][j] = 2 / 3 * rho * (mj * ((vj - us) ** 2).sum(1)).sum() / M
        out["trand"][j] = (mj * ((vj - U) ** 2).sum(1)).sum() / (2 * M)
    return out


def test_vectorised_matches_literal_sums_on_random_swarm():
    rng = np.random.default_rng(3)
    n, n_cv = 300, 17
    ids = rng.integers(-1, n_cv, n)
    vel = rng.normal(size=(n, 3)) * 2 + [3, 0, 0]
    m = rng.uniform(0.5, 2.0, n)
    f = instantaneous_fields(ids, vel, m, n_cv, DV)
    ref = _naive_fields(ids, vel, m, n_cv, DV)
    occupied = np.isfinite(ref["u"])
    np.testing.assert_allclose(f.u_axial_m_s[occupied], ref["u"][occupied])
    np.testing.assert_allclose(f.rho_s_kg_m3[occupied], ref["rho"][occupied])
    np.testing.assert_allclose(f.p_s_pa[occupied], ref["ps"][occupied])
    np.testing.assert_allclose(f.p_internal_pa[occupied], ref["pint"][occupied])
    np.testing.assert_allclose(f.t_rand_m2_s2[occupied], ref["trand"][occupied])


def test_single_sample_accumulator_equals_instantaneous_and_state_roundtrip_and_merge():
    rng = np.random.default_rng(7)
    n_cv = 5
    batches = [(rng.integers(-1, n_cv, 40), rng.normal(size=(40, 3)), rng.uniform(0.8, 1.2, 40)) for _ in range(4)]
    ref = rng.normal(size=(n_cv, 3))

    one = FieldAccumulator(n_cv, DV)
    one.add(*batches[0], reference_velocity_m_s=ref)
    inst = instantaneous_fields(*batches[0], n_cv, DV, reference_velocity_m_s=ref)
    for name, arr in inst.as_arrays().items():
        np.testing.assert_allclose(getattr(one.result(), name), arr, err_msg=name)

    full = FieldAccumulator(n_cv, DV)
    first, second = FieldAccumulator(n_cv, DV), FieldAccumulator(n_cv, DV)
    for i, b in enumerate(batches):
        full.add(*b, reference_velocity_m_s=ref)
        (first if i < 2 else second).add(*b, reference_velocity_m_s=ref)
    first.merge(second)
    replay = FieldAccumulator.from_state({k: v.copy() for k, v in full.state().items()})
    for other in (first, replay):
        for name, arr in full.result().as_arrays().items():
            np.testing.assert_allclose(getattr(other.result(), name), arr, err_msg=name)


def test_interagent_spacing():
    np.testing.assert_allclose(interagent_spacing(np.array([8.0, 1.0, 0.0])), [0.5, 1.0, np.nan])


def test_per_cv_effective_volume_scales_density_and_pressures_per_cv():
    """Eq. swarm_density with A_j dx_j per CV: a CV half outside the tunnel (volume dV/2) reads
    twice the density and sum-pressures of the same agents in a full CV; means are unchanged."""
    vol = np.array([DV, DV / 2])
    full = instantaneous_fields(IDS, VEL, 1.0, n_cv=2, cell_volume_m3=DV, reference_velocity_m_s=REF)
    eff = instantaneous_fields(IDS, VEL, 1.0, n_cv=2, cell_volume_m3=vol, reference_velocity_m_s=REF)
    np.testing.assert_allclose(eff.rho_s_kg_m3, [16, 16])
    np.testing.assert_allclose(eff.number_density_per_m3, [16, 16])
    for name in ("p_s_pa", "p_internal_pa", "p_dispersion_pa"):
        np.testing.assert_allclose(getattr(eff, name), getattr(full, name) * [1, 2], err_msg=name)
    np.testing.assert_allclose(eff.u_axial_m_s, full.u_axial_m_s)
    np.testing.assert_allclose(eff.t_rand_m2_s2, full.t_rand_m2_s2)
    acc = FieldAccumulator(2, vol)
    acc.add(IDS, VEL, 1.0, REF)
    np.testing.assert_allclose(acc.result().rho_s_kg_m3, eff.rho_s_kg_m3)
    back = FieldAccumulator.from_state(acc.state())
    np.testing.assert_allclose(back.result().p_dispersion_pa, eff.p_dispersion_pa)
    with pytest.raises(ValueError, match="merge"):
        acc.merge(FieldAccumulator(2, DV))


def test_per_cv_volume_must_match_n_cv_and_be_positive():
    with pytest.raises(ValueError, match=r"\(2,\)"):
        FieldAccumulator(2, np.array([DV, DV, DV]))
    with pytest.raises(ValueError, match=r"cell_volume_m3\[1\]"):
        instantaneous_fields(IDS, VEL, 1.0, n_cv=2, cell_volume_m3=np.array([DV, 0.0]))


# ------------------------------------------------------------------ boundaries (issue 38)
import re  # noqa: E402

from fisc_ground.fields.swarm_fields import drift_directions, fields_from_moments  # noqa: E402


def _refused(message, fn, *args, **kw):
    with pytest.raises(ValueError, match="^" + re.escape(message) + "$"):
        fn(*args, **kw)


def test_agent_ids_and_masses_at_their_limits():
    v1 = np.zeros((1, 3))
    assert cv_moments(np.array([1]), v1, 1.0, n_cv=2).count.tolist() == [0.0, 1.0]  # the last CV
    _refused("cv_ids contains 2, but n_cv is 2", cv_moments, np.array([2]), v1, 1.0, n_cv=2)  # one past it
    assert cv_moments(np.array([-1]), v1, 1.0, n_cv=2).count.tolist() == [0.0, 0.0]  # outside the map
    _refused("cv_ids contains -2; only -1 (outside the map) may be negative", cv_moments, np.array([-2]), v1, 1.0, n_cv=2)
    _refused("cv_ids must be a 1-D array, got shape (1, 1)", cv_moments, np.array([[0]]), v1, 1.0, n_cv=2)
    _refused("cv_ids must be integers, got dtype float64", cv_moments, np.array([0.0]), v1, 1.0, n_cv=2)
    _refused("masses must be a scalar or an (1,) array, got shape (2,)", cv_moments, np.array([0]), v1,
             np.ones(2), n_cv=2)
    for bad in (0.0, -1.0, np.nan):
        _refused("masses must be finite and > 0", cv_moments, np.array([0]), v1, bad, n_cv=2)
    _refused("velocities of agents inside the map must be finite", cv_moments, np.array([0]),
             np.array([[np.nan, 0.0, 0.0]]), 1.0, n_cv=2)
    assert cv_moments(np.array([-1]), np.array([[np.nan, 0.0, 0.0]]), 1.0, n_cv=2).count.sum() == 0  # outside: ignored


def test_drift_directions_at_their_limits():
    np.testing.assert_array_equal(drift_directions(None, 2), [[1.0, 0.0, 0.0]] * 2)
    np.testing.assert_array_equal(drift_directions([0.0, 0.0, 2e-12], 1), [[0.0, 0.0, 1.0]])  # tiny but > 1e-12
    _refused("drift_dir contains a zero or non-finite direction", drift_directions, [1e-12, 0.0, 0.0], 1)
    _refused("drift_dir contains a zero or non-finite direction", drift_directions, [np.inf, 0.0, 0.0], 1)
    _refused("drift_dir must be (3,) or (2, 3), got shape (2,)", drift_directions, [1.0, 0.0], 2)


def test_accumulator_arguments_and_errors():
    assert FieldAccumulator(0, 1.0).n_cv == 0  # an empty map is allowed
    _refused("n_cv must be >= 0, got -1", FieldAccumulator, -1, 1.0)
    params = SwarmGasParams(k_b_s=2.5)
    acc = FieldAccumulator(2, 1.0, drift_dir=[0.0, 3.0, 0.0], params=params)
    assert acc.params is params and FieldAccumulator(2, 1.0).params == SwarmGasParams()
    np.testing.assert_array_equal(acc.drift_dir, [[0.0, 1.0, 0.0]] * 2)
    back = FieldAccumulator.from_state(acc.state(), params)
    assert back.params is params
    np.testing.assert_array_equal(back.drift_dir, acc.drift_dir)
    _refused("moments of 3 CVs added to an accumulator of 2", acc.add_moments,
             cv_moments(np.array([0]), np.zeros((1, 3)), 1.0, n_cv=3))
    _refused("merge: accumulators differ in n_cv or cell volume", acc.merge, FieldAccumulator(2, 2.0))


def test_the_random_temperature_uses_the_boltzmann_like_constant_and_samples_are_integers():
    mom = cv_moments(np.array([0, 0]), np.array([[1.0, 0, 0], [3.0, 0, 0]]), 1.0, n_cv=1)
    t1 = fields_from_moments(mom, 1.0, params=SwarmGasParams(k_b_s=1.0))
    t2 = fields_from_moments(mom, 1.0, params=SwarmGasParams(k_b_s=2.0))
    assert t2.t_rand_m2_s2[0] == pytest.approx(2.0 * t1.t_rand_m2_s2[0]) and t1.t_rand_m2_s2[0] > 0
    assert t1.samples.dtype == np.int64 and t1.samples.tolist() == [2]
    given = fields_from_moments(mom, 1.0, samples=np.array([7.0]))
    assert given.samples.dtype == np.int64 and given.samples.tolist() == [7]


def test_a_sample_that_leaves_the_last_cvs_empty_adds_nothing_to_them():
    """Every moment has one row per CV even when the highest CVs hold nobody; the accumulator
    must not spread CV 0's momentum over CVs that were empty in that sample."""
    mom = cv_moments(np.array([0]), np.array([[2.0, 4.0, 6.0]]), 0.5, n_cv=3)
    np.testing.assert_array_equal(mom.momentum_kg_m_s, [[1.0, 2.0, 3.0], [0, 0, 0], [0, 0, 0]])
    outside = cv_moments(np.array([-1]), np.zeros((1, 3)), 1.0, n_cv=2)  # nobody inside: still 2 rows
    np.testing.assert_array_equal(outside.momentum_kg_m_s, np.zeros((2, 3)))
    acc = FieldAccumulator(2, DV)
    acc.add(np.array([0]), np.array([[2.0, 0, 0]]), 1.0)   # CV 1 empty in this sample
    acc.add(np.array([1]), np.array([[-1.0, 0, 0]]), 1.0)  # then one agent at -1 m/s
    np.testing.assert_array_equal(acc.momentum_kg_m_s, [[2.0, 0, 0], [-1.0, 0, 0]])
    np.testing.assert_allclose(acc.result().u_axial_m_s, [2.0, -1.0])


def test_result_uses_the_accumulators_own_drift_direction_and_parameters():
    params = SwarmGasParams(k_b_s=2.5, a_max_m_s2=7.0)
    acc = FieldAccumulator(2, DV, drift_dir=[0.0, 2.0, 0.0], params=params)
    acc.add(IDS, VEL, 1.0)
    got = acc.result()
    want = instantaneous_fields(IDS, VEL, 1.0, n_cv=2, cell_volume_m3=DV, drift_dir=[0.0, 1.0, 0.0], params=params)
    for name, arr in want.as_arrays().items():
        np.testing.assert_allclose(getattr(got, name), arr, err_msg=name)
    np.testing.assert_allclose(got.u_axial_m_s, [0.0, 1.0])  # projected on +y, not the default +x
    default = instantaneous_fields(IDS, VEL, 1.0, n_cv=2, cell_volume_m3=DV, drift_dir=[0.0, 1.0, 0.0])
    assert got.t_rand_m2_s2[0] == pytest.approx(2.5 / SwarmGasParams().k_b_s * default.t_rand_m2_s2[0])
    assert not np.allclose(got.t_ctrl_m2_s2[0], default.t_ctrl_m2_s2[0])  # a_max is the accumulator's


def test_result_before_any_referenced_sample_divides_nothing_by_zero():
    import warnings
    acc = FieldAccumulator(2, DV)
    acc.add(IDS, VEL, 1.0)  # no reference velocity: no dispersion moment
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # 0/0 would warn (RuntimeWarning: invalid value)
        f = acc.result()
    assert np.isnan(f.p_dispersion_pa).all()


def test_from_state_refuses_a_bad_state_naming_the_array_or_key():
    acc = FieldAccumulator(2, DV)
    acc.add(IDS, VEL, 1.0, REF)
    state = acc.state()
    _refused("state array 'mass_kg' has shape (3,), expected (2,)", FieldAccumulator.from_state,
             {**state, "mass_kg": np.zeros(3)})
    _refused("state array 'momentum_kg_m_s' has shape (2,), expected (2, 3)", FieldAccumulator.from_state,
             {**state, "momentum_kg_m_s": np.zeros(2)})
    for key in ("drift_dir", "m_dev2_kg_m2_s2", "n_ref_samples"):
        _refused(f"accumulator state lacks {key!r}", FieldAccumulator.from_state,
                 {k: v for k, v in state.items() if k != key})


def test_from_state_of_integer_sums_keeps_accumulating_in_floats():
    """A state written as integers (a JSON replay of whole counts and masses) must take further
    fractional samples, not fail on an integer array."""
    state = {"count": [2, 1], "mass_kg": [2, 1], "momentum_kg_m_s": [[6, 0, 2], [1, 1, 0]],
             "m_v2_kg_m2_s2": [24, 2], "m_dev2_kg_m2_s2": [0, 0], "n_time_samples": 1, "n_ref_samples": 0,
             "cell_volume_m3": DV, "drift_dir": [1, 0, 0]}
    acc = FieldAccumulator.from_state(state)
    assert all(getattr(acc, name).dtype == np.float64 for name in FieldAccumulator._SUMS)
    acc.add(np.array([1]), np.array([[0.5, 0, 0]]), 0.25)
    np.testing.assert_allclose(acc.mass_kg, [2.0, 1.25])
    np.testing.assert_allclose(acc.momentum_kg_m_s, [[6, 0, 2], [1.125, 1, 0]])
    np.testing.assert_allclose(acc.result().count, [1.0, 1.0])
