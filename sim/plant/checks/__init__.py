"""The paper's plant test campaign, as functions returning the measured figures.

The paper ("Individual-Agent Velocity Plant", "Performance Testing Prior to Swarm Use") reports
a settling time, a thrust-to-weight sweep, a headwind test with drag feed-forward, a Monte Carlo
noise test and an aggressive manoeuvre.  Each ``check_*`` function (modules ``steps``, ``robustness``, ``frequency``) runs one of them on
:mod:`sim.plant.model` (vectorised: a sweep's cases are agents of one plant, with per-agent
parameters where the case varies a parameter) and returns a frozen dataclass of figures.  The
tests (``tests/sim/test_plant.py``) assert on these functions, and ``python -m sim.plant.checks``
prints the "ours vs the paper" table of ``docs/plant.md``, so the docs and the tests agree.
"""

from sim.plant.checks.common import (
    DT_S,
    closed_loop_response,
    Run,
    second_order_settling_time_s,
    settling_time_s,
    simulate,
)
from sim.plant.checks.frequency import (
    check_constraints,
    check_coupling,
    check_frequency_response,
    ConstraintResult,
    CouplingResult,
    FrequencyResult,
)
from sim.plant.checks.report import (
    main,
    report_markdown,
)
from sim.plant.checks.robustness import (
    RACE_DURATION_S,
    check_noise,
    check_race,
    NoiseResult,
    race_command,
    RaceResult,
)
from sim.plant.checks.steps import (
    check_headwind,
    check_hover,
    check_single_axis_step,
    check_thrust_to_weight_sweep,
    HeadwindResult,
    HoverResult,
    steady_state_error_m_s,
    StepResult,
    SweepResult,
)

__all__ = [
    "ConstraintResult",
    "CouplingResult",
    "DT_S",
    "FrequencyResult",
    "HeadwindResult",
    "HoverResult",
    "NoiseResult",
    "RACE_DURATION_S",
    "RaceResult",
    "Run",
    "StepResult",
    "SweepResult",
    "check_constraints",
    "check_coupling",
    "check_frequency_response",
    "check_headwind",
    "check_hover",
    "check_noise",
    "check_race",
    "check_single_axis_step",
    "check_thrust_to_weight_sweep",
    "closed_loop_response",
    "main",
    "race_command",
    "report_markdown",
    "second_order_settling_time_s",
    "settling_time_s",
    "simulate",
    "steady_state_error_m_s",
]
