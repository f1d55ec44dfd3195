"""Optional packages and tools of the suite: skipped with the reason on a developer's machine, a FAILURE
when the environment variable ``CI`` is set (``.ci/run`` sets it), as a missing ``../shared`` is
(``tests/conftest.py``).  CI installs ``.[test]``, which pulls every optional package, so a skip there
would hide a broken install or a test that never runs.

- ``require_module("mavsdk", extra="mavsdk")`` instead of ``pytest.importorskip`` (tests/meta forbids
  the bare call): returns the module, or skips / fails naming the extra to install;
- ``needs(numba_available(), "numba", extra="jit")``: a ``skipif`` marker with such a reason;
- ``missing_optional(reason)``: True for a skip reason that means "an optional package or tool is
  missing" (``MISSING`` prefix, or pytest's own ``importorskip`` wording); ``tests/conftest.py`` turns
  those skips into failures under CI, whatever raised them.
"""

from __future__ import annotations

import importlib
import os
from types import ModuleType

import pytest

MISSING = "optional package missing"
"""Prefix of every skip reason that means an optional package or tool is not installed."""
_IMPORTORSKIP = "could not import"
"""The start of ``pytest.importorskip``'s own reason."""


def ci() -> bool:
    """True when the environment variable ``CI`` is set and not empty (``.ci/run``)."""
    return bool(os.environ.get("CI"))


def missing_reason(what: str, extra: str | None = None) -> str:
    """The skip reason for a missing package or tool ``what`` (installed by ``fisc[extra]``)."""
    how = f" (pip install -e '.[{extra}]', part of '.[test]')" if extra else ""
    return f"{MISSING}: {what}{how}"


def missing_optional(reason: str) -> bool:
    """True when a skip ``reason`` says an optional package or tool is missing."""
    text = reason.removeprefix("Skipped: ").strip()
    return text.startswith(MISSING) or text.startswith(_IMPORTORSKIP)


def require_module(name: str, extra: str | None = None) -> ModuleType:
    """``import name``; if it is not installed, skip (developer machine) or fail (``CI`` set)."""
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        reason = f"{missing_reason(name, extra)}: {exc}"
    if ci():
        pytest.fail(reason + "; CI is set, so a missing optional package is an error, not a skip", pytrace=False)
    pytest.skip(reason, allow_module_level=True)  # also at a module's import


def needs(available: bool, what: str, extra: str | None = None) -> pytest.MarkDecorator:
    """A ``skipif`` marker for a test that needs ``what``; its skip fails under CI (tests/conftest.py)."""
    return pytest.mark.skipif(not available, reason=missing_reason(what, extra))
