"""The documentation site (mkdocs.yml, docs/) builds with ``mkdocs build --strict``: no broken link or
anchor, every page in the nav.  Needs the ``docs`` extra (part of ``test``); without it the test skips
on a developer's machine and fails under CI (``CI`` set, as ``.ci/run`` does)."""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from import_graph import REPO


def _need_mkdocs() -> None:
    if importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("material") is None:
        msg = "mkdocs / mkdocs-material missing: pip install -e '.[docs]' (part of '.[test]')"
        if os.environ.get("CI"):
            pytest.fail(msg + "; CI is set, so this is an error, not a skip", pytrace=False)
        pytest.skip(msg)


def _build(root: Path, site: Path) -> subprocess.CompletedProcess:
    """``mkdocs build --strict`` of ``root``; not ``-q``: that silences the warnings strict mode counts."""
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(root / "mkdocs.yml"),
                           "-d", str(site)], capture_output=True, text=True, env=env, timeout=240)


def test_the_docs_site_builds_strictly(tmp_path):
    _need_mkdocs()
    out = _build(REPO, tmp_path / "site")
    assert out.returncode == 0, f"mkdocs build --strict failed:\n{out.stdout[-4000:]}\n{out.stderr[-4000:]}"
    assert (tmp_path / "site" / "index.html").is_file()
    assert (tmp_path / "site" / "studies" / "fidelity" / "index.html").is_file()


@pytest.mark.parametrize("breakage", ["broken link", "broken anchor", "page not in the nav"])
def test_the_strict_build_fails_on_a_broken_link_anchor_or_a_page_left_out(tmp_path, breakage):
    """The same site with one fault: the strict build must refuse it (so the check above can fail)."""
    _need_mkdocs()
    root = tmp_path / "repo"
    root.mkdir()
    shutil.copy2(REPO / "mkdocs.yml", root / "mkdocs.yml")
    shutil.copytree(REPO / "docs", root / "docs")
    status = root / "docs" / "status.md"
    if breakage == "broken link":
        status.write_text(status.read_text() + "\nSee [a page that is not there](no_such_page.md).\n")
    elif breakage == "broken anchor":
        status.write_text(status.read_text() + "\nSee [a section that is not there](studies/fidelity.md#no-such).\n")
    else:
        (root / "docs" / "stray.md").write_text("# A page nobody listed\n")
    out = _build(root, tmp_path / "site")
    assert out.returncode != 0, f"{breakage}: the strict build passed"
