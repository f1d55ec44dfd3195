"""``fisc-sim emulate``: an emulated swarm, headless, with real MAVLink in the loop.

N autopilot emulators (:class:`sim.autopilot.server.AutopilotEmulator`, PX4 or ArduPilot Copter
personality, the paper's velocity plant inside) and N onboard agents (:class:`fisc_agent.runner.
Runner`, the same code ``fisc-agent`` runs) talk MAVLink 2 over loopback UDP, one socket pair per
vehicle.  The agents fly the paper's Case 2 ("reservoir"): every vehicle starts disarmed on the
ground upstream of (and 10 m below) the inlet, arms, takes off, joins the tunnel at the inlet
(its mission's JOIN state) and flows through it (FLOW); after the outlet it flies back to the
inlet and goes round again (exit policy ``loop``), so the tunnel keeps being fed for the whole
run.  Start times are staggered so that vehicles reach the inlet at the paper's source rate
(eq. source_rate, scaled to the population as ``fisc-sim run`` scales it).

Process layout (2-core friendly): the emulators live in ``emulator_workers`` processes and the
agents in ``agent_workers`` processes; each process multiplexes its share in one thread on a
monotonic-deadline schedule (emulators: ``AutopilotEmulator.poll`` at the physics rate; agents:
``Runner.step`` at the setpoint rate).  Ground truth for the swarm fields is the emulators' true
vehicle state (not the telemetry), sampled on the ``fisc-sim run`` sampling grid, transformed to
the map frame with the default deployment transform (map x -> North, y -> East, z -> Up, map
origin at local NED (0, 0, -10)) and accumulated per CV with ``FieldAccumulator`` exactly as the
vectorised simulator does.  The outputs (fields.csv, metrics.json, figures, report.md) are
written with ``fisc_ground.fields.field_report``/``field_figures``, so they have the format of ``fisc-sim run``; in
addition ``emulation.json`` (timing, real-time figures, per-agent mission outcome) and, unless
disabled, ``comparison.json`` (the metric differences against ``fisc-sim run`` on the same
map, duration and mode, at the population that flies as many agents in the tunnel as the emulation
flew vehicles, and at the launched population N) are written, and report.md gets an "Emulation" section.

Modules: ``config`` (EmulateConfig), ``plan`` (launch plan, map), ``workers`` (the emulator and
agent processes), ``fly`` (start them, collect a ``SwarmRun``), ``analysis`` (fields, arrivals,
real time, comparison), ``outputs`` (the job: ``run``).
"""

from sim.emulate.analysis import (  # noqa: F401
    COMPARED_METRICS,
    compare_fields,
    entry_statistics,
    flowing,
    flowing_vehicles,
    ground_truth_fields,
    loop_stats,
    matched_population,
    realtime_summary,
    sample_window,
    steady_start_s,
)
from sim.emulate.config import LAUNCH_OVERHEAD_S, PERSONALITIES, TELEMETRY, EmulateConfig  # noqa: F401
from sim.emulate.fly import SwarmRun, fly_swarm  # noqa: F401
from sim.emulate.outputs import EmulateResult, run  # noqa: F401
from sim.emulate.plan import LaunchPlan, launch_plan, prepare_map  # noqa: F401
