"""No import cycles among fisc_agent, fisc_ground and sim, and the layering sim -> fisc_ground -> fisc_agent.

The graph is read from the source (``import_graph.py``), lazy imports inside functions included.
"""

from __future__ import annotations

from import_graph import PACKAGES, cycles, import_graph

def test_the_graph_sees_the_project():
    graph = import_graph()
    assert len(graph) > 60
    assert "fisc_agent.map.codec" in graph["fisc_agent.runner"] or "fisc_agent.map.codec" in graph["fisc_agent.cli"]
    # a lazy import inside a function is an edge too (run_monitor imports zenoh_config)
    assert "fisc_ground.zenoh.config" in graph["fisc_ground.monitor.run"]


def test_cycle_finder_finds_a_planted_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert cycles(graph) == [frozenset({"a", "b", "c"})]


def test_no_import_cycles():
    found = cycles(import_graph())
    assert not found, "import cycles: " + "; ".join(" <-> ".join(sorted(c)) for c in found)


def test_layering_agent_ground_sim():
    """fisc_agent imports neither fisc_ground nor sim; fisc_ground does not import sim."""
    graph = import_graph()
    bad = [(a, b) for a, deps in graph.items() for b in deps
           if (a.startswith("fisc_agent") and b.split(".")[0] in ("fisc_ground", "sim"))
           or (a.startswith("fisc_ground") and b.split(".")[0] == "sim")]
    assert not bad, f"imports against the layering: {bad}"
    assert set(PACKAGES) == {"fisc_agent", "fisc_ground", "sim"}
