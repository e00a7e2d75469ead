"""The library's layout (DESIGN section 2): one subpackage per domain, imports in allowed directions only.

Imports are read from the source (ast), not executed, so the check is cheap and sees
imports inside functions too.
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
TORCH_ALLOWED = {("radar", "differentiable"), ("radar", "gpu"), ("dataset", "readers")}
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


def test_the_library_keeps_its_import_directions():
    assert layout_violations(ROOT) == []


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
