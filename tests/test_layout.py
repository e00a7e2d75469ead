"""The library's layout (DESIGN section 2): one subpackage per domain, imports in allowed directions only.

Imports are read from the source (ast), not executed, so the check is cheap and sees
imports inside functions too. The same imports, module by module, must form no cycle:
imports made only for type checking (under `if TYPE_CHECKING:`) and imports inside
functions count, since they too tie two modules together both ways.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = "meshsar_builder"
ROOT = Path(__file__).resolve().parents[1]
DOMAINS = ("pipeline", "geometry", "radar", "dataset", "trainer", "bench")
# Subpackage -> the subpackages it may import. bench/ and cli.py sit on top and may import anything.
ALLOWED = {
    "pipeline": set(),
    "geometry": {"pipeline"},
    "radar": {"pipeline"},
    "dataset": {"pipeline", "geometry", "radar"},
    "trainer": {"pipeline", "geometry", "radar", "dataset"},
}
# Third-party imports a domain must not take (a geometry user should not load torch), and the
# modules exempted: the differentiable echo, the GPU radar (imported only for a CUDA device)
# and the PyTorch readers.
FORBIDDEN_EXTERNAL = {domain: {"torch"} for domain in ("pipeline", "geometry", "radar", "dataset")}
TORCH_ALLOWED = {("radar", "differentiable"), ("radar", "focused"), ("radar", "gpu"), ("dataset", "readers")}
MAX_LINES = 600


def _imported_modules(tree: ast.AST, module: str, is_package: bool) -> list[tuple[int, str]]:
    """(line, absolute dotted name) of every import in a module, relative ones resolved."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = module.split(".")
                base = parts[: len(parts) - node.level + (1 if is_package else 0)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            # `from meshsar_builder import trainer` imports the subpackage itself
            if name == PACKAGE:
                out += [(node.lineno, f"{PACKAGE}.{alias.name}") for alias in node.names]
            else:
                out.append((node.lineno, name))
    return out


def layout_violations(root: Path) -> list[str]:
    """Every broken import direction under `root` (a checkout holding meshsar_builder/), as 'file:line: why'."""
    problems, edges = [], {}
    for path in sorted((root / PACKAGE).rglob("*.py")):
        rel = path.relative_to(root)
        parts = rel.with_suffix("").parts
        is_package = parts[-1] == "__init__"
        module = ".".join(parts[:-1] if is_package else parts)
        domain = parts[1] if len(parts) > 2 else None  # None: meshsar_builder/__init__.py, cli.py
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(rel))
        for line, name in _imported_modules(tree, module, is_package):
            where = f"{rel}:{line}: imports {name}"
            top = name.split(".")[0]
            if top == "stages":
                problems.append(f"{where}: the library never imports a stage")
                continue
            if domain in FORBIDDEN_EXTERNAL and top == "torch" and (domain, parts[-1]) not in TORCH_ALLOWED:
                problems.append(f"{where}: {domain}/ must not import torch")
            if top != PACKAGE or domain not in ALLOWED:
                continue
            target = name.split(".")[1] if "." in name else None
            if target is None or target == domain or target == "__version__":
                continue
            if target not in ALLOWED[domain]:
                allowed = ", ".join(sorted(ALLOWED[domain])) or "no other subpackage"
                problems.append(f"{where}: {domain}/ may import {allowed}")
            edges.setdefault((domain, target), f"{rel}:{line}")
    for (a, b), where in sorted(edges.items()):
        if a < b and (b, a) in edges:
            problems.append(f"{where} and {edges[(b, a)]}: {a}/ and {b}/ import each other")
    return problems


def module_imports(root: Path) -> dict[str, dict[str, int]]:
    """Module -> {library module it imports: first line}, every import counted (type-only, in functions).

    `from a.b import c` is an import of module a.b.c where that is a module, else of a.b.
    """
    sources = {}
    for path in sorted((root / PACKAGE).rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        is_package = parts[-1] == "__init__"
        sources[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    graph: dict[str, dict[str, int]] = {}
    for module, (path, is_package) in sources.items():
        edges = graph.setdefault(module, {})
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = module.split(".")[: len(module.split(".")) - node.level + (1 if is_package else 0)]
                    name = ".".join(base + ([node.module] if node.module else []))
                else:
                    name = node.module or ""
                names = [f"{name}.{alias.name}" if f"{name}.{alias.name}" in sources else name for alias in node.names]
            else:
                continue
            for name in names:
                while name and name not in sources:  # a name inside a module: the module
                    name = name.rpartition(".")[0]
                if name and name != module:
                    edges.setdefault(name, node.lineno)
    return graph


def find_cycles(graph: dict[str, dict[str, int] | set[str]]) -> list[list[str]]:
    """One cycle [a, b, ..., a] per strongly connected group of nodes that import each other (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[list[str]] = []

    def visit(v: str) -> None:  # recursion depth is bounded by the module count
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1 or v in graph.get(v, ()):
                groups.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    cycles = []
    for group in sorted(groups):
        members, start = set(group), group[0]
        # a shortest path from start back to itself, inside the group (breadth first)
        prev: dict[str, str] = {}
        frontier, seen = [start], {start}
        while frontier and start not in prev:
            nxt = []
            for v in frontier:
                for w in sorted(graph.get(v, ())):
                    if w in members and w == start and start not in prev:
                        prev[start] = v
                    elif w in members and w not in seen:
                        seen.add(w)
                        prev[w] = v
                        nxt.append(w)
            frontier = nxt
        path, v = [start], prev[start]
        while v != start:
            path.append(v)
            v = prev[v]
        cycles.append([start, *reversed(path[1:]), start])
    return cycles


def import_cycles(root: Path) -> list[str]:
    """Every import cycle among the library's modules, as 'a -> b (file:line) -> ... -> a'."""
    graph = module_imports(root)
    out = []
    for cycle in find_cycles(graph):
        steps = [cycle[0]]
        for a, b in zip(cycle, cycle[1:]):
            steps.append(f"{b} ({a.replace('.', '/')}.py:{graph[a][b]})")
        out.append(" -> ".join(steps))
    return out


def test_the_library_keeps_its_import_directions():
    assert layout_violations(ROOT) == []


def test_the_library_has_no_import_cycles():
    assert import_cycles(ROOT) == []


@pytest.mark.parametrize("graph, expected", [
    ({"a": {"b"}, "b": {"c"}, "c": set()}, []),
    ({"a": {"b"}, "b": {"a"}}, [["a", "b", "a"]]),
    ({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}, [["a", "b", "c", "a"]]),
    ({"a": {"a"}}, [["a", "a"]]),
    ({"a": {"b", "c"}, "b": {"a"}, "c": {"d"}, "d": {"c"}}, [["a", "b", "a"], ["c", "d", "c"]]),
    ({"a": {"b", "d"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}, [["a", "d", "a"]]),  # one group, its shortest cycle
])
def test_the_cycle_finder_on_small_graphs(graph, expected):
    assert find_cycles(graph) == expected


@pytest.mark.parametrize("a_imports", [
    "from meshsar_builder.geometry.b import Params\n",
    "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from meshsar_builder.geometry.b import Params\n",
    "def f():\n    from .b import Params\n",
    "from meshsar_builder.geometry import b\n",
])
def test_a_planted_cycle_is_named_even_through_a_type_only_or_local_import(tmp_path, a_imports):
    root = _tree(tmp_path, {"geometry/a.py": a_imports,
                            "geometry/b.py": "import numpy as np\nfrom meshsar_builder.geometry.a import fit\n"})
    cycles = import_cycles(root)
    assert len(cycles) == 1, cycles
    assert cycles[0].startswith("meshsar_builder.geometry.a -> meshsar_builder.geometry.b (meshsar_builder/geometry/a.py:")
    assert cycles[0].endswith("-> meshsar_builder.geometry.a (meshsar_builder/geometry/b.py:2)"), cycles


def test_every_domain_is_a_documented_light_subpackage():
    for domain in DOMAINS:
        init = ROOT / PACKAGE / domain / "__init__.py"
        tree = ast.parse(init.read_text(encoding="utf-8"))
        doc = ast.get_docstring(tree)
        assert doc and "import" in doc.lower(), f"{init}: the docstring must say what lives here and what it may import"
        assert not [n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))], f"{init}: keep it light, no imports"


def test_no_module_grows_past_the_limit():
    long = [f"{p.relative_to(ROOT)}: {n} lines" for p in sorted((ROOT / PACKAGE).rglob("*.py"))
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_LINES]
    assert long == []


def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    for name, text in {**{f"{d}/__init__.py": '"""x; imports nothing."""\n' for d in DOMAINS}, **files}.items():
        path = tmp_path / PACKAGE / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    (tmp_path / PACKAGE / "__init__.py").write_text("")
    return tmp_path


@pytest.mark.parametrize("files, expected", [
    ({"geometry/bad.py": "from meshsar_builder.trainer import losses\n"},
     "meshsar_builder/geometry/bad.py:1: imports meshsar_builder.trainer: geometry/ may import pipeline"),
    ({"pipeline/bad.py": "def f():\n    from ..radar import echo\n"},
     "meshsar_builder/pipeline/bad.py:2: imports meshsar_builder.radar: pipeline/ may import no other subpackage"),
    ({"radar/bad.py": "from meshsar_builder import dataset\n"},
     "meshsar_builder/radar/bad.py:1: imports meshsar_builder.dataset: radar/ may import pipeline"),
    ({"dataset/bad.py": "import stages.radar\n"},
     "meshsar_builder/dataset/bad.py:1: imports stages.radar: the library never imports a stage"),
    ({"geometry/bad.py": "import torch\n"},
     "meshsar_builder/geometry/bad.py:1: imports torch: geometry/ must not import torch"),
])
def test_a_planted_violation_is_named(tmp_path, files, expected):
    assert layout_violations(_tree(tmp_path, files)) == [expected]


def test_two_subpackages_importing_each_other_are_named(tmp_path):
    root = _tree(tmp_path, {"dataset/a.py": "from meshsar_builder.trainer.model import X\n",
                            "trainer/b.py": "from meshsar_builder.dataset.readers import Y\n"})
    problems = layout_violations(root)
    assert any("dataset/ and trainer/ import each other" in p for p in problems), problems
    assert any(p.startswith("meshsar_builder/dataset/a.py:1: imports meshsar_builder.trainer.model: dataset/ may import")
               for p in problems), problems


def test_bench_and_cli_may_import_anything(tmp_path):
    root = _tree(tmp_path, {"bench/x.py": "from meshsar_builder.trainer import train\nimport torch\n",
                            "cli.py": "from meshsar_builder.trainer.train import train\n"})
    assert layout_violations(root) == []
