"""Every sweep spec under benchmarks/ parses, and each ``FILE.py:FUNCTION`` map it names builds a
reference field: a benchmark a reader is told to run must not fail at its first line."""

from pathlib import Path

import pytest

from fisc_ground.reference.field import ReferenceField
from sim.sweep.spec import load_case_function, load_spec

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"
SPECS = sorted(BENCH.glob("*.toml"))


def test_there_are_specs():
    assert {p.name for p in SPECS} >= {"fidelity_table.toml", "duct_family.toml", "duct_family_beta.toml",
                                       "duct_fresh.toml"}


@pytest.mark.parametrize("path", SPECS, ids=[p.name for p in SPECS])
def test_spec_parses_and_its_python_cases_build_references(path):
    spec = load_spec(path)
    points = spec.points()
    assert points
    cases = {p.run["map"] for p in points if ".py:" in str(p.run.get("map"))}
    for case in sorted(cases):
        file, func = case.rsplit(":", 1)
        assert Path(file).is_absolute() and Path(file).is_file(), case
        ref = load_case_function(file, func)()
        assert isinstance(ref, ReferenceField) and ref.n_nodes > 1000, case
