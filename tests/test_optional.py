"""No test is skipped silently (issue 38): a missing optional package skips on a developer's machine
and fails under CI (``CI`` set, as ``.ci/run`` does), as a missing ``../shared`` does."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from .optional import MISSING, missing_optional, missing_reason

REPO = Path(__file__).resolve().parents[1]


def _run_probes(ci: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "CI"}
    if ci is not None:
        env["CI"] = ci
    out = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rA", "-p", "no:cacheprovider", "--continue-on-collection-errors",
                          "tests/data/optional_probe.py", "tests/data/optional_probe_module.py"],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    return out.stdout + out.stderr


def _counts(text: str) -> dict[str, int]:
    return {k: int(n) for n, k in re.findall(r"(\d+) (failed|passed|skipped|errors?)", text.splitlines()[-1])}


def test_missing_optional_packages_skip_on_a_developer_machine():
    text = _run_probes(None)
    assert _counts(text) == {"skipped": 5}, text
    assert "optional package missing: fisc_no_such_package (pip install -e '.[test]', part of '.[test]')" in text
    assert "optional package missing: fisc-no-such-tool" in text


@pytest.mark.parametrize("ci", ["true", "1"])
def test_missing_optional_packages_fail_under_ci(ci):
    text = _run_probes(ci)
    counts = _counts(text)
    # the three ways to need a package fail (a skipif marker's at setup: an error), the module that
    # needs one at import is an error, and a skip for another reason (no holes in the file system) stays a skip
    assert counts == {"failed": 2, "skipped": 1, "errors": 2}, text
    assert "CI is set, so a missing optional package is an error, not a skip" in text
    for name in ("optional_probe.py::test_require_module", "optional_probe.py::test_needs_marker",
                 "optional_probe.py::test_bare_importorskip", "optional_probe_module.py"):
        assert re.search(rf"(FAILED|ERROR) \S*{re.escape(name)}", text), (name, text)
    assert "SKIPPED [1] tests/data/optional_probe.py:22: this file system does not report holes" in text


def test_an_empty_ci_variable_is_a_developer_machine():
    assert _counts(_run_probes(""))["skipped"] == 5


def test_skip_reasons_that_mean_a_missing_package():
    assert missing_optional(missing_reason("numba", "jit")) and missing_optional("Skipped: " + MISSING + ": x")
    assert missing_optional("could not import 'mavsdk': No module named 'mavsdk'")
    assert not missing_optional("fork not available here") and not missing_optional("")


def test_no_bare_importorskip_in_the_suite():
    """Every optional import goes through ``optional.require_module`` (which names the extra)."""
    allowed = {Path(__file__), REPO / "tests" / "optional.py", REPO / "tests" / "data" / "optional_probe.py",
               REPO / "tests" / "data" / "optional_probe_module.py"}
    offenders = [str(p.relative_to(REPO)) for p in (REPO / "tests").rglob("*.py")
                 if p not in allowed and "importorskip(" in p.read_text()]
    assert not offenders, f"use tests/optional.require_module instead of pytest.importorskip: {offenders}"
