"""The package tree draws the architecture (issue 39): few top-level entries per package, one
subpackage per idea with a docstring stating its interface, and no module family told apart only
by a name prefix."""

from __future__ import annotations

import ast
from collections import Counter

import pytest
from import_graph import REPO

MAX_TOP_LEVEL = 10


def _entries(package: str) -> list[str]:
    return sorted(p.name for p in (REPO / package).iterdir()
                  if p.name != "__pycache__" and (p.is_dir() or p.suffix == ".py"))


def prefix_families(names: list[str], min_size: int = 3) -> dict[str, list[str]]:
    """Name prefixes (the part before the first ``_``) shared by ``min_size`` or more sibling
    modules or packages, a bare name counting as its own prefix (``plant`` with ``plant_fit``)."""
    stems = [n[:-3] if n.endswith(".py") else n for n in names if n != "__init__.py"]
    counts = Counter(s.split("_")[0] for s in stems)
    return {p: sorted(s for s in stems if s.split("_")[0] == p) for p, c in counts.items() if c >= min_size}


def test_prefix_families_finds_a_family_and_only_that():
    assert prefix_families(["zenoh_a.py", "zenoh_b.py", "zenoh.py", "map.py", "__init__.py"]) == {
        "zenoh": ["zenoh", "zenoh_a", "zenoh_b"]}
    assert prefix_families(["zenoh_a.py", "zenoh_b.py", "map"]) == {}
    assert prefix_families([]) == {}


@pytest.mark.parametrize("package", ["fisc_agent", "fisc_ground"])
def test_top_level_is_small(package):
    entries = _entries(package)
    assert "__init__.py" in entries and "cli.py" in entries
    assert len(entries) <= MAX_TOP_LEVEL, f"{package}/ has {len(entries)} entries: {entries}"


def _package_dirs():
    for pkg in ("fisc_agent", "fisc_ground", "sim"):
        yield REPO / pkg
        yield from (p.parent for p in sorted((REPO / pkg).rglob("*/__init__.py")))


def test_no_prefix_families_anywhere():
    found = {d.relative_to(REPO).as_posix(): fam for d in _package_dirs() if (fam := prefix_families(_entries(d)))}
    assert not found, f"modules told apart only by a name prefix (make each family a subpackage): {found}"


def test_every_subpackage_states_its_interface():
    missing = [d.relative_to(REPO).as_posix() for d in _package_dirs()
               if len(ast.get_docstring(ast.parse((d / "__init__.py").read_text())) or "") < 40]
    assert not missing, f"subpackages whose __init__ docstring does not state their interface: {missing}"
