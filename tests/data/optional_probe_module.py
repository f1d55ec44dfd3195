"""Run by tests/test_optional.py only: a module that needs a missing package at import (a bare
``pytest.importorskip``: the hook of tests/conftest.py turns its skip into an error under CI)."""

import pytest

pytest.importorskip("fisc_no_such_package")


def test_never_runs():
    pass
