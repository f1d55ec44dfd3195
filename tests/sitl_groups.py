"""The xdist group of the real-autopilot tests (a pytest hook, re-exported by ``tests/conftest.py``).

A module of its own, without relative imports, so that ``tests/test_sitl_groups.py`` can load it into a
pytest run of probe tests and check that the grouping holds (pytest 9.2 with pytest-xdist 3.8 silently
dropped every ``xdist_group``: pytest-dev/pytest-xdist#1386; the test extra pins ``pytest<9.2``).
"""

from __future__ import annotations

import pytest

SITL_GROUP = "sitl"
"""The ``xdist_group`` of every real-autopilot test: the SITL instances of PX4 and ArduPilot talk on fixed
ports (udp 14540+i, 14550), so under ``pytest -n 2 --dist loadgroup`` (the README's command) one worker flies
them one after another while the other runs the rest.  (Their SITL sets also take ``sitl_kit.MachineLock``:
were the grouping lost, a second worker would wait for the first one's vehicles, never fly beside them.)"""


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Every ``sitl`` test goes to the one worker that flies the real autopilots (``SITL_GROUP``).  First:
    xdist's own hook (registered after this file, so called before it otherwise) turns the marks into groups."""
    for item in items:
        if item.get_closest_marker("sitl") is not None:
            item.add_marker(pytest.mark.xdist_group(SITL_GROUP))
