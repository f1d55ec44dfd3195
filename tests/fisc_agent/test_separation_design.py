"""Separation by design onboard (issue 37): the duct-adapted wall margin, the entry windows from the
map's admission budget, and their ``fisc-agent`` flags."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fisc_agent.cli import build_parser, config_from_args, main
from fisc_agent.flight.control import ScalarField
from fisc_agent.flight.spacing import DEFAULT_ENTRY_SLOTS, EntrySchedule, ScheduleSource, entry_schedule
from fisc_agent.flight.tracking import ParcelTracker, TrackingConfig
from fisc_agent.map.codec import load_map
from fisc_agent.map.lookup import CommandField
from fisc_agent.map.separation import DEFAULT_D_MIN_M, Separation, map_separation
from fisc_agent.map.wall import WALL_MARGIN_FRACTION, DuctWall, effective_margin_m, map_wall, reflect_at_wall
from fisc_ground.maps.build import default_map_path

D = DEFAULT_D_MIN_M            # 0.924 m: d_min / 2 = 0.462 m
PIPE = DuctWall(np.array([0.0, 10.0]), np.array([0.75, 0.75]))     # the throat radius


def test_effective_margin_at_the_throat_the_inlet_and_the_cap():
    # throat (R 0.75): half the radius (0.375) is below d_min / 2, which wins; the 0.8 m margin is not used
    assert effective_margin_m(0.75, 0.8, D) == pytest.approx(D / 2)
    # inlet of the default duct (R 1.54): half the radius, under the cap
    assert effective_margin_m(1.54, 0.8, D) == pytest.approx(0.77)
    # the cap: from R = margin / fraction up the configured margin
    edge = 0.8 / WALL_MARGIN_FRACTION
    assert effective_margin_m([edge - 1e-6, edge, edge + 1e-6, 5.0], 0.8, D) == pytest.approx(
        [0.8 - 5e-7, 0.8, 0.8, 0.8])
    # the floor: where fraction x R = d_min / 2 exactly, just below and just above
    r0 = D / 2 / WALL_MARGIN_FRACTION
    assert effective_margin_m([r0 - 1e-3, r0, r0 + 1e-3], 0.8, D) == pytest.approx(
        [D / 2, D / 2, D / 2 + WALL_MARGIN_FRACTION * 1e-3])


def test_a_smaller_configured_margin_is_kept_and_none_is_the_fixed_rule():
    assert effective_margin_m([0.5, 0.75, 3.0], 0.3, D) == pytest.approx([0.3, 0.3, 0.3])   # motion capture
    assert effective_margin_m([0.5, 3.0], 0.8, None) == pytest.approx([0.8, 0.8])
    assert effective_margin_m(0.75, 0.0, D) == 0.0


def test_a_duct_narrower_than_half_the_spacing_turns_every_deviation_inward():
    m = effective_margin_m(0.4, 0.8, D)
    assert m == pytest.approx(D / 2) and m > 0.4
    out = reflect_at_wall(np.array([[1.0, 0.05, 0.0]]), np.array([[0.0, 1.0, 0.0]]),
                          DuctWall(np.array([0.0, 2.0]), np.array([0.4, 0.4])), 0.8, D)
    assert out[0] == pytest.approx([0.0, -1.0, 0.0])


@pytest.mark.parametrize("margin, d_min", [(-0.1, D), (math.nan, D), (0.8, -1.0), (0.8, math.inf)])
def test_bad_margins_are_refused(margin, d_min):
    with pytest.raises(ValueError, match="margin|d_min"):
        effective_margin_m(0.75, margin, d_min)


def test_at_the_throat_the_core_now_deviates_freely():
    """0.35 m off the axis in a 0.75 m pipe: with the fixed 0.8 m margin an outward deviation is folded
    back (the zone covers the whole section); with the adapted margin (free core 0.288 m) it is kept
    up to R - d_min / 2 and folded beyond."""
    dev = np.array([[0.2, 0.5, 0.0]])
    for r, kept in ((0.2, True), (0.75 - D / 2 - 1e-6, True), (0.75 - D / 2 + 1e-6, False), (0.6, False)):
        p = np.array([[5.0, r, 0.0]])
        assert reflect_at_wall(p, dev, PIPE, 0.8)[0] == pytest.approx([0.2, -0.5, 0.0])     # before: always
        got = reflect_at_wall(p, dev, PIPE, 0.8, D)[0]
        assert got == pytest.approx([0.2, 0.5, 0.0] if kept else [0.2, -0.5, 0.0]), r


def _default_sfield():
    cmap = load_map(default_map_path())
    return ScalarField(CommandField.from_map(cmap), wall=map_wall(cmap.arrays), separation=map_separation(cmap.body))


def test_the_shipped_map_carries_its_budget_and_the_agent_reads_it():
    sf = _default_sfield()
    assert sf.separation.d_min_m == pytest.approx(D)
    assert sf.separation.max_in_tunnel >= 1 and sf.separation.admission_period_s > 0


def test_an_outward_deviation_fills_the_section_yet_stays_inside_the_wall():
    """An ideal vehicle under tracking whose deviation keeps pointing outward, through the default duct:
    with the adapted margin it flies out to about R - max(d_min / 2, R / 2) (well off the axis at the
    throat) and never closer to the wall than d_min / 2 less one step."""
    sf = _default_sfield()
    wall = sf.wall

    def fly(d_min):
        tracker = ParcelTracker(TrackingConfig(lookahead_s=0.5), x_outlet_m=15.0)
        pos, dt, throat_r, worst = (1.0, 0.0, 0.0), 0.05, 0.0, -math.inf

        def outward(p, stream):
            r = math.hypot(p[1], p[2])
            d = np.array([[0.0, 0.4 * p[1] / r, 0.4 * p[2] / r]]) if r > 0 else np.array([[0.0, 0.4, 0.0]])
            return tuple(float(v) for v in reflect_at_wall(np.array([p]), d, wall, 0.8, d_min)[0])

        for k in range(int(40.0 / dt)):
            v = tracker.step(k * dt, pos, lambda x, y, z: sf.flight((x, y, z), None, 0, 0.0, "staggered", 0.0), outward)
            if v is None or pos[0] > 14.5:
                break
            pos = tuple(p + dt * c for p, c in zip(pos, v))
            worst = max(worst, math.hypot(pos[1], pos[2]) - float(wall.radius_at(pos[0])))
            if 5.5 <= pos[0] <= 6.5:
                throat_r = max(throat_r, math.hypot(pos[1], pos[2]))
        return worst, throat_r, pos[0]

    worst, throat_r, reached = fly(D)
    assert reached > 14.0 and worst < -D / 2 + 0.1            # inside the wall by about d_min / 2
    assert throat_r > 0.3                                      # the throat's section is used off the axis (0.41 m)
    _, throat_fixed, _ = fly(None)
    assert throat_fixed < 0.15                                 # the fixed 0.8 m margin folds it onto the axis (0.09 m)


def test_entry_schedule_given_map_and_none():
    budget = Separation(max_in_tunnel=13, admission_period_s=2.9)
    assert entry_schedule(None, None, budget) == EntrySchedule(2.9, 13, ScheduleSource.MAP)
    assert entry_schedule(None, 20, budget) == EntrySchedule(2.9, 20, ScheduleSource.MAP)
    assert entry_schedule(0.0, None, budget) == EntrySchedule(0.0, DEFAULT_ENTRY_SLOTS, ScheduleSource.GIVEN)
    assert entry_schedule(4.0, 3, budget) == EntrySchedule(4.0, 3, ScheduleSource.GIVEN)
    assert entry_schedule(None, None, Separation()) == EntrySchedule(0.0, DEFAULT_ENTRY_SLOTS, ScheduleSource.NONE)
    one = Separation(max_in_tunnel=1, admission_period_s=20.0)
    assert entry_schedule(None, None, one) == EntrySchedule(20.0, 1, ScheduleSource.MAP)


@pytest.mark.parametrize("kw, match", [({"max_in_tunnel": 0}, "max_in_tunnel"), ({"max_in_tunnel": True}, "max_in_tunnel"),
                                       ({"admission_period_s": 0.0}, "admission_period_s"),
                                       ({"admission_period_s": math.inf}, "admission_period_s"),
                                       ({"vehicle_radius_m": -0.1}, "vehicle radius")])
def test_a_bad_budget_is_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        Separation(**kw)


BASE = ["--map", "m.fiscmap", "--mavlink", "udp://:14540", "--id", "7"]


@pytest.mark.parametrize("flag, value, field, want", [
    ("--entry-stagger", None, "entry_stagger_s", None), ("--entry-stagger", "auto", "entry_stagger_s", None),
    ("--entry-stagger", "off", "entry_stagger_s", 0.0), ("--entry-stagger", "0", "entry_stagger_s", 0.0),
    ("--entry-stagger", "2.5", "entry_stagger_s", 2.5),
    ("--entry-slots", None, "entry_slots", None), ("--entry-slots", "auto", "entry_slots", None),
    ("--entry-slots", "1", "entry_slots", 1), ("--entry-slots", "16", "entry_slots", 16),
])
def test_entry_flags(flag, value, field, want):
    argv = BASE + ([] if value is None else [flag, value])
    assert getattr(config_from_args(build_parser().parse_args(argv)), field) == want


@pytest.mark.parametrize("flag, value", [("--entry-stagger", "-1"), ("--entry-stagger", "soon"),
                                         ("--entry-stagger", "nan"), ("--entry-slots", "0"),
                                         ("--entry-slots", "2.5"), ("--entry-slots", "many")])
def test_bad_entry_flags_exit_2_naming_the_flag(flag, value, capsys):
    with pytest.raises(SystemExit) as exc:
        main(BASE + [flag, value])
    assert exc.value.code == 2 and f"argument {flag}" in capsys.readouterr().err
