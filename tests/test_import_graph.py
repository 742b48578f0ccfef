"""The library's import graph has no cycle, lazy imports included, and its modules stay small."""

from __future__ import annotations

from pathlib import Path

import grimp

SRC = Path(__file__).resolve().parents[1] / "src" / "safelane"
MAX_LINES = 800


def strongly_connected(edges: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles of ``edges`` (module → modules it imports): Tarjan's components of more than one
    module, iteratively (no recursion limit)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []
    for root in sorted(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    cycles.append(sorted(component))
    return cycles


def test_the_cycle_finder_finds_a_cycle() -> None:
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert strongly_connected(edges) == [["a", "b", "c"]]
    assert strongly_connected({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_in_the_library() -> None:
    graph = grimp.build_graph("safelane", include_external_packages=False)
    edges = {m: set(graph.find_modules_directly_imported_by(m)) for m in graph.modules}
    assert strongly_connected(edges) == []


def test_no_module_over_800_lines_in_the_library() -> None:
    paths = list(SRC.rglob("*.py"))
    assert len(paths) > 60 and SRC / "sim" / "fast" / "kernels.py" in paths
    long = {str(p.relative_to(SRC)): n for p in paths if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert long == {}


def private_imports(root: Path) -> list[str]:
    """``from safelane.x import _name`` anywhere under ``root``: a private helper used across modules."""
    import ast

    found = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("safelane"):
                names = [a.name for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]
                found += [f"{path.relative_to(root)}: {node.module}.{name}" for name in names]
    return found


def test_the_private_import_scan_finds_one(tmp_path: Path) -> None:
    (tmp_path / "m.py").write_text("from safelane.running.training import _helper\nfrom safelane.core import errors\n")
    assert private_imports(tmp_path) == ["m.py: safelane.running.training._helper"]


def test_no_module_imports_another_module_s_private_names() -> None:
    assert private_imports(SRC) == []
