"""No module of fisc_agent, fisc_ground or sim is over 500 lines (issue 11)."""

from __future__ import annotations

from import_graph import REPO, module_files

MAX_LINES = 500


def test_no_module_over_the_limit():
    sizes = {p.relative_to(REPO).as_posix(): len(p.read_text().splitlines()) for p in module_files().values()}
    assert len(sizes) > 60
    over = {f: n for f, n in sizes.items() if n > MAX_LINES}
    assert not over, f"modules over {MAX_LINES} lines: {over}"
