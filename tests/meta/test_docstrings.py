"""Every public function, class and method of fisc_agent, fisc_ground and sim has a docstring.

Public: a name without a leading underscore, at module level or in a public class (methods of a
class nested in a function are not API).  Read from the source (ast), so nothing is imported.
"""

from __future__ import annotations

import ast


from import_graph import REPO, module_files



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
        missing += _missing(module, path)
    assert not missing, f"{len(missing)} public functions/classes without a docstring: {missing}"
