"""Every public function, class and method of fisc_agent, fisc_ground and sim has a docstring.

Public: a name without a leading underscore, at module level or in a public class (methods of a
class nested in a function are not API).  Read from the source (ast), so nothing is imported.
"""

from __future__ import annotations

import ast

import pytest

from import_graph import REPO, module_files

#: Modules other work is rewriting or splitting today (issue 11 items 1, 2, 5, 6), left undocumented
#: here to keep the merge clean.  Each is an xfail(strict=True) case below: once documented, strict
#: mode fails the suite until the entry is removed.  The lead empties this set after merging.
KNOWN_UNDOCUMENTED = frozenset({
    "fisc_ground.monitor", "fisc_ground.recording",
})


def undocumented(tree: ast.Module, module: str) -> list[str]:
    """Dotted names of the public functions, classes and methods of ``tree`` without a docstring."""
    missing = []

    def visit(body, prefix: str) -> None:
        for node in body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                if node.name.startswith("_"):
                    continue
                name = f"{prefix}.{node.name}"
                overload = any(isinstance(d, ast.Name) and d.id == "overload" for d in
                               getattr(node, "decorator_list", []))
                if ast.get_docstring(node) is None and not overload:
                    missing.append(name)
                if isinstance(node, ast.ClassDef):
                    visit(node.body, name)

    visit(tree.body, module)
    return missing


def test_the_check_finds_a_missing_docstring():
    tree = ast.parse('def f():\n    """Doc."""\n\ndef g():\n    pass\n\nclass C:\n    def m(self):\n        return 1\n'
                     '    def _p(self):\n        pass\n')
    assert undocumented(tree, "m") == ["m.g", "m.C", "m.C.m"]


def _missing(module: str, path) -> list[str]:
    return undocumented(ast.parse(path.read_text(), str(path.relative_to(REPO))), module)


def test_every_public_function_has_a_docstring():
    missing = []
    for module, path in module_files().items():
        if module not in KNOWN_UNDOCUMENTED:
            missing += _missing(module, path)
    assert not missing, f"{len(missing)} public functions/classes without a docstring: {missing}"


@pytest.mark.parametrize("module", sorted(KNOWN_UNDOCUMENTED))
@pytest.mark.xfail(strict=True, reason="being rewritten elsewhere today; remove from KNOWN_UNDOCUMENTED once documented")
def test_known_undocumented_module_is_documented(module):
    path = module_files().get(module)
    assert path is None or not _missing(module, path)  # a module split away counts as done
