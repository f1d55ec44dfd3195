"""``fisc_agent`` stays lean (this replaces the older partial check in tests/fisc_agent/test_agent_cli.py): importing every one of its modules loads none of scipy, matplotlib,
numba, fisc_ground or sim (checked in a fresh interpreter, so nothing else has imported them)."""

from __future__ import annotations

import json
import subprocess
import sys

from import_graph import REPO, module_files

FORBIDDEN = ("scipy", "matplotlib", "numba", "fisc_ground", "sim", "meshio", "rich", "dask", "foxglove", "mcap",
             "mavsdk")  # mavsdk: optional, imported only when --backend mavsdk connects

_PROBE = """
import importlib, json, sys
mods = json.loads(sys.argv[1])
for m in mods:
    importlib.import_module(m)
top = sorted({name.split(".")[0] for name in sys.modules})
print(json.dumps(top))
"""


def _loaded_after_importing(modules: list[str]) -> set[str]:
    out = subprocess.run([sys.executable, "-c", _PROBE, json.dumps(modules)], cwd=REPO, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return set(json.loads(out.stdout.strip().splitlines()[-1]))


def test_every_agent_module_imports_without_heavy_packages():
    modules = sorted(m for m in module_files(("fisc_agent",)))
    assert "fisc_agent.runner" in modules and "fisc_agent.cli" in modules and len(modules) > 25
    loaded = _loaded_after_importing(modules)
    assert "fisc_agent" in loaded
    assert not loaded & set(FORBIDDEN), f"fisc_agent pulled in {sorted(loaded & set(FORBIDDEN))}"


def test_the_probe_sees_a_heavy_import():
    """The check can fail: importing a fisc_ground module that needs scipy shows scipy loaded."""
    loaded = _loaded_after_importing(["fisc_ground.fields.flight_score"])
    assert {"scipy", "fisc_ground"} <= loaded
