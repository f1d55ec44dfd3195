"""The "ours vs the paper" table of docs/plant.md from every check; ``python -m sim.plant.checks``."""

from __future__ import annotations

import argparse

from sim.plant.model import Backend
from sim.plant.checks.steps import check_headwind, check_hover, check_single_axis_step, check_thrust_to_weight_sweep
from sim.plant.checks.robustness import check_noise, check_race
from sim.plant.checks.frequency import check_constraints, check_coupling, check_frequency_response


def _fmt(xs, spec: str = ".3f") -> str:
    return ", ".join(format(x, spec) for x in xs)


def report_markdown(backend: Backend = "auto") -> str:
    """Run every check with its defaults and return the "ours vs the paper" markdown table."""
    st = check_single_axis_step(backend=backend)
    st5 = check_single_axis_step(step_m_s=5.0, backend=backend)
    hv = check_hover(backend=backend)
    sw = check_thrust_to_weight_sweep(backend=backend)
    big = check_thrust_to_weight_sweep(cmd_speed_m_s=60.0, duration_s=40.0, backend=backend)
    hw = check_headwind(backend=backend)
    rc = check_race(backend=backend)
    nz = check_noise(backend=backend)
    nzp = check_noise(kind="process", backend=backend)
    cp = check_coupling(backend=backend)
    fr = check_frequency_response(backend=backend)
    cs = check_constraints(backend=backend)
    rows = [
        ("Single-axis step: 2 % settling time", "about 1.67 s",
         f"x/y/z {_fmt(st.settling_time_s, '.2f')} s (1 m/s step); {_fmt(st5.settling_time_s, '.2f')} s (5 m/s); "
         f"linear model {st.analytic_settling_time_s:.2f} s"),
        ("Single-axis step: overshoot", "none",
         f"{max(st.overshoot_frac) * 100:.2f} % (1 m/s), {max(st5.overshoot_frac) * 100:.2f} % (5 m/s)"),
        ("Single-axis step: steady-state error", "very small",
         f"{_fmt(st.steady_state_error_m_s, '.4f')} m/s (1 m/s), {_fmt(st5.steady_state_error_m_s, '.3f')} m/s (5 m/s)"),
        ("Hover stability", "stable",
         f"from trim: max speed {hv.max_speed_from_trim_m_s:.1e} m/s; from {hv.initial_speed_m_s:.2f} m/s "
         f"and zero thrust: {hv.final_speed_from_perturbed_m_s:.1e} m/s after 30 s"),
        ("T/W sweep 1.5..6: max speed", "common, near 7.48 m/s",
         f"{_fmt(sw.max_speed_m_s, '.2f')} m/s for a {sw.cmd_speed_m_s:g} m/s command "
         f"(T/W {_fmt(sw.thrust_to_weight, 'g')}); under a {big.cmd_speed_m_s:g} m/s command "
         f"{_fmt(big.max_speed_m_s, '.1f')} m/s (tilt-limited drag terminal speed {big.tilt_limited_speed_m_s:.1f} m/s)"),
        ("T/W sweep: peak tilt / active constraint", "54.3 deg, attitude",
         f"{_fmt(sw.peak_tilt_deg, '.1f')} deg ({', '.join(sw.active_constraint)}) for the {sw.cmd_speed_m_s:g} m/s command, "
         f"peak thrust/T_max {_fmt(sw.peak_thrust_frac, '.2f')}; {_fmt(big.peak_tilt_deg, '.1f')} deg for {big.cmd_speed_m_s:g} m/s"),
        (f"Headwind 0..8 m/s, k_ff {hw.feedforward_gain:g}: steady-state error", "0.01..0.06 m/s",
         f"{hw.cmd_speed_m_s:g} m/s flight, winds {_fmt(hw.headwind_m_s, 'g')} m/s: still-air ff "
         f"{_fmt(hw.error_still_air_ff_m_s)}; wind-aware ff {_fmt(hw.error_wind_aware_ff_m_s)}; no ff "
         f"{_fmt(hw.error_no_ff_m_s)} m/s"),
        ("Monte Carlo noise 0..0.5 m/s RMS: lateral RMSE", "0.57 -> 2.98 m/s",
         f"measurement noise {_fmt(nz.rmse_lateral_m_s, '.2f')}; process noise {_fmt(nzp.rmse_lateral_m_s, '.2f')} m/s "
         f"(noise {_fmt(nz.noise_rms_m_s, 'g')} m/s, race profile, {nz.runs} runs/level, seed {nz.seed})"),
        ("Monte Carlo noise: vertical RMSE", "0.19 -> 2.18 m/s",
         f"measurement noise {_fmt(nz.rmse_vertical_m_s, '.2f')}; process noise {_fmt(nzp.rmse_vertical_m_s, '.2f')} m/s"),
        ("Aggressive manoeuvre (race), k_ff " + _fmt(rc.feedforward_gain, "g"), "tracks all axes (figure)",
         f"lateral RMSE {_fmt(rc.rmse_lateral_m_s)} m/s, vertical {_fmt(rc.rmse_vertical_m_s)} m/s, "
         f"8 m/s cruise error {_fmt(rc.cruise_error_m_s)} m/s, peak tilt {_fmt(rc.peak_tilt_deg, '.1f')} deg"),
        ("Cross-axis coupling", "decoupled (no figure)",
         f"{cp.step_m_s:g} m/s x step: max v_y {cp.max_y_from_hover_m_s:.1e}, v_z {cp.max_z_from_hover_m_s:.1e} m/s; "
         f"while cruising y at {cp.cruise_y_m_s:g} m/s: max y deviation {cp.max_y_dev_while_cruising_m_s:.3f} m/s"),
        ("Frequency response: -3 dB bandwidth", "no figure",
         f"{fr.bandwidth_hz:.3f} Hz measured, {fr.model_bandwidth_hz:.3f} Hz linear model "
         f"(1/(2 pi tau_v) = {fr.first_order_bandwidth_hz:.3f} Hz)"),
        ("Constraints never violated", "enforced",
         f"{cs.agents} random agents x {cs.steps} steps: max tilt excess {cs.max_tilt_excess_deg:.1e} deg, "
         f"max thrust excess {cs.max_thrust_excess_frac:.1e}"),
    ]  # fmt: skip
    lines = ["| Test | Paper | Ours |", "|---|---|---|"]
    lines += [f"| {a} | {b} | {c} |" for a, b, c in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m sim.plant.checks``: print the "ours vs the paper" table."""
    ap = argparse.ArgumentParser(prog="python -m sim.plant.checks", description=__doc__.split("\n")[0])
    ap.add_argument("--backend", choices=("auto", "numpy", "numba"), default="auto", help="plant kernel")
    args = ap.parse_args(argv)
    print(report_markdown(args.backend))  # CLI entry point: printing is its job
    return 0
