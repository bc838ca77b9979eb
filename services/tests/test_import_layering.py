"""crowdbake's modules import one another in layers: no module reaches itself again through others (a
circle), and the layers below (crowdbake.storage, crowdbake.formats) import nothing from the layers
that use them (crowdbake.stages, crowdbake.bake).

The graph is read from the source with ast, nothing imported: absolute `crowdbake.x` imports and relative
ones, at a module's top or inside a function. `from package import name` is an arrow to the submodule
`name` when there is one, else to the package's __init__. Importing a submodule also runs its parents'
__init__ files, but those are not arrows here: a package whose __init__ hands on its submodules' names
(crowdbake.formats.gltf) would otherwise be a circle with every submodule that imports a sibling.
"""
from __future__ import annotations

import ast
from pathlib import Path

import crowdbake

PACKAGE = "crowdbake"
LOWER_LAYERS = ("crowdbake.storage", "crowdbake.formats")
UPPER_LAYERS = ("crowdbake.stages", "crowdbake.bake")


def module_names(root: Path, package: str = PACKAGE) -> dict[str, Path]:
    """Every module under the package folder `root` by dotted name (a package by its __init__.py)."""
    names = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names[".".join((package, *parts))] = path
    return names


def _imported(node: ast.AST, importer: str, is_package: bool) -> list[str]:
    """The dotted names one import statement brings in: `x.y` for `import x.y`, and for `from base import
    a, b`, `base.a` and `base.b` (each later taken as the submodule when there is one, else as base)."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    if node.level == 0:
        base = node.module or ""
    else:  # relative: level 1 is the importer's own package (an __init__ is its package)
        package = importer.split(".") if is_package else importer.split(".")[:-1]
        base = ".".join([*package[: len(package) - node.level + 1], *([node.module] if node.module else [])])
    return [f"{base}.{alias.name}" for alias in node.names]


def _target(name: str, modules: dict[str, Path]) -> str | None:
    """The module a dotted name lands in: the longest prefix of it that is a module of the package."""
    parts = name.split(".")
    for end in range(len(parts), 0, -1):
        if ".".join(parts[:end]) in modules:
            return ".".join(parts[:end])
    return None


def import_graph(root: Path, package: str = PACKAGE) -> dict[str, set[str]]:
    """module -> the package's modules it imports (itself left out)."""
    modules = module_names(root, package)
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        targets = set()
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for imported in _imported(node, name, path.name == "__init__.py"):
                    targets.add(_target(imported, modules))
        graph[name] = targets - {None, name}
    return graph


def circles(graph: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[set[str]] = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        on_stack.add(module)
        for other in sorted(graph.get(module, ())):
            if other not in index:
                visit(other)
                low[module] = min(low[module], low[other])
            elif other in on_stack:
                low[module] = min(low[module], index[other])
        if low[module] == index[module]:
            component = set()
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.add(member)
                if member == module:
                    break
            if len(component) > 1:
                found.append(component)

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return found


def _within(module: str, packages: tuple[str, ...]) -> bool:
    return any(module == package or module.startswith(package + ".") for package in packages)


def upward_arrows(graph: dict[str, set[str]], lower=LOWER_LAYERS, upper=UPPER_LAYERS) -> list[tuple[str, str]]:
    """(importer, imported) for every import from a lower layer into an upper one."""
    return sorted((a, b) for a, targets in graph.items() if _within(a, lower) for b in targets if _within(b, upper))


def test_the_checker_finds_a_circle_and_an_upward_arrow(tmp_path):
    """A synthetic package: a <-> b through a relative import inside a function, storage importing a
    stage, and a package __init__ that hands on its submodule, which must not count as a circle."""
    files = {
        "__init__.py": "",
        "a.py": "def late():\n    from .b import thing\n",
        "b.py": "import crowdbake.a\n",
        "storage/__init__.py": "",
        "storage/rows.py": "from crowdbake.stages import plan\nfrom ..formats import reader\n",
        "formats/__init__.py": "",
        "formats/reader.py": "",
        "stages/__init__.py": "from .plan import STAGES\n",
        "stages/plan.py": "from crowdbake.stages import helpers\n",
        "stages/helpers.py": "",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    graph = import_graph(tmp_path)
    assert graph["crowdbake.a"] == {"crowdbake.b"} and graph["crowdbake.b"] == {"crowdbake.a"}
    assert graph["crowdbake.storage.rows"] == {"crowdbake.stages.plan", "crowdbake.formats.reader"}
    assert graph["crowdbake.stages"] == {"crowdbake.stages.plan"}
    assert circles(graph) == [{"crowdbake.a", "crowdbake.b"}]
    assert upward_arrows(graph) == [("crowdbake.storage.rows", "crowdbake.stages.plan")]


def test_crowdbake_has_no_import_circle():
    found = circles(import_graph(Path(crowdbake.__file__).parent))
    assert found == [], "modules that import each other: " + "; ".join(" <-> ".join(sorted(c)) for c in found)


def test_storage_and_formats_import_nothing_from_stages_or_bake():
    arrows = upward_arrows(import_graph(Path(crowdbake.__file__).parent))
    assert arrows == [], "imports from a lower layer up: " + ", ".join(f"{a} -> {b}" for a, b in arrows)
