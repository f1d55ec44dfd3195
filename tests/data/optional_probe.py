"""Run by tests/test_optional.py only (not a test_*.py file): each way a test can skip."""

import pytest

from ..optional import needs, require_module


def test_require_module():
    require_module("fisc_no_such_package", extra="test")


@needs(False, "fisc-no-such-tool")
def test_needs_marker():
    pass


def test_bare_importorskip():
    pytest.importorskip("fisc_no_such_package")


def test_a_skip_for_another_reason():
    pytest.skip("this file system does not report holes")
