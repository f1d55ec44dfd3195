"""Suite-wide fixtures.

``shared_path``: the one resolver for the CFD data in ``../shared`` (beside the checkout, or
``$FISC_SHARED_DIR``).  On a developer machine without it the test is skipped with the reason;
when the environment variable ``CI`` is set (``.ci/run`` runs with ``CI=true``) a missing file
FAILS the test, so CI can never pass by skipping the reference checks.

The same holds for optional packages and tools (``tests/optional.py``): under ``CI`` every skip whose
reason says one is missing (``optional.missing_optional``: ``require_module``, ``needs`` and even a bare
``pytest.importorskip``) is reported as a failure, at collection or at run time.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import pytest

from .optional import ci, missing_optional
from .sitl_groups import pytest_collection_modifyitems  # noqa: F401 (a hook, here to be found)

REPO_ROOT = Path(__file__).resolve().parents[1]


def shared_root() -> Path:
    """``$FISC_SHARED_DIR`` if set, else ``../shared`` beside the repository."""
    env = os.environ.get("FISC_SHARED_DIR")
    return Path(env) if env else REPO_ROOT.parent / "shared"


def resolve_shared(*parts: str) -> Path:
    """The file ``<shared>/<parts...>``; skip (developer machine) or fail (``CI`` set) if missing."""
    path = shared_root().joinpath(*parts)
    if path.exists():
        return path
    msg = (f"shared data {'/'.join(parts)} not found at {path} (the CFD data beside the checkout, "
           "../shared, or $FISC_SHARED_DIR)")
    if os.environ.get("CI"):
        pytest.fail(msg + "; CI is set, so missing data is an error, not a skip", pytrace=False)
    pytest.skip(msg)


@pytest.fixture(scope="session")
def shared_path() -> Callable[..., Path]:
    """``shared_path("reference", "cd_nozzle", "axisym_cells.csv")`` -> Path (see ``resolve_shared``)."""
    return resolve_shared


@pytest.fixture(scope="session", autouse=True)
def _own_lab_port_per_worker():
    """Under xdist each worker is a lab of its own: a test that leaves ``FISC_ZENOH_PORT`` unset would meet
    the other worker's processes on the default lab port (7447).  Each worker sets it to a free port of
    its own once; a test that sets it still wins."""
    from fisc_agent.zenoh.session import PORT_ENV

    from .ports import free_tcp_port

    own = bool(os.environ.get("PYTEST_XDIST_WORKER")) and PORT_ENV not in os.environ
    if own:
        os.environ[PORT_ENV] = str(free_tcp_port())
    yield
    if own:
        os.environ.pop(PORT_ENV, None)


@pytest.fixture(autouse=True)
def _own_agent_state_dir(tmp_path_factory, monkeypatch):
    """Every test gets its own ``$XDG_STATE_HOME``: an agent's state file (``fisc-agent --state-file
    auto``: hands-off, fleet hold, command floors) must not carry from one test's flight to the next."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path_factory.mktemp("xdg_state")))


def _fail_missing_optional_under_ci(report) -> None:
    """Turn a skip for a missing optional package into a failure when ``CI`` is set."""
    if not (report.skipped and ci()) or hasattr(report, "wasxfail"):
        return
    longrepr = report.longrepr
    reason = longrepr[2] if isinstance(longrepr, tuple) and len(longrepr) == 3 else str(longrepr)
    if missing_optional(reason):
        report.outcome = "failed"
        report.longrepr = f"{reason.removeprefix('Skipped: ')}; CI is set, so a missing optional package is an error, not a skip"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """A test skipped for a missing optional package fails under ``CI``."""
    outcome = yield
    _fail_missing_optional_under_ci(outcome.get_result())


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector):
    """A module skipped at import for a missing optional package fails under ``CI``."""
    outcome = yield
    _fail_missing_optional_under_ci(outcome.get_result())
