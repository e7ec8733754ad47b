"""The diagnosis' modules import one another without a loop (also not through an import inside a function):
each can be read, tested and replaced from the bottom up."""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "src" / "virtualaxis" / "diagnosis"


def _imports(path: Path) -> set[str]:
    """The ``virtualaxis.diagnosis`` modules a module imports anywhere in its code, except under
    ``if TYPE_CHECKING:`` (annotations only, never run)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for b in node.body for n in ast.walk(b))
    out: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module == "virtualaxis.diagnosis":
                out.update(a.name for a in node.names if (PKG / f"{a.name}.py").exists())
            elif node.module.startswith("virtualaxis.diagnosis."):
                out.add(node.module.split(".")[2])
        elif isinstance(node, ast.Import):
            out.update(a.name.split(".")[2] for a in node.names if a.name.startswith("virtualaxis.diagnosis."))
    return out - {path.stem}


def _cycle(graph: dict[str, set[str]]) -> list[str]:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> list[str]:
        state[m] = 1
        stack.append(m)
        for n in sorted(graph.get(m, ())):
            if state.get(n) == 1:
                return stack[stack.index(n):] + [n]
            if n not in state and (found := visit(n)):
                return found
        stack.pop()
        state[m] = 2
        return []

    for m in sorted(graph):
        if m not in state and (found := visit(m)):
            return found
    return []


def test_the_diagnosis_modules_import_one_another_without_a_loop():
    graph = {p.stem: _imports(p) for p in PKG.glob("*.py") if p.stem != "__init__"}
    assert graph["data"] and graph["alignment"], "the import graph was read"
    loop = _cycle(graph)
    assert not loop, " -> ".join(loop)
