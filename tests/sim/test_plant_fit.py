"""Fitting the VelocityPlant to a flight, and the px4-sih preset against a real PX4 SIH flight."""

from pathlib import Path

import numpy as np
import pytest

from fisc_agent.flight.flightlog import read_flight_log
from sim.plant.model import PlantParams
from sim.plant.fit import PLANT_PRESETS, fit_plant, flight_log_arrays, plant_preset, replay, split_segments

DATA = Path(__file__).resolve().parents[1] / "data"
FLIGHTS = {"px4-sih": DATA / "px4_sih_stock_flight.csv", "px4-sih-tuned": DATA / "px4_sih_flight.csv"}
"""JOIN and FLOW rows of ``fisc-agent --flight-log`` on ../shared/sitl/px4: stock parameters, and the
velocity loop tuned (``MPC_XY_VEL_P_ACC`` 3.5, ``_I_ACC`` 1.5)."""


def test_fit_recovers_a_known_plant_from_its_own_response():
    truth = PlantParams(tau_v_s=0.3, tau_thrust_s=0.12, drag_area_m2=(0.3, 0.3, 0.3), drag_feedforward_gain=0.4)
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 20.0, 0.05)
    sp = np.repeat(rng.uniform(-3, 3, size=(len(t) // 30 + 1, 2)), 30, axis=0)[: len(t)]
    v = replay(truth, t, sp, np.zeros(2))
    fit = fit_plant(t, sp, v)
    assert fit.rms_m_s < 0.02 < fit.rms_paper_m_s
    assert fit.params.tau_v_s == pytest.approx(0.3, abs=0.08)


@pytest.mark.parametrize("name, bound", [("px4-sih", 0.095), ("px4-sih-tuned", 0.085)])
def test_each_px4_sih_preset_reproduces_its_real_px4_flight_better_than_the_other_models(name, bound):
    t, sp, v = flight_log_arrays(read_flight_log(FLIGHTS[name]))
    segs = split_segments(t, sp, v)
    assert sum(len(s[0]) for s in segs) > 300

    def rms(p):
        return float(np.sqrt(np.mean(np.concatenate([replay(p, a, b, c[0]) - c for a, b, c in segs]) ** 2)))

    own = rms(plant_preset(name))
    others = {other: rms(p) for other, p in PLANT_PRESETS.items() if other != name}
    assert own < bound and all(own < 0.9 * r for r in others.values()), (own, others)


def test_unknown_preset_names_the_choices():
    with pytest.raises(ValueError, match="px4-sih"):
        plant_preset("crazyflie")
