"""The import arrows between the rooms (docs/design.md, "Layout"), checked on the source.

runtime/ (nehad.runtime) is the torch-free runtime: it may import nothing of nehad.* outside
nehad.runtime, and never torch. nehad/ (the training package) never imports the command line
(nehad.cli) or the exporter (nehad.export). Imports inside functions count as much as those at
the top of a module: a lazy import still makes the room depend on the other.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# folder -> the package it is installed as (pyproject.toml, [tool.setuptools] package-dir)
PACKAGES = {"nehad": "nehad", "runtime": "nehad.runtime", "export": "nehad.export",
            "cli": "nehad.cli"}


def module_name(folder: str, path: Path) -> tuple[str, bool]:
    """(dotted module name, is a package __init__) of a source file in `folder`."""
    parts = list(path.relative_to(ROOT / folder).with_suffix("").parts)
    is_package = parts[-1] == "__init__"
    if is_package:
        parts = parts[:-1]
    return ".".join([PACKAGES[folder], *parts]), is_package


def _type_only_nodes(tree) -> set[int]:
    """ids of the nodes inside `if TYPE_CHECKING:` blocks (imports for annotations, never run)."""
    skip = set()
    for node in ast.walk(tree):
        if (isinstance(node, ast.If) and isinstance(node.test, ast.Name)
                and node.test.id == "TYPE_CHECKING"):
            for stmt in node.body:
                skip.update(id(n) for n in ast.walk(stmt))
    return skip


def imported_names(folder: str, path: Path, type_only: bool = True):
    """(line, dotted name) of every import in the file, relative imports resolved; for
    ``from a import b`` both ``a`` and ``a.b`` (b may be a submodule). `type_only=False` leaves
    out the imports under `if TYPE_CHECKING:`."""
    module, is_package = module_name(folder, path)
    tree = ast.parse(path.read_text(), str(path))
    skip = set() if type_only else _type_only_nodes(tree)
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                if not is_package:
                    base = base[:-1]
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            yield node.lineno, target
            for alias in node.names:
                yield node.lineno, f"{target}.{alias.name}"


def runtime_violation(name: str) -> bool:
    top = name.split(".")[0]
    if top == "torch":
        return True
    return top == "nehad" and name != "nehad" and not (
        name == "nehad.runtime" or name.startswith("nehad.runtime."))


def training_violation(name: str) -> bool:
    return any(name == p or name.startswith(p + ".") for p in ("nehad.cli", "nehad.export"))


def violations(folder: str, rule) -> list[str]:
    found = []
    for path in sorted((ROOT / folder).rglob("*.py")):
        for line, name in imported_names(folder, path):
            if rule(name):
                found.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    return sorted(set(found))


def test_the_runtime_imports_only_itself():
    assert violations("runtime", runtime_violation) == []


def test_the_training_package_imports_neither_the_cli_nor_the_exporter():
    assert violations("nehad", training_violation) == []


@pytest.mark.parametrize("source, bad", [
    ("from nehad.data.dnerf import load_dnerf", True),
    ("def f():\n    import torch\n", True),
    ("from .. import trainer", True),           # nehad.trainer, from runtime/x.py
    ("from ..cli import errors", True),
    ("from . import cameras", False),           # nehad.runtime.cameras
    ("from nehad.runtime.ply import read_gaussian_ply", False),
    ("import numpy as np", False),
])
def test_the_rule_sees_lazy_and_relative_imports(tmp_path, monkeypatch, source, bad):
    folder = tmp_path / "runtime"
    folder.mkdir()
    (folder / "x.py").write_text(source)
    monkeypatch.setattr(__import__(__name__), "ROOT", tmp_path)
    assert bool(violations("runtime", runtime_violation)) is bad


def test_no_undefined_names_or_unused_imports():
    """ruff's pyflakes rules (F) over every room: an undefined name is a NameError waiting on
    some path (export_split_model had one on its error path), an unused import a stale arrow."""
    import shutil
    import subprocess

    ruff = shutil.which("ruff")
    if ruff is None:
        pytest.skip("ruff is not installed (it is in the dev extra)")
    rooms = [str(ROOT / f) for f in ("nehad", "export", "runtime", "cli", "tests", "bench")]
    res = subprocess.run([ruff, "check", "--select", "F", "--no-cache", "--output-format",
                          "concise", *rooms], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def import_graph() -> dict[str, set[str]]:
    """module -> the project modules it imports when it runs (at the top or inside functions;
    `if TYPE_CHECKING:` imports are annotations only and left out)."""
    modules = {}
    for folder in PACKAGES:
        for path in sorted((ROOT / folder).rglob("*.py")):
            modules[module_name(folder, path)[0]] = (folder, path)
    graph = {}
    for name, (folder, path) in modules.items():
        deps = set()
        for _, target in imported_names(folder, path, type_only=False):
            parts = target.split(".")
            for k in range(len(parts), 0, -1):  # the longest prefix that is a module
                cand = ".".join(parts[:k])
                if cand in modules:
                    if cand != name:
                        deps.add(cand)
                    break
        graph[name] = deps
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative)."""
    index, low, on_stack, stack, found = {}, {}, set(), [], []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        found.append(sorted(comp))
    return found


def test_no_import_circle():
    assert import_cycles(import_graph()) == []


def test_the_circle_check_finds_a_lazy_circle(tmp_path, monkeypatch):
    (tmp_path / "nehad").mkdir()
    (tmp_path / "nehad" / "a.py").write_text("from nehad.b import f\n")
    (tmp_path / "nehad" / "b.py").write_text("def f():\n    from nehad import a\n")
    (tmp_path / "nehad" / "c.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from nehad import a\n")
    monkeypatch.setattr(__import__(__name__), "ROOT", tmp_path)
    graph = import_graph()
    assert import_cycles(graph) == [["nehad.a", "nehad.b"]]
    assert graph["nehad.c"] == set()


# -- sizes a reader can take in at once (issue 28) ---------------------------------------------

MAX_FUNCTION_LINES = 60
MAX_TRAINER_LINES = 300


def long_functions(folder: Path, limit: int = MAX_FUNCTION_LINES) -> list[str]:
    """'path:line name (N lines)' for every function or method under `folder` longer than
    `limit` lines (its def through its last line, decorators not counted)."""
    out = []
    for path in sorted(folder.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > limit:
                    out.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    return out


def test_no_function_of_the_training_package_is_over_60_lines():
    assert long_functions(ROOT / "nehad") == []
    assert len((ROOT / "nehad" / "trainer.py").read_text().splitlines()) <= MAX_TRAINER_LINES


def test_the_length_check_finds_a_long_function(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(61))
    (tmp_path / "m.py").write_text(f"def short():\n    pass\n\n\ndef long():\n{body}\n")
    global ROOT
    saved, ROOT = ROOT, tmp_path
    try:
        assert long_functions(tmp_path) == ["m.py:5 long (62 lines)"]
    finally:
        ROOT = saved
