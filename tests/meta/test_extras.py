"""Every ``fisc[EXTRA]`` named in a message or a doc exists in pyproject.toml, and the lean base
install carries only what fisc-agent needs."""

from __future__ import annotations

import re
import tomllib

from import_graph import REPO

from fisc_agent.common.cli_common import EXTRA_OF_MODULE

LEAN = {"numpy", "pymavlink", "eclipse-zenoh", "pynacl"}


def _project() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]


def _named_extras() -> dict[str, set[str]]:
    found: dict[str, set[str]] = {}
    files = [*REPO.glob("fisc_agent/**/*.py"), *REPO.glob("fisc_ground/**/*.py"), *REPO.glob("sim/**/*.py"),
             *REPO.glob("docs/**/*.md"), REPO / "README.md"]
    for path in files:
        for match in re.finditer(r"fisc\[([a-z0-9_,\- ]+)\]", path.read_text()):
            for extra in match.group(1).split(","):
                found.setdefault(extra.strip(), set()).add(str(path.relative_to(REPO)))
    return found


def test_every_named_extra_exists():
    extras = set(_project()["optional-dependencies"])
    named = _named_extras()
    assert "jit" in named and "mavsdk" in named  # the scan finds the messages of sim/plant/model.py and mavsdk_backend
    missing = {e: sorted(files) for e, files in named.items() if e not in extras}
    assert not missing, f"extras named but not defined in pyproject.toml: {missing}"
    assert set(EXTRA_OF_MODULE.values()) <= extras


def test_base_install_is_the_lean_agent():
    deps = {re.split(r"[<>=\[ ;]", d, maxsplit=1)[0].lower() for d in _project()["dependencies"]}
    assert deps == LEAN


def test_test_extra_pulls_everything():
    opt = _project()["optional-dependencies"]
    assert any(d.startswith("fisc[all") for d in opt["test"])
    everything = " ".join(opt["all"])
    for extra in ("ground", "sim", "sweep", "jit", "mavsdk"):
        assert extra in everything
