"""The ``../shared`` resolver (tests/conftest.py): a skip on a developer machine, a failure in CI."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NEEDS_SHARED = "tests/fisc_ground/test_scaling.py::test_scaled_reference_map_is_flyable"


def _run(tmp_path, ci: bool) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "CI"}
    env["FISC_SHARED_DIR"] = str(tmp_path / "no-shared-here")
    if ci:
        env["CI"] = "true"
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", NEEDS_SHARED],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)


def test_missing_shared_data_skips_with_the_reason_on_a_developer_machine(tmp_path):
    out = _run(tmp_path, ci=False)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "1 skipped" in out.stdout and "no-shared-here" in out.stdout


def test_missing_shared_data_fails_when_ci_is_set(tmp_path):
    out = _run(tmp_path, ci=True)
    assert out.returncode == 1, out.stdout + out.stderr
    assert "1 failed" in out.stdout and "CI is set, so missing data is an error" in out.stdout
