"""The import graph of fisc_agent, fisc_ground and sim, read from the source (ast, nothing imported).

An edge A -> B means module A imports module B anywhere in its code: at the top, or inside a
function (a lazy import is still a dependency of the design), and under ``if TYPE_CHECKING:``
(an annotation names a dependency too: the package has no such import).  ``from P import name`` is an edge to ``P.name`` when that is a
module, else to ``P``.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("fisc_agent", "fisc_ground", "sim")


def module_files(packages=PACKAGES) -> dict[str, Path]:
    """Dotted module name -> file, for every .py of ``packages``."""
    out = {}
    for pkg in packages:
        for path in sorted((REPO / pkg).rglob("*.py")):
            rel = path.relative_to(REPO).with_suffix("")
            parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
            out[".".join(parts)] = path
    return out


def _imports(tree: ast.AST, module: str, is_package: bool) -> list[tuple[str, tuple[str, ...]]]:
    """(imported module, names taken from it) of every import statement."""
    found: list[tuple[str, tuple[str, ...]]] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.Import):
            found.extend((alias.name, ()) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                prefix = ".".join(base + ([node.module] if node.module else []))
            else:
                prefix = node.module or ""
            found.append((prefix, tuple(alias.name for alias in node.names)))
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def import_graph(packages=PACKAGES) -> dict[str, set[str]]:
    """Module -> the project modules it imports (edges inside ``packages`` only)."""
    files = module_files(packages)
    graph: dict[str, set[str]] = {}
    for mod, path in files.items():
        edges = set()
        for prefix, names in _imports(ast.parse(path.read_text(), str(path)), mod, path.name == "__init__.py"):
            targets = [f"{prefix}.{n}" if f"{prefix}.{n}" in files else prefix for n in names] or [prefix]
            edges.update(t for t in targets if t in files and t != mod)
        graph[mod] = edges
    return graph


def cycles(graph: dict[str, set[str]]) -> list[frozenset[str]]:
    """Strongly connected components with more than one module (Tarjan), i.e. the import cycles."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[frozenset[str]] = []
    counter = [0]

    def strong(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(frozenset(comp))

    for v in sorted(graph):
        if v not in index:
            strong(v)
    return out
