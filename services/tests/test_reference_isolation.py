"""No module a bake ships imports a test oracle.

The `reference` package under services/crowdbake (crowdbake.reference:
the float64 and numpy twins the shaders are tested against) is imported only by other reference modules,
the tests and the benchmarks, so the code a real bake runs is the one a reader finds by following its
imports. The scan reads every module's syntax tree: imports at the top, inside functions and relative
ones alike.
"""
from __future__ import annotations

import ast
from pathlib import Path

from repo_paths import REPO_ROOT

SHIPPED_ROOT = REPO_ROOT / "services" / "crowdbake"
ORACLE_PACKAGE = "reference"


def module_name(path: Path, root: Path) -> str:
    """The dotted name of the module at `path` in the package at `root` (an __init__.py names its package)."""
    parts = path.relative_to(root.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_names(tree: ast.Module, module: str, is_package: bool) -> list[tuple[int, str]]:
    """(line, absolute dotted name) of every import in `tree`: `import a.b` gives a.b, `from a import b` a.b,
    relative imports resolved against `module`; string imports (importlib.import_module, __import__) too."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                package = module.split(".") if is_package else module.split(".")[:-1]
                package = package[:len(package) - (node.level - 1)]
                base = ".".join(package + ([base] if base else []))
            found += [(node.lineno, f"{base}.{alias.name}") for alias in node.names]
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            function = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            if function in ("import_module", "__import__") and isinstance(node.args[0].value, str):
                found.append((node.lineno, node.args[0].value))
    return found


def is_oracle(name: str) -> bool:
    return ORACLE_PACKAGE in name.split(".")


def oracle_imports(root: Path) -> list[str]:
    """'<file>:<line> imports <name>' for every import of a reference package by a module outside one."""
    found = []
    for path in sorted(root.rglob("*.py")):
        module = module_name(path, root)
        if is_oracle(module):
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for line, name in imported_names(tree, module, path.name == "__init__.py"):
            if is_oracle(name):
                found.append(f"{path.relative_to(root.parent).as_posix()}:{line} imports {name}")
    return found


def write_package(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_the_scan_finds_every_way_a_shipped_module_reaches_an_oracle(tmp_path):
    """A synthetic package whose shipped modules import its oracle at the top, inside a function, relatively,
    by `from package import reference` and by name: each is found, and nothing else is (an oracle may import
    shipped code and other oracles)."""
    root = tmp_path / "pkg"
    write_package(root, {
        "__init__.py": "",
        "reference/__init__.py": "",
        "reference/oracle.py": "from pkg import shipped\nfrom . import helper\n",
        "reference/helper.py": "import pkg.clean\n",
        "shipped.py": "import numpy\n\n\ndef draw():\n    from pkg.reference import oracle\n    return oracle\n",
        "clean.py": "from pkg import shipped\nfrom pkg.shipped import draw\n",
        "stages/__init__.py": "from .. import reference\n",
        "stages/relative.py": "from ..reference.oracle import shipped\n",
        "stages/by_name.py": "import importlib\n\nORACLE = importlib.import_module('pkg.reference.helper')\n",
        "stages/absolute.py": "import pkg.reference.oracle as oracle\n",
    })
    assert oracle_imports(root) == [
        "pkg/shipped.py:5 imports pkg.reference.oracle",
        "pkg/stages/__init__.py:1 imports pkg.reference",
        "pkg/stages/absolute.py:1 imports pkg.reference.oracle",
        "pkg/stages/by_name.py:3 imports pkg.reference.helper",
        "pkg/stages/relative.py:1 imports pkg.reference.oracle.shipped",
    ]


def test_no_shipped_module_imports_a_reference_package():
    oracles = sorted(path.parent.relative_to(SHIPPED_ROOT).as_posix() for path in SHIPPED_ROOT.rglob(f"{ORACLE_PACKAGE}/__init__.py"))
    assert oracles == ["reference"], "the scan looks at the oracles it is meant to guard"
    assert oracle_imports(SHIPPED_ROOT) == []
