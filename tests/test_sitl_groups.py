"""Under the README's ``pytest -n 2 --dist loadgroup`` every ``sitl`` test runs on one worker
(``tests/sitl_groups.py``), checked on probe tests in a pytest run of their own."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

HOOK = Path(__file__).with_name("sitl_groups.py")

CONFTEST = f'''
import importlib.util

_spec = importlib.util.spec_from_file_location("fisc_sitl_groups", {str(HOOK)!r})
_mod = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_mod)
pytest_collection_modifyitems = _mod.pytest_collection_modifyitems
'''

PROBES = '''
import os
import time

import pytest

OUT = os.environ["PROBE_OUT"]


def _note(name):
    time.sleep(0.2)
    with open(os.path.join(OUT, name), "w") as f:
        f.write(os.environ["PYTEST_XDIST_WORKER"])


@pytest.mark.sitl
@pytest.mark.parametrize("k", range(6))
def test_flight(k):
    _note(f"sitl{k}")


@pytest.mark.parametrize("k", range(6))
def test_unit(k):
    _note(f"unit{k}")
'''


def test_every_sitl_test_runs_on_one_xdist_worker(tmp_path):
    (tmp_path / "pytest.ini").write_text("[pytest]\nmarkers =\n    sitl: probe\n")
    (tmp_path / "conftest.py").write_text(CONFTEST)
    (tmp_path / "test_probes.py").write_text(PROBES)
    out = tmp_path / "out"
    out.mkdir()
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "2", "--dist", "loadgroup", "-p",
                          "no:cacheprovider", str(tmp_path)], cwd=tmp_path, capture_output=True, text=True,
                         timeout=120, env={**os.environ, "PROBE_OUT": str(out)})
    assert run.returncode == 0, run.stdout + run.stderr
    workers = {f.name: f.read_text() for f in out.iterdir()}
    assert len(workers) == 12
    assert len({w for n, w in workers.items() if n.startswith("sitl")}) == 1, workers
