"""No module of fisc_agent, fisc_ground or sim is over 500 lines (issue 11)."""

from __future__ import annotations

import pytest

from import_graph import module_files

MAX_LINES = 500

#: Modules being split by other work today (issue 11 item 5).  Each is an xfail(strict=True) case
#: below: once a file is at most MAX_LINES the case passes and strict mode fails the suite, so the
#: entry must then be removed.  The lead empties this set after merging the splits.
KNOWN_LARGE = frozenset({
    "sim/emulate.py", "fisc_ground/monitor.py",
})


def _rel_sizes() -> dict[str, int]:
    from import_graph import REPO

    return {p.relative_to(REPO).as_posix(): len(p.read_text().splitlines()) for p in module_files().values()}


def test_no_module_over_the_limit():
    sizes = _rel_sizes()
    assert len(sizes) > 60
    over = {f: n for f, n in sizes.items() if n > MAX_LINES and f not in KNOWN_LARGE}
    assert not over, f"modules over {MAX_LINES} lines: {over}"


@pytest.mark.parametrize("path", sorted(KNOWN_LARGE))
@pytest.mark.xfail(strict=True, reason="being split (issue 11 item 5); remove from KNOWN_LARGE once under the limit")
def test_known_large_module_is_split(path):
    sizes = _rel_sizes()
    assert sizes.get(path, 0) <= MAX_LINES, f"{path}: {sizes[path]} lines"  # a file split away counts as done
