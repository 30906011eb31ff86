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


def imported_names(folder: str, path: Path):
    """(line, dotted name) of every import in the file, relative imports resolved; for
    ``from a import b`` both ``a`` and ``a.b`` (b may be a submodule)."""
    module, is_package = module_name(folder, path)
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
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
