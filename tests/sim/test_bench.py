"""``fisc-sim bench``'s timing of the paper's run: both presets are flown as their names say (the
figures themselves are machine-dependent and only printed)."""

from sim.bench import bench_paper_run
from sim.run import load_command_map


def test_the_paper_run_is_timed_with_each_preset_as_it_flies():
    paper = bench_paper_run(load_command_map(None, preset="paper"), "paper", agents=200, duration_s=5.0)
    default = bench_paper_run(load_command_map(None), "default", agents=200, duration_s=5.0)
    assert (paper["mode"], paper["lookahead_s"]) == ("mean", 0.0)
    assert (default["mode"], default["lookahead_s"]) == ("kinetic", 0.5)
    for r in (paper, default):
        assert r["steps"] == 100 and r["agent_steps"] > 0 and r["wall_s"] > 0
